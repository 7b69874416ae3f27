"""One script, three engines: gymnasium's forkserver AsyncVectorEnv of the gym shim, then a TorchRL
ParallelEnv of single CPU envs (TorchRL's own, what users write by habit, then
``maniskill_torchrl.parallel.ParallelEnv``), then the batched CPU env ``ManiSkillEnv(num_envs=2)``.

The sequence runs as a user's script would, in a subprocess with a timeout (a hang fails the
tests instead of the session). Why it used to hang (see ``maniskill_torchrl/_mp.py``): the first
process started by the AsyncVectorEnv makes Python pin the global start method to "fork";
``torchrl``, imported after that, takes it for the user's choice, so ParallelEnv forks the
parent, which holds a SAPIEN renderer (gymnasium builds one env in the parent), and the workers
deadlock in the Vulkan driver. The script checks that condition before starting TorchRL's
ParallelEnv, and skips that stage with a message instead of waiting for the timeout.

Both ParallelEnv stages run in one process (one subprocess, not two: each start imports torch,
TorchRL and ManiSkill in the parent and in every worker): TorchRL's first, as it depends on the
global start method that the gym stage left; the library's ParallelEnv starts its workers with
"spawn" whatever that global says. A stage that raises is reported and the next ones still run;
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

    from maniskill_torchrl._mp import vulkan_loaded

    if mp.get_start_method(allow_none=True) == "fork" and vulkan_loaded():
        print("WOULD_HANG start method pinned to fork with a SAPIEN renderer in the parent", flush=True)
        ok = False
    else:
        ok &= stage("torchrl-parallel", lambda: parallel(TorchRLParallelEnv))

    from maniskill_torchrl.parallel import ParallelEnv

    ok &= stage("library-parallel", lambda: parallel(ParallelEnv))

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
    """The script, running in its own session (a hung run is killed with its workers)."""

    def __init__(self, folder: Path) -> None:
        script = folder / "sequence.py"
        script.write_text(SCRIPT)
        self.out, self.err = (open(folder / name, "w+") for name in ("stdout.txt", "stderr.txt"))
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            [sys.executable, str(script)],
            cwd=folder,
            env=env,
            stdout=self.out,
            stderr=self.err,
            text=True,
            start_new_session=True,
        )

    def wait(self) -> subprocess.CompletedProcess:
        try:
            self.proc.wait(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(f"the sequence hung (killed after {TIMEOUT_S} s); stdout so far:\n{self._read()[0][-3000:]}")
        return subprocess.CompletedProcess(self.proc.args, self.proc.returncode, *self._read())

    def _read(self) -> tuple[str, str]:
        self.out.seek(0)
        self.err.seek(0)
        return self.out.read(), self.err.read()

    def kill(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.proc.wait()


_EARLY: list[_Run] = []


def start_early() -> None:
    """Called by ``conftest.py`` once the tests are collected, when a test of this file is selected:
    the script (about 45 s, most of it on one core: each stage waits for processes that import
    torch, TorchRL and ManiSkill) then runs while the tests collected before this file run in the
    pytest process. Killed when pytest exits if no test has waited for it."""
    folder = Path(tempfile.mkdtemp(prefix="test_hang_"))
    run = _Run(folder)
    _EARLY.append(run)
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    atexit.register(run.kill)  # first (atexit runs in reverse order)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> subprocess.CompletedProcess:
    """The script's run, shared by the tests (each checks its own stages); started early when
    ``conftest.py`` could (:func:`start_early`)."""
    run = _EARLY.pop() if _EARLY else _Run(tmp_path_factory.mktemp("hang"))
    return run.wait()


@pytest.mark.parametrize("which", ["library", "torchrl"])
def test_gym_then_parallelenv_then_batched_env(sequence: subprocess.CompletedProcess, which: str) -> None:
    """``which``: the ParallelEnv of the second stage, ``maniskill_torchrl.parallel.ParallelEnv`` or
    TorchRL's own (what users write by habit)."""
    proc = sequence
    out = proc.stdout
    report = f"exit {proc.returncode}\n--- stdout ---\n{out[-3000:]}\n--- stderr ---\n{proc.stderr[-3000:]}"
    if which == "torchrl":
        assert "WOULD_HANG" not in out, (
            "TorchRL's ParallelEnv would fork a parent holding a SAPIEN renderer: importing maniskill_torchrl "
            f"should have set the 'spawn' start method\n{out[-3000:]}"
        )
    # ran to its end without a crash (exit 1: a stage failed, checked below)
    assert "SEQUENCE DONE" in out and proc.returncode in (0, 1), report
    assert "STAGE gym ok" in out, report
    assert f"STAGE {which}-parallel ok" in out, report
    assert "STAGE batched ok" in out, report
