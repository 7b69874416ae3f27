"""One script, three engines: gymnasium's forkserver AsyncVectorEnv of the gym shim, then a TorchRL
ParallelEnv of single CPU envs (TorchRL's own, what users write by habit, then
``maniskill_torchrl.parallel.ManiSkillParallelEnv``), then the batched CPU env ``ManiSkillEnv(num_envs=2)``.

The sequence runs as a user's script would, in a subprocess with a timeout (a hang fails the
tests instead of the session). Why it used to hang (see ``maniskill_torchrl/_mp.py``): the first
process started by the AsyncVectorEnv makes Python pin the global start method to "fork";
``torchrl``, imported after that, takes it for the user's choice, so ParallelEnv forks the
parent (the script imports TorchRL first, as a TorchRL script does; the library itself sets no
start method), which holds a SAPIEN renderer (gymnasium builds one env in the parent), and the workers
deadlock in the Vulkan driver. The script checks that condition before starting TorchRL's
ParallelEnv, and skips that stage with a message instead of waiting for the timeout.

Both ParallelEnv stages run in one process (one subprocess, not two: each start imports torch,
TorchRL and ManiSkill in the parent and in every worker): TorchRL's first, as it depends on the
global start method that the gym stage left; the library's ParallelEnv starts its workers with
the forkserver whatever that global says. A stage that raises is reported and the next ones still run;
each test checks its own stage and the ones around it.

The gym and ParallelEnv stages start one worker each: one process pins the start method, and one
forked worker building a ManiSkill env is enough to hang; every extra worker costs seconds of
imports. The batched env needs two (``num_envs=1`` runs in-process).
"""

from __future__ import annotations

import atexit
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

TIMEOUT_S = 300  # four engines start on 2 cores: under a minute when idle

SCRIPT = """
import multiprocessing as mp
import sys
import traceback
import warnings

warnings.filterwarnings("ignore")
import gymnasium as gym
import torchrl  # noqa: F401  (a TorchRL script imports it first: it sets "spawn", which fork-after-gym needs)

import mani_skill.envs  # noqa: F401
from maniskill_torchrl.wrappers import CPUGymWrapper


def thunk():
    import mani_skill.envs  # noqa: F401

    return CPUGymWrapper(gym.make("PickCube-v1", num_envs=1, obs_mode="state", max_episode_steps=10))


def single():
    from torchrl.envs import TransformedEnv

    from maniskill_torchrl import CPUUnbatch, ManiSkillEnv

    return TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=10), CPUUnbatch())


def parallel(ParallelEnv):
    penv = ParallelEnv(1, single)
    try:
        td = penv.rollout(3)
        assert td.batch_size == (1, 3), td.batch_size
    finally:
        penv.close()


def stage(name, fn):
    try:
        fn()
    except Exception:
        print(f"STAGE {name} FAILED", flush=True)
        traceback.print_exc(file=sys.stdout)
        sys.stdout.flush()
        return False
    print(f"STAGE {name} ok", flush=True)
    return True


if __name__ == "__main__":
    ok = True
    envs = gym.vector.AsyncVectorEnv([thunk], context="forkserver")
    envs.reset(seed=0)
    for _ in range(3):
        envs.step(envs.action_space.sample())
    envs.close()
    print("STAGE gym ok", flush=True)

    from torchrl.envs import ParallelEnv as TorchRLParallelEnv

    from maniskill_torchrl._internal.mp import vulkan_loaded

    if mp.get_start_method(allow_none=True) == "fork" and vulkan_loaded():
        print("WOULD_HANG start method pinned to fork with a SAPIEN renderer in the parent", flush=True)
        ok = False
    else:
        ok &= stage("torchrl-parallel", lambda: parallel(TorchRLParallelEnv))

    from maniskill_torchrl.parallel import ManiSkillParallelEnv

    ok &= stage("library-parallel", lambda: parallel(ManiSkillParallelEnv))

    from maniskill_torchrl import ManiSkillEnv

    def batched():
        env = ManiSkillEnv("PickCube-v1", num_envs=2, sim_backend="cpu", obs_mode="state", max_episode_steps=10)
        try:
            env.set_seed(0)
            td = env.rollout(3)
            assert td.batch_size == (2, 3), td.batch_size
        finally:
            env.close()

    ok &= stage("batched", batched)
    print("SEQUENCE DONE", flush=True)
    sys.exit(0 if ok else 1)
"""


class _Run:
    """The script, running in its own session (a hung run is killed with its workers), its output and
    exit code in ``folder``: another process of the same test run (an xdist worker) can wait for it."""

    def __init__(self, folder: Path, start: bool = True) -> None:
        self.folder, self.proc = folder, None
        if not start:
            return
        (folder / "sequence.py").write_text(SCRIPT)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # sh writes the exit code once the script ends, whatever process waits for it
        self.proc = subprocess.Popen(
            ["sh", "-c", '"$0" sequence.py >stdout.txt 2>stderr.txt; echo $? >rc.tmp; mv rc.tmp rc', sys.executable],
            cwd=folder,
            env=env,
            start_new_session=True,
        )
        (folder / "pgid").write_text(str(self.proc.pid))

    def wait(self) -> subprocess.CompletedProcess:
        rc = self.folder / "rc"
        deadline = time.monotonic() + TIMEOUT_S
        while not rc.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        out, err = self._read()
        if not rc.exists():
            self.kill()
            pytest.fail(f"the sequence hung (killed after {TIMEOUT_S} s); stdout so far:\n{out[-3000:]}")
        return subprocess.CompletedProcess(["sequence.py"], int(rc.read_text()), out, err)

    def _read(self) -> tuple[str, str]:
        return tuple(
            (self.folder / n).read_text() if (self.folder / n).exists() else "" for n in ("stdout.txt", "stderr.txt")
        )

    def kill(self) -> None:
        try:
            os.killpg(int((self.folder / "pgid").read_text()), signal.SIGKILL)
        except (OSError, ValueError):
            pass
        if self.proc is not None:
            self.proc.wait()

    def finish(self) -> None:
        """At this process's exit: the run may serve another xdist worker, so let it end (it was
        started with the tests, so it is long over by then), bounded by its timeout."""
        if self.proc is not None and self.proc.poll() is None:
            try:
                self.proc.wait(timeout=max(0.0, TIMEOUT_S - (time.monotonic() - self.started)))
            except subprocess.TimeoutExpired:
                pass
        self.kill()


_EARLY: list[_Run] = []


def _shared_folder() -> Path | None:
    """The folder of this test run's one early run under pytest-xdist (its workers share the run id)."""
    uid = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    return Path(tempfile.gettempdir()) / f"test_hang_{uid}" if uid else None


def start_early() -> None:
    """Called by ``conftest.py`` once the tests are collected, when a test of this file is selected:
    the script (about 45 s, most of it on one core: each stage waits for processes that import
    torch, TorchRL and ManiSkill) then runs beside the tests collected before this file. Once per
    test run: without xdist in the pytest process; under xdist (every worker collects every test)
    only in the first worker to claim the run's shared folder, and whichever worker runs the tests
    waits for that run. Killed when the starting process exits, after its timeout at the latest."""
    shared = _shared_folder()
    if shared is not None:
        try:
            shared.mkdir()
        except FileExistsError:
            return  # another worker started it
        folder = shared
    else:
        folder = Path(tempfile.mkdtemp(prefix="test_hang_"))
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
    run = _Run(folder)
    run.started = time.monotonic()
    _EARLY.append(run)
    atexit.register(run.finish)  # first (atexit runs in reverse order)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> subprocess.CompletedProcess:
    """The script's run, shared by the tests (each checks its own stages); started early when
    ``conftest.py`` could (:func:`start_early`)."""
    shared = _shared_folder()
    if _EARLY:
        run = _EARLY[0]
    elif shared is not None and (shared / "pgid").exists():  # started by another xdist worker
        run = _Run(shared, start=False)
    else:
        run = _Run(tmp_path_factory.mktemp("hang"))
    return run.wait()


@pytest.mark.parametrize("which", ["library", "torchrl"])
def test_gym_then_parallelenv_then_batched_env(sequence: subprocess.CompletedProcess, which: str) -> None:
    """``which``: the ParallelEnv of the second stage, ``maniskill_torchrl.parallel.ManiSkillParallelEnv`` or
    TorchRL's own (what users write by habit)."""
    proc = sequence
    out = proc.stdout
    report = f"exit {proc.returncode}\n--- stdout ---\n{out[-3000:]}\n--- stderr ---\n{proc.stderr[-3000:]}"
    if which == "torchrl":
        assert "WOULD_HANG" not in out, (
            "TorchRL's ParallelEnv would fork a parent holding a SAPIEN renderer: importing torchrl "
            f"first should have set the 'spawn' start method\n{out[-3000:]}"
        )
    # ran to its end without a crash (exit 1: a stage failed, checked below)
    assert "SEQUENCE DONE" in out and proc.returncode in (0, 1), report
    assert "STAGE gym ok" in out, report
    assert f"STAGE {which}-parallel ok" in out, report
    assert "STAGE batched ok" in out, report
