"""One script, three engines: gymnasium's forkserver AsyncVectorEnv of the gym shim, then a TorchRL
ParallelEnv of single CPU envs, then the batched CPU env ``ManiSkillEnv(num_envs=2)``.

Each sequence runs as a user's script would, in a subprocess with a timeout (a hang fails the
test instead of the session). Why it used to hang (see ``maniskill_torchrl/_mp.py``): the first
process started by the AsyncVectorEnv makes Python pin the global start method to "fork";
``torchrl``, imported after that, takes it for the user's choice, so ParallelEnv forks the
parent, which holds a SAPIEN renderer (gymnasium builds one env in the parent), and the workers
deadlock in the Vulkan driver. The script checks that condition before starting the
ParallelEnv, so it fails in seconds with a message instead of waiting for the timeout.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TIMEOUT_S = 300  # three engines start on 2 cores: ~40 s when idle

SCRIPT = """
import multiprocessing as mp
import sys
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


if __name__ == "__main__":
    which = sys.argv[1]
    envs = gym.vector.AsyncVectorEnv([thunk] * 2, context="forkserver")
    envs.reset(seed=0)
    for _ in range(3):
        envs.step(envs.action_space.sample())
    envs.close()
    print("STAGE gym ok", flush=True)

    if which == "torchrl":
        from torchrl.envs import ParallelEnv

        from maniskill_torchrl._mp import vulkan_loaded

        if mp.get_start_method(allow_none=True) == "fork" and vulkan_loaded():
            print("WOULD_HANG start method pinned to fork with a SAPIEN renderer in the parent", flush=True)
            sys.exit(3)
    else:
        from maniskill_torchrl.parallel import ParallelEnv
    penv = ParallelEnv(2, single)
    td = penv.rollout(3)
    assert td.batch_size == (2, 3), td.batch_size
    penv.close()
    print("STAGE parallel ok", flush=True)

    from maniskill_torchrl import ManiSkillEnv

    try:
        env = ManiSkillEnv("PickCube-v1", num_envs=2, obs_mode="state", max_episode_steps=10)
    except ValueError as err:
        if "GPU sim" in str(err):
            print("SKIP_BATCHED", flush=True)
            sys.exit(0)
        raise
    env.set_seed(0)
    td = env.rollout(3)
    assert td.batch_size == (2, 3), td.batch_size
    env.close()
    print("STAGE batched ok", flush=True)
"""


def run_sequence(tmp_path: Path, which: str) -> subprocess.CompletedProcess:
    script = tmp_path / "sequence.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    try:
        return subprocess.run(
            [sys.executable, str(script), which],
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
def test_gym_then_parallelenv_then_batched_env(tmp_path: Path, which: str) -> None:
    """``which``: the ParallelEnv of the second stage, ``maniskill_torchrl.parallel.ParallelEnv`` or
    TorchRL's own (what users write by habit)."""
    proc = run_sequence(tmp_path, which)
    out = proc.stdout
    assert "WOULD_HANG" not in out, (
        "TorchRL's ParallelEnv would fork a parent holding a SAPIEN renderer: importing maniskill_torchrl "
        f"should have set the 'spawn' start method\n{out[-3000:]}"
    )
    assert proc.returncode == 0, (
        f"exit {proc.returncode}\n--- stdout ---\n{out[-3000:]}\n--- stderr ---\n{proc.stderr[-3000:]}"
    )
    assert "STAGE gym ok" in out and "STAGE parallel ok" in out, out
    assert "SKIP_BATCHED" not in out, out
    assert "STAGE batched ok" in out, out
