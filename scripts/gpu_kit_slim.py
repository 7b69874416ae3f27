"""Slims a wheel: drops the files that the GPU checks never read, rewrites RECORD.

Used by ``scripts/gpu_kit.py`` (``make gpu-kit``) to fit mani_skill and sapien,
with everything else the accelerator machine lacks, into carries of at most
60 MiB. The result is still a wheel that ``pip install --no-deps --target``
installs: same name and version, RECORD lists exactly the files kept, and
``<name>.dist-info/SLIMMED.txt`` says what was dropped and why.

The kit runs the GPU checks (``tests/gpu``, ``benchmarks/bench_gpu.py``: PushCube-v1 and
MS-CartpoleBalance-v1) and the whole CPU suite (``scripts/gpu_check.py``), so every asset
that the suite's tasks open stays. Those tasks are PickCube-v1, PushCube-v1 (and the test
tasks registered on it), PullCube-v1, StackCube-v1, MS-CartpoleBalance-v1,
TwoRobotPickCube-v1 (two ``panda_wristcam``: the RealSense D415 mesh), RotateValveLevel0-v1
(the D'Claw) and DrawTriangle-v1 (``panda_stick``); PickSingleYCB-v1 and AnymalC-Reach-v1
appear only as tasks whose assets are missing. The files they open were listed with
``strace -f -e trace=openat,stat`` while each task was made with ``obs_mode="state_dict"``
and ``"rgb"``, reset, stepped and rendered on the CPU sim (2026-11-26, mani_skill 3.0.1).

What is dropped (``SLIM_RULES``), and why it is safe for those checks:

- mani_skill: the environment map (no Python code references it), every
  robot's assets but the Panda's and the D'Claw's files above (the Panda:
  ``panda_v2`` / ``panda_v3`` / ``panda_stick`` URDFs with ``franka_description``
  meshes; CartpoleBalance is an MJCF file under ``envs/tasks/control/assets``),
  the Panda folder's other camera meshes (D435, plug) and Sciurus17 meshes
  (mobile Pandas), the ReplicaCAD / kitchen-counter scene assets, an unused 2k
  floor texture and the ManiSkill2 scene mesh. All Python modules stay, so every
  task still registers; tasks that need a dropped asset fail when they are made.
- sapien: C++ headers, the macOS Vulkan loader and the active-light patterns
  of SAPIEN's stereo depth sensor (``sapien.sensor``; ManiSkill's state
  observations do not use it). The OpenImageDenoise libraries stay: SAPIEN's
  renderer library links them.

Usage: ``python3 scripts/gpu_kit_slim.py IN.whl OUT_DIR`` (the rules are picked
by the wheel's distribution name; a wheel without rules is copied unchanged).
"""

from __future__ import annotations

import base64
import fnmatch
import hashlib
import os
import sys
import zipfile

# distribution name -> list of (fnmatch pattern over archive paths, reason); a file is
# dropped when it matches a pattern and no KEEP pattern.
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
    "sapien": [
        ("sapien/include/*", "C++ headers"),
        ("sapien/vulkan_library/*.dylib", "macOS Vulkan loader"),
        ("sapien/sensor/assets/patterns/*", "stereo depth sensor light patterns (sapien.sensor only)"),
    ],
}
KEEP: dict[str, list[str]] = {
    # Python sources of scene builders stay: mani_skill imports them when it registers tasks.
    "mani_skill": [
        "*.py",
        "mani_skill/assets/robots/panda/*.urdf",
        "mani_skill/assets/robots/panda/*.srdf",
        "mani_skill/assets/robots/panda/franka_description/*",
        # panda_wristcam (TwoRobotPickCube-v1): the wrist camera's mesh.
        "mani_skill/assets/robots/panda/realsense2_description/meshes/d415.stl",
        # RotateValveLevel0-v1: the D'Claw's URDF, collision meshes and the visual meshes it names.
        "mani_skill/assets/robots/dclaw/dclaw_gripper_glb.urdf",
        "mani_skill/assets/robots/dclaw/meshes/collision/*",
        "mani_skill/assets/robots/dclaw/meshes/visual/*.glb",
    ],
    "sapien": ["*.py"],
}


def _record_hash(data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"sha256={digest}"


def dist_name(wheel_path: str) -> str:
    return os.path.basename(wheel_path).split("-")[0].lower().replace("-", "_")


def reason_to_drop(name: str, path: str) -> str | None:
    rules = SLIM_RULES.get(name, [])
    if any(fnmatch.fnmatchcase(path, k) for k in KEEP.get(name, [])):
        return None
    for pattern, reason in rules:
        if fnmatch.fnmatchcase(path, pattern):
            return reason
    return None


def slim(src: str, out_dir: str) -> str:
    """Writes the slimmed wheel into ``out_dir`` (same file name) and returns its path."""
    name = dist_name(src)
    os.makedirs(out_dir, exist_ok=True)
    dst = os.path.join(out_dir, os.path.basename(src))
    tmp = dst + ".part"
    dropped: dict[str, list[int]] = {}
    with zipfile.ZipFile(src) as zin:
        infos = zin.infolist()
        record_name = next(i.filename for i in infos if i.filename.endswith(".dist-info/RECORD"))
        dist_info = record_name.rsplit("/", 1)[0]
        kept_rows: list[str] = []
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
            for info in infos:
                if info.filename == record_name or info.is_dir():
                    continue
                reason = reason_to_drop(name, info.filename)
                if reason is not None:
                    n_bytes = dropped.setdefault(reason, [0, 0])
                    n_bytes[0] += 1
                    n_bytes[1] += info.file_size
                    continue
                data = zin.read(info)
                out = zipfile.ZipInfo(info.filename, date_time=info.date_time)
                out.external_attr = info.external_attr  # keeps the executable bit of .so files
                out.compress_type = zipfile.ZIP_DEFLATED
                zout.writestr(out, data, compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
                kept_rows.append(f"{info.filename},{_record_hash(data)},{len(data)}")
            if dropped:
                lines = [f"Slimmed by maniskill_torchrl scripts/gpu_kit_slim.py from {os.path.basename(src)}.", ""]
                for reason, (n, size) in sorted(dropped.items()):
                    lines.append(f"dropped {n} files, {size / 2**20:.1f} MiB: {reason}")
                note = ("\n".join(lines) + "\n").encode()
                note_name = f"{dist_info}/SLIMMED.txt"
                zout.writestr(
                    zipfile.ZipInfo(note_name, date_time=(2020, 1, 1, 0, 0, 0)),
                    note,
                    compress_type=zipfile.ZIP_DEFLATED,
                )
                kept_rows.append(f"{note_name},{_record_hash(note)},{len(note)}")
            kept_rows.append(f"{record_name},,")
            zout.writestr(
                zipfile.ZipInfo(record_name, date_time=(2020, 1, 1, 0, 0, 0)),
                ("\n".join(kept_rows) + "\n").encode(),
                compress_type=zipfile.ZIP_DEFLATED,
            )
    os.replace(tmp, dst)
    before, after = os.path.getsize(src), os.path.getsize(dst)
    print(f"slim {os.path.basename(src)}: {before / 2**20:.1f} MiB -> {after / 2**20:.1f} MiB")
    for reason, (n, size) in sorted(dropped.items()):
        print(f"    dropped {n:4d} files {size / 2**20:6.1f} MiB unpacked: {reason}")
    return dst


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__)
        return 2
    slim(argv[0], argv[1])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
