"""maniskill_torchrl.parallel.ManiSkillParallelEnv: same data as TorchRL's ParallelEnv, sleeping wait,
batch-scheduled workers, errors instead of hangs (a dead worker, fork after a SAPIEN renderer).

The toy envs here are plain torch (no ManiSkill); workers start with the forkserver, the library's
default (TorchRL's reference too; the pytest process may hold a SAPIEN renderer from other
tests, and then fork is unsafe). One ManiSkill test checks
the real worker env against an in-process SerialEnv of the same envs.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase, SerialEnv, TransformedEnv
from torchrl.envs import ParallelEnv as TorchRLParallelEnv

from maniskill_torchrl._internal import mp as _mp
from maniskill_torchrl.parallel import ManiSkillParallelEnv, set_batch_policy, usable_cores

STEPS = 12


class SeededToy(EnvBase):
    """Unbatched env with seeded random observations and rewards; episodes of 5 steps.

    ``crash_at``: the worker process exits (code 3) at that step, as a crashing simulator would.
    """

    def __init__(self, crash_at: int | None = None) -> None:
        super().__init__()
        self.observation_spec = Composite(observation=Unbounded((3,)), count=Unbounded((), dtype=torch.int64))
        self.action_spec = Bounded(-1.0, 1.0, (2,))
        self.reward_spec = Unbounded((1,))
        self.crash_at = crash_at
        self.gen = torch.Generator().manual_seed(0)
        self.t = 0

    def _obs(self) -> TensorDict:
        return TensorDict(observation=torch.rand(3, generator=self.gen), count=torch.tensor(self.t))

    def _reset(self, tensordict):
        self.t = 0
        return self._obs()

    def _step(self, tensordict):
        self.t += 1
        if self.crash_at is not None and self.t >= self.crash_at:
            os._exit(3)
        out = self._obs()
        out["observation"] += tensordict["action"].sum()
        out["reward"] = torch.rand(1, generator=self.gen)
        done = torch.tensor([self.t >= 5])
        out["done"] = out["terminated"] = done
        return out

    def _set_seed(self, seed: int | None) -> None:
        self.gen.manual_seed(0 if seed is None else seed)


def crashing_toy() -> SeededToy:
    return SeededToy(crash_at=3)


def run(env, steps: int = STEPS, seed: int = 3) -> TensorDict:
    """Seeded steps as a collector makes them (``step_and_maybe_reset``), with fixed actions."""
    env.set_seed(seed)
    td = env.reset()
    g = torch.Generator().manual_seed(1)
    out = []
    for _ in range(steps):
        td.set("action", torch.rand(env.batch_size + (2,), generator=g) * 2 - 1)
        step, td = env.step_and_maybe_reset(td)
        out.append(step.clone())
    return torch.stack(out, -1)


@pytest.fixture(scope="module")
def torchrl_rollout() -> TensorDict:
    """The reference: TorchRL's own ParallelEnv (spin wait), seeded."""
    ref_env = TorchRLParallelEnv(2, SeededToy, mp_start_method="forkserver")
    try:
        return run(ref_env)
    finally:
        ref_env.close()


@pytest.fixture(scope="module")
def toy_envs():
    """``ManiSkillParallelEnv(2, SeededToy, wait=...)`` per wait mode, started once for the module:
    every use seeds its rollout (``run``)."""
    made: dict[str, ManiSkillParallelEnv] = {}

    def get(wait: str) -> ManiSkillParallelEnv:
        if wait not in made:
            made[wait] = ManiSkillParallelEnv(2, SeededToy, wait=wait)
        return made[wait]

    yield get
    for env in made.values():
        env.close()


@pytest.mark.parametrize("wait", ["sleep", "spin"])
def test_same_rollout_as_torchrl_parallelenv(torchrl_rollout: TensorDict, toy_envs, wait: str) -> None:
    env = toy_envs(wait)
    got = run(env)
    assert env.wait == wait
    ref = torchrl_rollout
    assert ref["next", "done"].any() and ref["next", "done"].sum() < ref["next", "done"].numel()
    assert set(ref.keys(True, True)) == set(got.keys(True, True))
    for key in ref.keys(True, True):
        torch.testing.assert_close(got[key], ref[key], rtol=0, atol=0, msg=lambda m, k=key: f"{k}: {m}")


def test_worker_crash_raises_quickly() -> None:
    env = ManiSkillParallelEnv(2, crashing_toy, wait="sleep")
    # Start the workers first (a few seconds on a busy machine): the limit is on the crash.
    env.reset()
    t0 = time.perf_counter()
    with pytest.raises(RuntimeError, match="dead"):
        run(env, steps=6)
    assert time.perf_counter() - t0 < 15


def test_wait_and_options() -> None:
    workers = max(1, usable_cores())
    assert ManiSkillParallelEnv(workers, SeededToy).wait == "sleep"  # no core left for the parent
    env = ManiSkillParallelEnv(1, SeededToy, wait="spin")
    assert env.wait == "spin"
    assert env._mp_start_method == "forkserver"
    assert ManiSkillParallelEnv(1, SeededToy, mp_start_method="spawn")._mp_start_method == "spawn"
    with pytest.raises(ValueError, match="wait"):
        ManiSkillParallelEnv(2, SeededToy, wait="busy")
    with pytest.raises(ValueError, match="poll_s"):
        ManiSkillParallelEnv(2, SeededToy, poll_s=0)


@pytest.mark.skipif(not hasattr(os, "SCHED_BATCH"), reason="Linux scheduling policy")
def test_workers_run_as_batch_threads(toy_envs) -> None:
    assert not ManiSkillParallelEnv(1, SeededToy, wait="spin")._batch_workers  # only with a sleeping parent
    env = toy_envs("sleep")
    env.reset()
    assert len(env._workers) == 2
    for worker in env._workers:
        for tid in os.listdir(f"/proc/{worker.pid}/task"):
            assert os.sched_getscheduler(int(tid)) == os.SCHED_BATCH
    assert not set_batch_policy(2**22 + 12345)  # no such process: nothing to do, no error


def test_fork_after_renderer_is_refused(monkeypatch) -> None:
    """mp_start_method="fork" in a process holding a SAPIEN renderer: an error at start, not a hang."""
    monkeypatch.setattr(_mp, "vulkan_loaded", lambda: True)
    env = ManiSkillParallelEnv(2, SeededToy, mp_start_method="fork")
    with pytest.raises(RuntimeError, match="SAPIEN renderer"):
        env.reset()


def test_vulkan_loaded_after_a_maniskill_env() -> None:
    """The detection the fork guard relies on: building a ManiSkill env loads the Vulkan loader."""
    import gymnasium as gym

    env = gym.make("PickCube-v1", num_envs=1, obs_mode="state")
    env.close()
    assert _mp.vulkan_loaded()


@pytest.mark.slow
def test_importing_the_library_changes_no_start_method() -> None:
    """A drop-in changes one import and nothing else: the gym shim, as ManiSkill's module, and the
    package leave the global start method unset (``None``) and do not import TorchRL (whose own
    import sets ``"spawn"`` when nothing is set: TorchRL's choice, checked here too)."""
    code = (
        "import multiprocessing as mp, sys\n"
        "import maniskill_torchrl.wrappers.gymnasium, maniskill_torchrl.wrappers.action_repeat\n"
        "import maniskill_torchrl\n"
        "print(mp.get_start_method(allow_none=True), 'torchrl' in sys.modules, end=' ')\n"
        "import torchrl\n"
        "print(mp.get_start_method(allow_none=True))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["None", "False", "spawn"], out.stdout + out.stderr


_PRELOAD_SCRIPT = """
import multiprocessing as mp, sys
from maniskill_torchrl._internal.mp import preload_forkserver

def imported(name, queue):
    queue.put(name in sys.modules)

def child_has(name):
    ctx = mp.get_context("forkserver")
    queue = ctx.Queue()
    process = ctx.Process(target=imported, args=(name, queue))
    process.start()
    process.join(60)
    return queue.get(timeout=60)

if __name__ == "__main__":
    mp.set_forkserver_preload(["__main__", "wave"])  # the user's own list is kept
    print(preload_forkserver(["colorsys"]), child_has("colorsys"), child_has("wave"), child_has("__main__"))
    # the forkserver runs now: its imports are fixed
    print(preload_forkserver(["colorsys"]), preload_forkserver(["tabnanny"]), child_has("tabnanny"))
"""


def test_preload_forkserver(tmp_path) -> None:
    """The forkserver imports the modules once: its children start with them; a running one keeps its own."""
    script = tmp_path / "preload.py"
    script.write_text(_PRELOAD_SCRIPT)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split("\n")[:2] == ["True True True True", "True False False"], out.stdout


def _maniskill_worker():
    from maniskill_torchrl import CPUUnbatch, ManiSkillEnv

    return TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=5), CPUUnbatch())


@pytest.mark.slow
def test_maniskill_workers_match_serial_env() -> None:
    """Two ManiSkill workers give what the same two envs give in-process (SerialEnv), bit for bit."""
    env = ManiSkillParallelEnv(2, _maniskill_worker)
    ref_env = SerialEnv(2, _maniskill_worker)
    try:
        got = run_maniskill(env)
        ref = run_maniskill(ref_env)
    finally:
        env.close()
        ref_env.close()
    assert got["next", "done"].any()
    for key in ref.keys(True, True):
        torch.testing.assert_close(got[key], ref[key], rtol=0, atol=0, msg=lambda m, k=key: f"{k}: {m}")


def run_maniskill(env, steps: int = 8) -> TensorDict:
    env.set_seed(5)
    td = env.reset()
    g = torch.Generator().manual_seed(2)
    out = []
    for _ in range(steps):
        td.set("action", torch.rand(env.batch_size + (8,), generator=g) * 2 - 1)
        step, td = env.step_and_maybe_reset(td)
        out.append(step.clone())
    return torch.stack(out, -1)


def test_workers_fork_from_a_preloaded_forkserver(monkeypatch) -> None:
    """The env's workers start with the forkserver, which it asks to import TorchRL's worker and ManiSkill
    (the tests' own forkserver already has: here the call is recorded, not made)."""
    import maniskill_torchrl.parallel as parallel_module

    asked = []
    monkeypatch.setattr(parallel_module, "preload_forkserver", lambda modules: asked.append(tuple(modules)))
    env = ManiSkillParallelEnv(1, SeededToy)
    try:
        env.reset()
    finally:
        env.close()
    assert env._mp_start_method == "forkserver"
    assert asked == [parallel_module.WORKER_IMPORTS] and "mani_skill.envs" in asked[0]
