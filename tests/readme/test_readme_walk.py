"""The README walked as a newcomer walks it (``make test-readme``, in ``.ci/run``; not in ``make test``).

A fresh virtual environment gets the package from the wheel built from this tree, with the extras the README's
Install names (``pip install "<wheel>[maniskill,demo,hydra]"``), and the README's numpy 1 folder for the motion
planner (its ``pip install --target`` line, run as written). Every README command then runs from a temporary folder
that is not the repository, with a copy of ``examples/`` there (the README's paths are the clone's): its two
quickstart blocks, and each ``python examples/...`` line of its training block with its smoke flag; a line that
cannot run here (the GPU ones on a CPU machine) is listed with its reason, so that a new README line is either
walked or said. Exit status and outputs are checked.

What is reused, documented: the new venv does not download torch, TorchRL and ManiSkill again (several GB): a
``.pth`` file points it at a folder of links to ``.venv``'s installed packages, *without* ``maniskill_torchrl``
and its editable finder, so that the package comes from the wheel alone (checked: ``maniskill_torchrl.__file__``
is inside the new venv) and pip resolves the extras against what is there.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
EXTRAS = "maniskill,demo,hydra"
CUDA = shutil.which("nvidia-smi") is not None

# README training line (its start) -> (the smoke flags added, or None with the reason it is not run here)
SMOKE: dict[str, tuple[list[str] | None, str]] = {
    "python examples/ppo_torchrl.py --smoke": ([], "writes outputs/ppo/ppo_checkpoint.pt"),
    "python examples/ppo_torchrl.py --sim-backend cpu --device cuda": (None, "needs CUDA"),
    "python examples/ppo_torchrl.py --device cpu --env-id PullCube-v1": (["--smoke"], ""),
    "python examples/ppo_torchrl.py": (None, "the GPU run: hours on a CPU machine (its note is checked below)"),
    "python examples/evaluate_gym.py": (["--episodes", "2"], "reads the PPO smoke run's checkpoint"),
    "python examples/sac_torchrl.py": (["--smoke"], ""),
    "python examples/bc_torchrl.py": (["--smoke"], "plans 20 demos with ManiSkill's motion planner"),
    "python examples/trainers/train.py --config-name ppo_pullcube": (
        [
            "collector.total_frames=400",
            "hooks.evaluation.interval=200",
            "hooks.evaluation.episodes=2",
            "eval_env.base_env.max_episode_steps=5",
            "training_env.base_env.max_episode_steps=20",
        ],
        "",
    ),
}


def readme_blocks(lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", README, flags=re.S | re.M)


def training_lines() -> list[str]:
    """The ``python ...`` commands of the README's bash blocks, continuation lines joined, comments dropped."""
    lines = []
    for block in readme_blocks("bash"):
        for cmd in block.replace("\\\n", " ").splitlines():
            cmd = " ".join(cmd.split("#")[0].split())
            if cmd.startswith("python examples/"):
                lines.append(cmd)
    return lines


def smoke_of(cmd: str) -> tuple[list[str] | None, str]:
    key = max((k for k in SMOKE if cmd == k or cmd.startswith(k + " ")), key=len, default=None)
    assert key is not None, f"README command {cmd!r} is neither walked nor skipped: add it to SMOKE"
    return SMOKE[key]


@pytest.fixture(scope="module")
def newcomer(tmp_path_factory) -> dict:
    """The fresh venv and the folder the commands run from: {"python", "folder", "env"}."""
    base = tmp_path_factory.mktemp("readme")
    dist = base / "dist"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(dist), str(ROOT)],
        check=True,
        timeout=300,
    )
    (wheel,) = dist.glob("maniskill_torchrl-*.whl")
    shared = base / "installed"  # .venv's packages, less this package: links, no copies
    shared.mkdir()
    for entry in Path(sysconfig.get_paths()["purelib"]).iterdir():
        if not entry.name.startswith(("maniskill_torchrl", "__editable__", "_readme_walk")):
            (shared / entry.name).symlink_to(entry)
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = venv / "bin" / "python"
    purelib = subprocess.run(
        [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    (Path(purelib) / "_readme_walk_shared.pth").write_text(f"{shared}\n")
    subprocess.run([python, "-m", "pip", "install", "-q", f"{wheel}[{EXTRAS}]"], check=True, timeout=600)
    folder = base / "newcomer"
    shutil.copytree(ROOT / "examples", folder / "examples", ignore=shutil.ignore_patterns("__pycache__"))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(PATH=f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}", PYTHONUNBUFFERED="1")
    return {"python": str(python), "folder": folder, "env": env}


def run(newcomer: dict, cmd: str | list[str], timeout: int = 600) -> subprocess.CompletedProcess:
    args = shlex.split(cmd) if isinstance(cmd, str) else cmd
    if args[0] == "python":
        args[0] = newcomer["python"]
    proc = subprocess.run(
        args, cwd=newcomer["folder"], env=newcomer["env"], capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == 0, f"{cmd}: exit {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def test_the_package_comes_from_the_wheel(newcomer):
    out = run(newcomer, ["python", "-c", "import maniskill_torchrl, sys; print(maniskill_torchrl.__file__)"]).stdout
    assert str(Path(newcomer["python"]).parents[1]) in out and str(ROOT) not in out
    run(newcomer, ["maniskill-torchrl", "--help"])


def test_the_numpy1_line_of_the_install(newcomer):
    """The README's line for the motion planner's numpy 1, run as written."""
    (line,) = [m for m in re.findall(r"`(python -m pip install --target [^`]+)`", README)]
    run(newcomer, ["bash", "-c", line], timeout=300)


@pytest.mark.parametrize("index", range(len(readme_blocks("python"))))
def test_quickstart_blocks(newcomer, index):
    script = newcomer["folder"] / f"quickstart_{index}.py"
    script.write_text(readme_blocks("python")[index])
    out = run(newcomer, ["python", script.name]).stdout
    assert out.strip(), "the quickstart printed nothing"


@pytest.mark.parametrize("cmd", training_lines())
def test_training_commands(newcomer, cmd):
    flags, why = smoke_of(cmd)
    if flags is None:
        if "CUDA" in why and CUDA:
            pytest.skip("a CUDA machine: sized for hours")
        if cmd == "python examples/ppo_torchrl.py" and not CUDA:
            # what the line becomes here is said up front: checked through --help's parse, not run
            code = "import sys; sys.path.insert(0, 'examples'); import ppo_torchrl; ppo_torchrl.parse_args([])"
            assert "No CUDA device here" in run(newcomer, ["python", "-c", code]).stdout
        pytest.skip(why)
    if "evaluate_gym" in cmd:
        if not (newcomer["folder"] / "outputs" / "ppo" / "ppo_checkpoint.pt").exists():
            run(newcomer, "python examples/ppo_torchrl.py --smoke")
        cmd = re.sub(r"--episodes \d+", "", cmd)
    proc = run(newcomer, f"{cmd} {' '.join(flags)}")
    folder = newcomer["folder"]
    if "ppo_torchrl.py --smoke" in cmd:
        assert (folder / "outputs" / "ppo" / "ppo_checkpoint.pt").is_file()
    if "sac_torchrl" in cmd:
        assert (folder / "outputs" / "sac" / "sac_checkpoint.pt").is_file()
    if "bc_torchrl" in cmd:
        assert (folder / "demos" / "PickCube-v1" / "motionplanning").is_dir()  # under the folder it ran from
        assert (folder / "outputs" / "bc" / "bc_checkpoint.pt").is_file()
    if "train.py" in cmd:
        assert "output folder: " in proc.stdout
        out = Path(proc.stdout.split("output folder: ")[1].splitlines()[0])
        assert (out / "policy.pt").is_file() and folder in out.parents
        # the command its last line prints: the run's policy, evaluated through ManiSkill's gym path
        assert f"evaluate it: python examples/evaluate_gym.py --checkpoint {out / 'policy.pt'}" in proc.stdout
        evaluated = run(
            newcomer, f"python examples/evaluate_gym.py --checkpoint {out} --episodes 2 --max-episode-steps 5"
        )
        assert "episodes: 2" in evaluated.stdout and "avg success_once" in evaluated.stdout, evaluated.stdout
    if "evaluate_gym" in cmd:
        assert "success" in proc.stdout
