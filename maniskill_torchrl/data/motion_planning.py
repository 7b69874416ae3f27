"""ManiSkill motion-planning demonstrations, made offline in the control and observation modes a policy trains on.

:func:`make_demos` (and ``maniskill-torchrl make-demos``, and ``examples/bc_torchrl.py`` on demand):

1. ManiSkill's motion-planning solutions (``python -m mani_skill.examples.motionplanning.panda.run``)
   write ``num_demos`` successful episodes in ``pd_joint_pos`` on the CPU sim, seeds ``0..num_demos-1``.
   ManiSkill pins mplib 0.1.1, which is built for numpy 1.x and crashes (a segmentation fault in
   ``mplib.Planner.__init__``) under numpy 2, which the rest of the stack (opencv-python 5) needs. The
   planner's process therefore runs with a numpy 1 first on its ``PYTHONPATH``: a folder made once with
   ``pip install --target <folder> "numpy<2"`` (``make setup`` makes ``.venv/numpy1``), found at
   ``$MANISKILL_TORCHRL_NUMPY1``, else ``<sys.prefix>/numpy1`` (the environment's own folder). Nothing
   else sees that numpy, and nothing is installed at run time: without the folder, :class:`Numpy1Missing`
   says the command that makes it.
2. ManiSkill's ``replay_trajectory`` converts them to ``control_mode`` with state observations:
   ``<out_dir>/<env_id>/motionplanning/trajectory.state.<control_mode>.physx_cpu.h5`` (+ ``.json``), the
   file :class:`~maniskill_torchrl.data.ManiSkillExperienceReplay` reads. Episodes the conversion fails are
   dropped.

Every path is the caller's (``out_dir`` as given, resolved once) or the running interpreter's: none depends
on a repository checkout or on a ``.venv``. Idempotent: a finished run of at least ``num_demos`` demos (its
stamp, ``.made-<count>``, beside the converted file) is kept; a reader takes the first ``num_demos``
episodes (``ManiSkillExperienceReplay(num_episodes=...)``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["Numpy1Missing", "demo_path", "make_demos", "numpy1_folder"]

NUMPY1_ENV = "MANISKILL_TORCHRL_NUMPY1"


class Numpy1Missing(RuntimeError):
    """The numpy 1 that ManiSkill's motion planner (mplib 0.1.1) needs is not there; the message says
    how to make it."""


def numpy1_folder() -> Path | None:
    """The folder whose numpy 1 the planner's process imports first, or ``None`` where this
    environment's numpy is 1.x already (nothing to add).

    Raises:
        Numpy1Missing: numpy is 2.x here and the folder (``$MANISKILL_TORCHRL_NUMPY1``, else
            ``<sys.prefix>/numpy1``) holds no numpy.
    """
    import numpy

    if int(numpy.__version__.split(".")[0]) < 2:
        return None
    folder = Path(os.environ.get(NUMPY1_ENV) or Path(sys.prefix) / "numpy1")
    if not (folder / "numpy" / "__init__.py").is_file():
        raise Numpy1Missing(
            f"ManiSkill's motion planner (mplib 0.1.1) crashes under numpy {numpy.__version__}; it runs with "
            f"numpy 1 first on its path, from {folder}, which holds no numpy. Make it once with\n"
            f'    {sys.executable} -m pip install --target "{folder}" "numpy<2"\n'
            f"(`make setup` does it for .venv), or point ${NUMPY1_ENV} to a folder made so. Only the "
            "planner's process sees that numpy."
        )
    return folder


def demo_path(out_dir: str | Path, env_id: str, control_mode: str = "pd_ee_delta_pos") -> Path:
    """Where :func:`make_demos` writes the converted file (an absolute path)."""
    return Path(out_dir).resolve() / env_id / "motionplanning" / f"trajectory.state.{control_mode}.physx_cpu.h5"


def _count(json_path: Path) -> int:
    try:
        return len(json.loads(json_path.read_text())["episodes"])
    except (OSError, ValueError, KeyError):
        return 0


def _made(folder: Path) -> int:
    return max((int(p.name[len(".made-") :]) for p in folder.glob(".made-*") if p.name[6:].isdigit()), default=0)


def _run(cmd: list[str], log_path: Path, env: dict[str, str] | None, what: str) -> None:
    with log_path.open("w") as log:
        proc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    if proc.returncode != 0:
        tail = "\n".join(log_path.read_text(errors="replace").splitlines()[-20:])
        raise RuntimeError(f"{what} failed (exit {proc.returncode}); its log: {log_path}\n{tail}")


def make_demos(
    env_id: str,
    num_demos: int,
    control_mode: str = "pd_ee_delta_pos",
    out_dir: str | Path = "demos",
    *,
    processes: int | None = None,
    log: Callable[[str], None] = print,
) -> Path:
    """Plans ``num_demos`` successful ``env_id`` demonstrations and converts them to ``control_mode``
    with state observations; returns the converted ``.h5`` (see the module docstring). Kept when made
    already with at least ``num_demos``.

    Args:
        processes: planner and conversion processes (default: the CPUs this process may use).
        log: where the progress lines go.

    Raises:
        Numpy1Missing: before anything runs, where the planner's numpy 1 is missing.
        RuntimeError: the planner or the conversion failed (the message names its log and ends with its tail).
    """
    converted = demo_path(out_dir, env_id, control_mode)
    folder = converted.parent
    made = _made(folder) if folder.is_dir() else 0
    if converted.is_file() and made >= num_demos:
        log(f"make_demos: {converted} made already (from {made} planned demos)")
        return converted
    numpy1 = numpy1_folder()
    procs = processes or len(os.sched_getaffinity(0))
    folder.mkdir(parents=True, exist_ok=True)
    for old in [*folder.glob(".made-*"), *folder.glob("trajectory*")]:
        old.unlink()
    env = None
    if numpy1 is not None:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(numpy1), os.environ.get("PYTHONPATH")])))
    t0 = time.perf_counter()
    log(f"make_demos: planning {num_demos} {env_id} demos on {procs} processes (log: {folder / 'planning.log'})")
    _run(
        [
            sys.executable,
            "-m",
            "mani_skill.examples.motionplanning.panda.run",
            *("-e", env_id, "-n", str(num_demos), "-b", "cpu", "--only-count-success"),
            *("--record-dir", str(converted.parents[2]), "--traj-name", "trajectory", "--num-procs", str(procs)),
        ],
        folder / "planning.log",
        env,
        "planning the demonstrations",
    )
    log(f"make_demos: planned in {time.perf_counter() - t0:.0f} s ({_count(folder / 'trajectory.json')} episodes)")
    t1 = time.perf_counter()
    log(f"make_demos: converting to {control_mode}, state observations (log: {folder / 'conversion.log'})")
    _run(
        [
            sys.executable,
            "-m",
            "mani_skill.trajectory.replay_trajectory",
            *("--traj-path", str(folder / "trajectory.h5"), "-c", control_mode, "-o", "state", "--save-traj"),
            *("-b", "physx_cpu", "--num-envs", str(procs)),
        ],
        folder / "conversion.log",
        None,
        "converting the demonstrations",
    )
    if not converted.is_file():
        raise RuntimeError(f"the conversion wrote no {converted}; its log: {folder / 'conversion.log'}")
    episodes = _count(converted.with_suffix(".json"))
    log(f"make_demos: converted in {time.perf_counter() - t1:.0f} s: {converted} ({episodes} episodes)")
    (folder / f".made-{num_demos}").touch()
    return converted
