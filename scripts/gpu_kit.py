"""Builds the GPU kit (`make gpu-kit`, idempotent, downloads cached in --cache): what the accelerator machine
(Python 3.12, torch 2.11, no registry) lacks for scripts/gpu_check.py, in the git-ignored .gpu/, one folder per
device carry (benchmarks/README.md, "GPU kit"), each with its MANIFEST.txt; .gpu/physx when this machine has SAPIEN's
PhysX GPU library. Check the slimmed wheels with `.venv/bin/python scripts/gpu_kit_slim.py --verify`.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT, MIB = Path(__file__).resolve().parents[1], 2**20
SLIM = str(ROOT / "scripts/gpu_kit_slim.py")
VENV_PY = str(ROOT / ".venv/bin/python") if (ROOT / ".venv/bin/python").exists() else sys.executable
# What the machine lacks, resolved for cp312 from the project's pins (installed there with --no-deps).
PINS = """torchrl==0.14.1 tensordict==0.14.3 pyvers==0.2.3 hoptorch==0.1.4 orjson==3.13.0 importlib-metadata==10.2.0
lazy-importer==0.1.0 gymnasium==1.4.0 farama-notifications==0.0.6 sapien==3.0.3 pyperclip==1.11.0 dacite==1.9.2
importlib-resources==7.1.0 transforms3d==0.4.2 mani-skill==3.0.1 gitpython==3.2.1 gitdb==4.0.12 smmap==5.0.3
trimesh==5.2.0 defusedxml==0.7.1 tyro==1.0.17 docstring-parser==0.18.0 typeguard==4.6.0 pytorch-kinematics==0.7.6
arm-pytorch-utilities==0.5.0 pytorch-seed==0.2.0 ipython==9.18.1 ipython-pygments-lexers==1.1.1 traitlets==5.16.1
matplotlib-inline==0.2.2 prompt-toolkit==3.0.53 wcwidth==0.9.4 stack-data==0.6.3 executing==2.3.0 asttokens==3.0.2
pure-eval==0.2.4 pexpect==4.9.0 ptyprocess==0.7.0 imageio-ffmpeg==0.7.0""".split()  # ffmpeg 0.8.x: 65 MiB, 0.7.0: 28
DEBS = {"gl": "libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2",
        "x11": "libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0"}  # fmt: skip
MANIFEST = """maniskill_torchrl GPU kit, part {name}, built {when} by scripts/gpu_kit.py, for python3.12, torch 2.11;
installed by scripts/gpu_check.py (pip install --no-index --no-deps --target). Left out: mplib + toppra (motion
planning, 12.4 MiB), jedi + parso (tab completion, 4.8 MiB), opencv-python (the machine has the headless one), torch,
triton, nvidia-*, cuda-* (preinstalled: torch 2.11.0+cu130). Slimmed: mani_skill, sapien (*.dist-info/SLIMMED.txt)

"""


# PEP 600 names (manylinux_2_28_x86_64) and the legacy alias manylinux2014 (= 2_17): pip reads any other
# spelling as an unknown platform that no wheel has.
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64")


def download_command(folder: Path, pins: list[str]) -> list[str]:
    """The ``pip download`` of ``pins`` as cp312 wheels for the accelerator machine's platforms."""
    plat = [a for p in PLATFORMS for a in ("--platform", p)]
    return [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "-d", str(folder),
            "--python-version", "3.12", "--implementation", "cp", *plat, *pins]  # fmt: skip


def wheels(cache: Path) -> list[Path]:
    """The pinned wheels (downloaded once; mani_skill and sapien slimmed) and the project's wheel."""
    want, have = {re.sub(r"[-_.]+", "_", p.split("==")[0]): p.split("==")[1] for p in PINS}, {}
    for f in sorted((cache / "wheels").glob("*.whl")):
        if want.get(f.name.split("-")[0].lower()) == f.name.split("-")[1]:
            have[f.name.split("-")[0].lower()] = f
    if missing := [f"{n}=={v}" for n, v in want.items() if n not in have]:
        print(f"gpu-kit: downloading {len(missing)} cp312 wheels into {cache / 'wheels'}", flush=True)
        subprocess.run(download_command(cache / "wheels", missing), check=True)
        return wheels(cache)
    for name in ("mani_skill", "sapien"):  # slimmed again when the wheel or the rules changed
        src, have[name] = have[name], cache / "slim" / have[name].name
        if not have[name].exists() or have[name].stat().st_mtime < max(src.stat().st_mtime, Path(SLIM).stat().st_mtime):
            subprocess.run([sys.executable, SLIM, str(src), str(cache / "slim")], check=True)
    shutil.rmtree(cache / "project", ignore_errors=True)  # the project, built from the working tree each time
    had_build = (ROOT / "build").exists()
    subprocess.run([VENV_PY, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index", "-w",
                    str(cache / "project"), str(ROOT)], check=True, cwd=ROOT)  # fmt: skip
    if not had_build:
        shutil.rmtree(ROOT / "build", ignore_errors=True)
    return sorted(have.values()) + sorted((cache / "project").glob("*.whl"))


def debs(cache: Path) -> dict[str, list[Path]]:
    """Debian bookworm's amd64 .debs, with apt lists of our own (the device README's recipe)."""
    o = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64", f"-oDir::State::Lists={cache}/apt-lists",
         "-oAPT::Sandbox::User=root", "-qq"]  # fmt: skip
    for folder, pkgs in DEBS.items():
        (d := cache / folder).mkdir(parents=True, exist_ok=True)
        if want := [p for p in pkgs.split() if not list(d.glob(f"{p}_*.deb"))]:
            (cache / "apt-lists/partial").mkdir(parents=True, exist_ok=True)
            subprocess.run(["apt-get", *o, "update"], check=True)
            subprocess.run(["apt-get", *o, "download", *want], check=True, cwd=d)
            for f in d.glob("*.deb"):  # names the carry accepts: epochs come url-escaped (2%3a1.8.4)
                f.rename(d / re.sub(r"[^A-Za-z0-9._-]", "_", f.name.replace("%3a", "_")))
    return {folder: sorted((cache / folder).glob("*.deb")) for folder in DEBS}


def assemble(whls: list[Path], deb_bytes: int, limit: int) -> list[list[Path]]:
    """Fewest parts under limit: each wheel, biggest first, into the part with the fewest bytes (.debs in the first)."""
    for k in range(1, 10):
        parts, size = [[] for _ in range(k)], [deb_bytes] + [0] * (k - 1)
        for w in sorted(whls, key=lambda w: w.stat().st_size, reverse=True):
            parts[i := size.index(min(size))].append(w)
            size[i] += w.stat().st_size
        if max(size) <= limit:
            return parts
    sys.exit(f"gpu-kit: ERROR: no split fits {limit / MIB:.1f} MiB per part")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", type=Path, default=Path.home() / ".cache/maniskill_torchrl/gpu-kit")
    p.add_argument("--physx", type=Path, help="folder of libPhysXGpu_64.so (default ~/.sapien/physx/<version>)")
    args = p.parse_args()
    whls, debs_ = wheels(args.cache), debs(args.cache)
    files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                           capture_output=True, text=True).stdout.split("\0")  # fmt: skip
    repo = sum((ROOT / f).stat().st_size for f in files if f and (ROOT / f).is_file())
    limit = 60 * MIB - repo  # a carry holds 64 MiB with the repository; 4 MiB kept for its growth
    parts = assemble(whls, sum(f.stat().st_size for fs in debs_.values() for f in fs), limit)
    shutil.rmtree(kit := ROOT / ".gpu", ignore_errors=True)
    names = ["kit"] + [f"kit{i + 2}" for i in range(len(parts) - 1)]
    when = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    for i, (name, part) in enumerate(zip(names, parts)):
        for sub, fs in [("wheels", part)] + (list(debs_.items()) if i == 0 else []):
            (kit / name / sub).mkdir(parents=True)
            for f in fs:
                shutil.copy2(f, kit / name / sub / f.name)
        (kit / name / "PARTS.txt").write_text("".join(f"{n}\n" for n in names))
        listing = [f"  {f.stat().st_size / MIB:8.2f} MiB  {f.relative_to(kit / name)}\n"
                   for f in sorted((kit / name).rglob("*")) if f.is_file()]  # fmt: skip
        (kit / name / "MANIFEST.txt").write_text(MANIFEST.format(name=name, when=when) + "".join(listing))
    version = "105.1-physx-5.3.1.patch0"  # sapien 3.0.3's sapien.physx.version()
    physx = args.physx or Path.home() / ".sapien/physx" / version
    if (physx / "libPhysXGpu_64.so").exists():
        shutil.copytree(physx, kit / "physx")
        (kit / "physx/VERSION").write_text(version + "\n")
        print(f"gpu-kit: PhysX GPU library {version} from {physx}: carry .gpu/physx beside .gpu/kit")
    else:  # SAPIEN downloads it from GitHub on first use: the machine cannot
        print(f"gpu-kit: NOTE: no {physx}/libPhysXGpu_64.so (SAPIEN's {version} linux-so.zip): no GPU sim there")
    for folder in sorted(kit.iterdir()):
        size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
        print(f"gpu-kit:   .gpu/{folder.name:6s} {size / MIB:5.1f} MiB + repo {repo / MIB:.1f} MiB per run")
        if size + repo > 64 * MIB:
            sys.exit("gpu-kit: ERROR: a part exceeds 64 MiB with the repository")
    return 0


if __name__ == "__main__":
    sys.exit(main())
