"""The gym shim's CPUGymWrapper in the stacks ManiSkill's own baselines build, bit for bit against the same
stacks over ManiSkill's CPUGymWrapper (issue 63, item 2):

- ManiSkill's ``FrameStack`` under ``CPUGymWrapper`` (the batched env stacked, then unbatched);
- the diffusion-policy CPU stack (``examples/baselines/diffusion_policy/diffusion_policy/make_env.py``):
  ``CPUGymWrapper`` -> ``RecordEpisode`` (trajectories saved) -> gymnasium's ``RecordEpisodeStatistics`` ->
  ``ClipAction`` -> ``FrameStackObservation``, in a ``SyncVectorEnv``; the trajectory files compared too.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np
import pytest
from mani_skill.utils.wrappers import CPUGymWrapper as MSCPUGymWrapper
from mani_skill.utils.wrappers import FrameStack, RecordEpisode

from maniskill_torchrl.wrappers import CPUGymWrapper
from support.helpers import assert_same, close_envs, make_gym_env

EPISODE, STACK = 5, 3


def _frame_stacked(cls):
    return cls(FrameStack(make_gym_env("PickCube-v1", obs_mode="state", max_episode_steps=EPISODE), STACK))


def test_frame_stack_under_cpu_gym_wrapper():
    envs = [_frame_stacked(MSCPUGymWrapper), _frame_stacked(CPUGymWrapper)]
    try:
        assert envs[1].observation_space == envs[0].observation_space
        rng = np.random.default_rng(1)
        for episode in range(2):
            outs = [env.reset(seed=30 + episode) for env in envs]
            assert_same(outs[0], outs[1], f"reset {episode}")
            assert outs[1][0].shape == (STACK, 42)
            for t in range(EPISODE):
                action = rng.uniform(-1, 1, 8).astype(np.float32)
                outs = [env.step(action.copy()) for env in envs]
                assert_same(outs[0], outs[1], f"episode {episode}, step {t}")
    finally:
        close_envs(envs)


def _diffusion_policy_thunk(cls, out_dir: Path):
    def thunk():
        env = make_gym_env("PickCube-v1", obs_mode="state", max_episode_steps=EPISODE)
        env = cls(env)
        env = RecordEpisode(env, output_dir=str(out_dir), save_trajectory=True, save_video=False)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        env = gym.wrappers.ClipAction(env)
        return gym.wrappers.FrameStackObservation(env, STACK)

    return thunk


def _h5(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


@pytest.mark.parametrize("num_envs", [2])
def test_the_diffusion_policy_cpu_stack(tmp_path, num_envs):
    venvs = [
        gym.vector.SyncVectorEnv(
            [_diffusion_policy_thunk(cls, tmp_path / cls.__module__.split(".")[0] / str(i)) for i in range(num_envs)]
        )
        for cls in (MSCPUGymWrapper, CPUGymWrapper)
    ]
    try:
        rng = np.random.default_rng(2)
        outs = [v.reset(seed=[40 + i for i in range(num_envs)]) for v in venvs]
        assert_same(outs[0], outs[1], "reset")
        for t in range(EPISODE):
            action = rng.uniform(-1.5, 1.5, (num_envs, 8)).astype(np.float32)  # past the bounds: ClipAction clips
            outs = [v.step(action.copy()) for v in venvs]
            for out in outs:  # RecordEpisodeStatistics' wall time: the machine's, not the env's
                out[4].get("episode", {}).pop("t", None)
            assert_same(outs[0], outs[1], f"step {t}")
        assert outs[1][3].all(), "the episodes are truncated at the end"
        assert outs[1][4]["episode"]["l"].tolist() == [EPISODE] * num_envs  # RecordEpisodeStatistics
    finally:
        for v in venvs:
            v.close()
    for i in range(num_envs):
        files = [sorted((tmp_path / name / str(i)).glob("*.h5")) for name in ("mani_skill", "maniskill_torchrl")]
        assert len(files[0]) == len(files[1]) == 1, files
        theirs, ours = _h5(files[0][0]), _h5(files[1][0])
        assert list(theirs) == list(ours) and theirs, f"env {i}: datasets {list(theirs)} vs {list(ours)}"
        for name in theirs:
            assert_same(theirs[name], ours[name], f"env {i}: {name}")
