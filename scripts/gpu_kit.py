"""Builds the GPU kit (`make gpu-kit`): what the accelerator machine lacks for scripts/gpu_check.py, as
carries of the device tool (benchmarks/README.md, "GPU kit").

    python3 scripts/gpu_kit.py            # fill .gpu/ (idempotent: downloads cached in --cache)
    python3 scripts/gpu_kit.py --verify   # then make, step and render the suite's tasks with the slimmed wheels

The machine: Python 3.12, torch 2.11 preinstalled, no registry. Into the git-ignored .gpu/, one folder
per carry (each at most 64 MiB with the repository): cp312 wheels of the pins below (mani_skill and
sapien slimmed by gpu_kit_slim.py: one carry holds 64 MiB and they unpack to 148 MiB), the project's
own wheel (its console script), Debian's Vulkan / GL loaders and libX11 .debs (in .gpu/kit), and
SAPIEN's PhysX GPU library as .gpu/physx when this machine has it. MANIFEST.txt lists each part.
"""

from __future__ import annotations

import argparse
import datetime
import glob
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MIB = 2**20
# What the machine lacks, resolved for cp312 from the project's pins (installed there with --no-deps).
PINS = """torchrl==0.14.1 tensordict==0.14.3 pyvers==0.2.3 hoptorch==0.1.4 orjson==3.13.0 importlib-metadata==10.2.0
lazy-importer==0.1.0 gymnasium==1.4.0 farama-notifications==0.0.6 sapien==3.0.3 pyperclip==1.11.0
importlib-resources==7.1.0 transforms3d==0.4.2 mani-skill==3.0.1 dacite==1.9.2 gitpython==3.2.1 gitdb==4.0.12
smmap==5.0.3 trimesh==5.2.0 defusedxml==0.7.1 tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.0
pytorch-kinematics==0.7.6 arm-pytorch-utilities==0.5.0 pytorch-seed==0.2.0 ipython==9.18.1
ipython-pygments-lexers==1.1.1 traitlets==5.16.1 matplotlib-inline==0.2.2 prompt-toolkit==3.0.53 wcwidth==0.9.4
stack-data==0.6.3 executing==2.3.0 asttokens==3.0.2 pure-eval==0.2.4 pexpect==4.9.0 ptyprocess==0.7.0
imageio-ffmpeg==0.7.0""".split()  # imageio-ffmpeg 0.7.0: 28 MiB (the suite writes .mp4); 0.8.x is 65 MiB
EXCLUDED = [
    "mplib==0.1.1 + toppra: mani_skill's motion-planning examples only (11.5 + 0.9 MiB)",
    "jedi + parso: IPython's tab completion only (4.8 MiB)",
    "opencv-python: the machine has opencv-python-headless (same cv2 module)",
    "torch, triton, nvidia-*, cuda-*: preinstalled there (torch 2.11.0+cu130)",
]
DEBS = {
    "gl": "libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2",
    "x11": "libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0",
}
PLATFORMS = ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"]
VENV_PY = str(ROOT / ".venv/bin/python") if (ROOT / ".venv/bin/python").exists() else sys.executable

VERIFY = r"""
import os, sys, warnings
warnings.filterwarnings("ignore")
import gymnasium as gym, mani_skill, sapien
import mani_skill.envs  # noqa: F401
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


def log(msg: str) -> None:
    print(f"gpu-kit: {msg}", flush=True)


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "_", name).lower()


def pip_download(dest: Path, pins: list[str], *extra: str) -> None:
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "-d", str(dest)]
    subprocess.run(cmd + list(extra) + pins, check=True)


def wheels(cache: Path) -> list[Path]:
    """The pinned wheels (slimmed where a slim copy exists) and the project's wheel."""
    want = {norm(p.split("==")[0]): p.split("==")[1] for p in PINS}
    have = {}
    for f in sorted((cache / "wheels").glob("*.whl")):
        name, ver = norm(f.name.split("-")[0]), f.name.split("-")[1]
        if want.get(name) == ver:
            have[name] = cache / "slim" / f.name if (cache / "slim" / f.name).exists() else f
    missing = [f"{n}=={v}" for n, v in want.items() if n not in have]
    if missing:
        log(f"downloading {len(missing)} cp312 wheels into {cache / 'wheels'}")
        plat = [a for p in PLATFORMS for a in ("--platform", p)]
        pip_download(cache / "wheels", missing, "--python-version", "3.12", "--implementation", "cp", *plat)
        return wheels(cache)
    for name in ("mani_skill", "sapien"):  # slim again when the wheel or the rules changed
        src = next((cache / "wheels").glob(f"{name}-{want[name]}-*.whl"))
        dst = cache / "slim" / src.name
        if not dst.exists() or dst.stat().st_mtime < max(
            src.stat().st_mtime, Path(__file__).with_name("gpu_kit_slim.py").stat().st_mtime
        ):
            subprocess.run(
                [sys.executable, str(ROOT / "scripts/gpu_kit_slim.py"), str(src), str(cache / "slim")], check=True
            )
            have[name] = dst
    # the project, built from the working tree each time (pure Python; .venv has setuptools)
    shutil.rmtree(cache / "project", ignore_errors=True)
    had_build = (ROOT / "build").exists()
    subprocess.run([VENV_PY, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index", "-w",
                    str(cache / "project"), str(ROOT)], check=True, cwd=ROOT)  # fmt: skip
    if not had_build:
        shutil.rmtree(ROOT / "build", ignore_errors=True)
    return sorted(have.values()) + sorted((cache / "project").glob("*.whl"))


def debs(cache: Path) -> dict[str, list[Path]]:
    """Debian bookworm's amd64 .debs, with apt lists of our own (the device README's recipe)."""
    out = {}
    for folder, pkgs in DEBS.items():
        d = cache / folder
        d.mkdir(parents=True, exist_ok=True)
        want = [p for p in pkgs.split() if not list(d.glob(f"{p}_*.deb"))]
        if want:
            o = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64", f"-oDir::State::Lists={cache}/apt-lists",
                 "-oAPT::Sandbox::User=root", "-qq"]  # fmt: skip
            (cache / "apt-lists/partial").mkdir(parents=True, exist_ok=True)
            if not (cache / "apt-lists/.updated").exists():
                subprocess.run(["apt-get", *o, "update"], check=True)
                (cache / "apt-lists/.updated").touch()
            log(f"downloading {' '.join(want)}")
            subprocess.run(["apt-get", *o, "download", *want], check=True, cwd=d)
            for f in d.glob("*.deb"):  # names the carry accepts: epochs come url-escaped (2%3a1.8.4)
                f.rename(d / re.sub(r"[^A-Za-z0-9._-]", "_", f.name.replace("%3a", "_")))
        out[folder] = sorted(d.glob("*.deb"))
    return out


def repo_bytes() -> int:
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True).stdout.split("\0")  # fmt: skip
    return sum((ROOT / f).stat().st_size for f in files if f and (ROOT / f).is_file())


def assemble(whls: list[Path], debs_: dict[str, list[Path]], limit: int) -> list[dict]:
    """Fewest parts under limit: each wheel, biggest first, into the part with the fewest bytes (the .debs
    in the first, .gpu/kit)."""
    deb_bytes = sum(f.stat().st_size for fs in debs_.values() for f in fs)
    for k in range(1, 10):
        parts = [{"wheels": [], "bytes": deb_bytes if i == 0 else 0} for i in range(k)]
        for w in sorted(whls, key=lambda w: w.stat().st_size, reverse=True):
            part = min(parts, key=lambda p: p["bytes"])
            part["wheels"].append(w)
            part["bytes"] += w.stat().st_size
        if all(p["bytes"] <= limit for p in parts):
            return parts
    sys.exit(f"gpu-kit: ERROR: no split fits {limit / MIB:.1f} MiB per part")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", default=os.path.expanduser("~/.cache/maniskill_torchrl/gpu-kit"))
    p.add_argument("--part-mib", type=float, default=60, help="most MiB in one part (60)")
    p.add_argument("--slack-mib", type=float, default=4, help="MiB kept free per command for the repo's growth (4)")
    p.add_argument("--no-debs", action="store_true", help="without the .debs (apt-get needed)")
    p.add_argument("--physx", default=None, help="folder of libPhysXGpu_64.so (default ~/.sapien/physx/<version>)")
    p.add_argument(
        "--verify", action="store_true", help="then make, step and render the suite's tasks with the slim wheels"
    )
    args = p.parse_args()
    cache = Path(args.cache)
    for d in ("wheels", "slim"):
        (cache / d).mkdir(parents=True, exist_ok=True)
    whls = wheels(cache)
    debs_ = {} if args.no_debs else debs(cache)
    repo = repo_bytes()
    limit = int(min(args.part_mib * MIB, 64 * MIB - repo - args.slack_mib * MIB))
    parts = assemble(whls, debs_, limit)
    kit = ROOT / ".gpu"
    shutil.rmtree(kit, ignore_errors=True)
    names = ["kit" if i == 0 else f"kit{i + 1}" for i in range(len(parts))]
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    for i, (name, part) in enumerate(zip(names, parts)):
        folder = kit / name
        (folder / "wheels").mkdir(parents=True)
        for w in part["wheels"]:
            shutil.copy2(w, folder / "wheels" / w.name)
        for sub, fs in debs_.items() if i == 0 else []:
            (folder / sub).mkdir()
            for f in fs:
                shutil.copy2(f, folder / sub / f.name)
        (folder / "PARTS.txt").write_text("".join(f"{n}\n" for n in names))
        files = sorted(f for f in folder.rglob("*") if f.is_file())
        listing = "".join(f"  {f.stat().st_size / MIB:8.2f} MiB  {f.relative_to(folder)}\n" for f in files)
        (folder / "MANIFEST.txt").write_text(
            f"maniskill_torchrl GPU kit, part {name}, built {when} by scripts/gpu_kit.py, for python3.12, torch 2.11;\n"
            "installed by scripts/gpu_check.py (pip install --no-index --no-deps --target).\n"
            "On torch 2.11 torchrl 0.14.1's C extension (built for torch 2.14) does not load: prioritized replay is\n"
            "unavailable there; the env, transforms, Collector, PPO and SAC with uniform replay work.\n"
            "Left out on purpose:\n"
            + "".join(f"  - {e}\n" for e in EXCLUDED)
            + "Slimmed: mani_skill, sapien (*.dist-info/SLIMMED.txt)\n\n"
            + listing
        )
    res = subprocess.run(
        [VENV_PY, "-c", "import sapien.physx as p; print(p.version())"], capture_output=True, text=True
    )
    version = res.stdout.strip() or "105.1-physx-5.3.1.patch0"
    physx = Path(args.physx or Path.home() / ".sapien/physx" / version)
    if (physx / "libPhysXGpu_64.so").exists():
        shutil.copytree(physx, kit / "physx")
        (kit / "physx/VERSION").write_text(version + "\n")
        log(f"PhysX GPU library {version} from {physx}: carry .gpu/physx beside .gpu/kit")
    else:
        log(f"NOTE: no PhysX GPU library in {physx}: the GPU sim cannot start on the machine (SAPIEN downloads it")
        log(f"      from GitHub, release {version}, linux-so.zip); unzip it there (or --physx DIR) and rerun")
    status = 0
    for folder in sorted(kit.iterdir()):
        size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
        n_whl, n_deb = len(list(folder.glob("wheels/*.whl"))), len(list(folder.glob("*/*.deb")))
        log(f"  {'.gpu/' + folder.name:10s} {size / MIB:6.1f} MiB ({n_whl} wheels, {n_deb} .debs) + repo "
            f"{repo / MIB:.1f} MiB = {(size + repo) / MIB:.1f} MiB per run")  # fmt: skip
        status |= size + repo > 64 * MIB
    if status:
        sys.exit("gpu-kit: ERROR: a part exceeds 64 MiB with the repository")
    if args.verify:
        return verify(cache, kit)
    return 0


def verify(cache: Path, kit: Path) -> int:
    """The slimmed mani_skill with a slimmed sapien for .venv's Python, from a --target folder, on the CPU sim."""
    tag = subprocess.run([VENV_PY, "-c", "import sys; print(f'cp{sys.version_info[0]}{sys.version_info[1]}')"],
                         capture_output=True, text=True).stdout.strip()  # fmt: skip
    vdir = cache / f"verify-{tag}"
    if not glob.glob(str(vdir / f"in/sapien-3.0.3-{tag}-*.whl")):
        subprocess.run([VENV_PY, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "-d",
                        str(vdir / "in"), "sapien==3.0.3"], check=True)  # fmt: skip
    src = glob.glob(str(vdir / f"in/sapien-3.0.3-{tag}-*.whl"))[0]
    subprocess.run(
        [sys.executable, str(ROOT / "scripts/gpu_kit_slim.py"), src, str(vdir / "slim")],
        check=True,
        capture_output=True,
    )
    with tempfile.TemporaryDirectory() as target:
        slim = glob.glob(str(vdir / "slim/sapien-*.whl")) + glob.glob(str(kit / "kit*/wheels/mani_skill-*.whl"))
        pip = [VENV_PY, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-compile", "--target", target]
        subprocess.run(pip + slim, check=True)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [target, os.environ.get("PYTHONPATH")])))
        rc = subprocess.run([VENV_PY, "-c", VERIFY, target], env=env).returncode
    log("verify: " + ("ok" if rc == 0 else "FAILED"))
    return rc


if __name__ == "__main__":
    sys.exit(main())
