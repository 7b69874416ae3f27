"""Slims the mani_skill and sapien wheels of the GPU kit (scripts/gpu_kit.py) to what the checks open.

Still needed: a device carry holds 64 MiB with the repository; these wheels are 97 + 49 MiB, slimmed 18 + 39 MiB.

    python3 scripts/gpu_kit_slim.py IN.whl OUT_DIR        # the same wheel, less the files SLIM_RULES drop
    .venv/bin/python scripts/gpu_kit_slim.py --verify [CACHE KIT]  # the suite's tasks, slimmed wheels, CPU sim

The result installs with `pip install --no-deps --target`: same name and version, RECORD lists what was kept,
<name>.dist-info/SLIMMED.txt what was dropped and why. Every asset the suite's tasks open stays: PickCube-v1,
PushCube-v1, PullCube-v1, StackCube-v1, MS-CartpoleBalance-v1, TwoRobotPickCube-v1 (panda_wristcam: the D415
mesh), RotateValveLevel0-v1 (the D'Claw), DrawTriangle-v1 (panda_stick); listed with `strace -f -e
trace=openat,stat` while each was made (state_dict, rgb), reset, stepped and rendered (2026-11-26, mani_skill
3.0.1). All Python modules stay, so every task still registers; one that needs a dropped asset fails when made.
"""

from __future__ import annotations

import base64
import fnmatch
import glob
import hashlib
import os
import subprocess
import sys
import tempfile
import zipfile

# distribution -> (fnmatch pattern over archive paths, reason); a file is dropped when it matches one and no KEEP.
SLIM_RULES: dict[str, list[tuple[str, str]]] = {
    "mani_skill": [
        ("mani_skill/assets/environment_maps/*", "environment map: not referenced by any code"),
        ("mani_skill/assets/maniskill2-scene-2.glb", "ManiSkill2 scene mesh: unused by the checked tasks"),
        ("mani_skill/assets/robots/*", "robot assets other than the Panda's and the D'Claw's"),
        ("mani_skill/assets/robots/panda/realsense2_description/*", "camera meshes other than the D415"),
        ("mani_skill/assets/robots/panda/sciurus17_description/*", "Sciurus17 meshes (mobile Panda only)"),
        ("mani_skill/utils/scene_builder/replicacad/*", "ReplicaCAD scene assets (downloaded scenes)"),
        ("mani_skill/utils/scene_builder/kitchen_counter/*", "kitchen-counter scene assets"),
        ("mani_skill/utils/building/assets/floor_tiles_06_diff_2k_aligned.png", "2k floor texture: not referenced"),
    ],
    "sapien": [  # the OpenImageDenoise libraries stay: SAPIEN's renderer library links them
        ("sapien/include/*", "C++ headers"),
        ("sapien/vulkan_library/*.dylib", "macOS Vulkan loader"),
        ("sapien/sensor/assets/patterns/*", "stereo depth sensor light patterns (sapien.sensor only)"),
    ],
}
KEEP: dict[str, list[str]] = {
    "mani_skill": [
        "*.py",  # scene builders' sources too: mani_skill imports them when it registers tasks
        "mani_skill/assets/robots/panda/*.urdf",
        "mani_skill/assets/robots/panda/*.srdf",
        "mani_skill/assets/robots/panda/franka_description/*",
        "mani_skill/assets/robots/panda/realsense2_description/meshes/d415.stl",  # panda_wristcam
        "mani_skill/assets/robots/dclaw/dclaw_gripper_glb.urdf",  # RotateValveLevel0-v1
        "mani_skill/assets/robots/dclaw/meshes/collision/*",
        "mani_skill/assets/robots/dclaw/meshes/visual/*.glb",
    ],
    "sapien": ["*.py"],
}
VERIFY = r"""
import sys, warnings
warnings.filterwarnings("ignore")
import gymnasium as gym, mani_skill, sapien, mani_skill.envs
for mod in (mani_skill, sapien):
    assert mod.__file__.startswith(sys.argv[1]), f"{mod.__name__} from {mod.__file__}"
for env_id in ("PushCube-v1", "MS-CartpoleBalance-v1", "PickCube-v1", "PullCube-v1", "StackCube-v1",
               "TwoRobotPickCube-v1", "RotateValveLevel0-v1", "DrawTriangle-v1"):
    for obs_mode in ("state", "rgb"):
        env = gym.make(env_id, num_envs=1, obs_mode=obs_mode, render_mode="rgb_array", sim_backend="physx_cpu")
        env.reset(seed=0)
        for _ in range(3):
            env.step(env.action_space.sample())
        env.render()
        env.close()
    print(f"gpu-kit:   {env_id}: state and rgb, reset, step, render: ok")
"""


def reason_to_drop(name: str, path: str) -> str | None:
    if any(fnmatch.fnmatchcase(path, k) for k in KEEP.get(name, [])):
        return None
    return next((reason for pattern, reason in SLIM_RULES.get(name, []) if fnmatch.fnmatchcase(path, pattern)), None)


def slim(src: str, out_dir: str) -> str:
    """Writes the slimmed wheel into out_dir (same file name) and returns its path."""
    name, dst = os.path.basename(src).split("-")[0].lower(), os.path.join(out_dir, os.path.basename(src))
    os.makedirs(out_dir, exist_ok=True)
    dropped: dict[str, list[int]] = {}
    rows: list[str] = []

    def add(zout: zipfile.ZipFile, info: zipfile.ZipInfo, data: bytes, level: int | None = None) -> None:
        zout.writestr(info, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=level)
        digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
        rows.append(f"{info.filename},sha256={digest},{len(data)}")

    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst + ".part", "w") as zout:
        record = next(i.filename for i in zin.infolist() if i.filename.endswith(".dist-info/RECORD"))
        for info in zin.infolist():
            if info.filename == record or info.is_dir():
                continue
            if (reason := reason_to_drop(name, info.filename)) is not None:
                dropped.setdefault(reason, [0, 0])[0] += 1
                dropped[reason][1] += info.file_size
                continue
            out = zipfile.ZipInfo(info.filename, date_time=info.date_time)
            out.external_attr = info.external_attr  # keeps the executable bit of .so files
            add(zout, out, zin.read(info), level=9)
        lines = [f"dropped {n} files, {size / 2**20:.1f} MiB: {why}" for why, (n, size) in sorted(dropped.items())]
        if dropped:
            note = f"Slimmed by maniskill_torchrl scripts/gpu_kit_slim.py from {os.path.basename(src)}.\n\n"
            info = zipfile.ZipInfo(record.rsplit("/", 1)[0] + "/SLIMMED.txt", date_time=(2020, 1, 1, 0, 0, 0))
            add(zout, info, (note + "\n".join(lines) + "\n").encode())
        rows.append(f"{record},,")
        info = zipfile.ZipInfo(record, date_time=(2020, 1, 1, 0, 0, 0))
        zout.writestr(info, ("\n".join(rows) + "\n").encode(), compress_type=zipfile.ZIP_DEFLATED)
    os.replace(dst + ".part", dst)
    print(f"slim {os.path.basename(src)}: {os.path.getsize(src) / 2**20:.1f} -> {os.path.getsize(dst) / 2**20:.1f} MiB")
    print("".join(f"    {line}\n" for line in lines), end="")
    return dst


def verify(cache: str = os.path.expanduser("~/.cache/maniskill_torchrl/gpu-kit"), kit: str = ".gpu") -> int:
    """The kit's slimmed mani_skill with sapien slimmed for this Python, from a --target folder, on the CPU sim."""
    tag = f"cp{sys.version_info[0]}{sys.version_info[1]}"
    vdir = os.path.join(cache, f"verify-{tag}")
    if not glob.glob(f"{vdir}/in/sapien-3.0.3-{tag}-*.whl"):
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "-d",
                        f"{vdir}/in", "sapien==3.0.3"], check=True)  # fmt: skip
    sapien = slim(glob.glob(f"{vdir}/in/sapien-3.0.3-{tag}-*.whl")[0], f"{vdir}/slim")
    with tempfile.TemporaryDirectory() as target:
        pip = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile", "--target"]
        subprocess.run(pip + [target, sapien, *glob.glob(f"{kit}/kit*/wheels/mani_skill-*.whl")], check=True)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [target, os.environ.get("PYTHONPATH")])))
        rc = subprocess.run([sys.executable, "-c", VERIFY, target], env=env).returncode
    print("gpu-kit: verify: " + ("ok" if rc == 0 else "FAILED"))
    return rc


if __name__ == "__main__":
    if sys.argv[1:2] == ["--verify"]:
        sys.exit(verify(*sys.argv[2:4]))
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    slim(*sys.argv[1:])
