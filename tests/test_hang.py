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
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

TIMEOUT_S = 300  # four engines start on 2 cores: about a minute when idle

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
    penv = ParallelEnv(2, single)
    try:
        td = penv.rollout(3)
        assert td.batch_size == (2, 3), td.batch_size
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
    envs = gym.vector.AsyncVectorEnv([thunk] * 2, context="forkserver")
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
        env = ManiSkillEnv("PickCube-v1", num_envs=2, obs_mode="state", max_episode_steps=10)
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


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> subprocess.CompletedProcess:
    """The script's run, shared by the tests (each checks its own stages)."""
    tmp_path = tmp_path_factory.mktemp("hang")
    script = tmp_path / "sequence.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    try:
        return subprocess.run(
            [sys.executable, str(script)],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=TIMEOUT_S,
            start_new_session=True,
        )
    except subprocess.TimeoutExpired as err:
        out = (err.stdout or b"").decode() if isinstance(err.stdout, bytes) else (err.stdout or "")
        pytest.fail(f"the sequence hung (killed after {TIMEOUT_S} s); stdout so far:\n{out[-3000:]}")


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
