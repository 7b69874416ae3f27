"""FlattenActionSpace against ManiSkill's FlattenActionSpaceWrapper on a two-robot task, bit for bit: the flat
action's bounds, and the episodes a flat action gives (one env, and the batched CPU env)."""

from __future__ import annotations

import pytest
import torch
from mani_skill.utils.wrappers import FlattenActionSpaceWrapper
from torchrl.envs import TransformedEnv, check_env_specs

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.transforms import FlattenActionSpace
from support.helpers import close_envs, make_gym_env

TASK, EPISODE = "TwoRobotPickCube-v1", 4


def _actions(n: int, steps: int) -> torch.Tensor:
    # distinct per agent, so that a swapped or misaligned cut changes the episode
    return torch.sin(torch.arange(steps * n * 16, dtype=torch.float32) * 0.37).reshape(steps, n, 16)


def test_the_flat_action_steps_as_maniskills_wrapper():
    ref = FlattenActionSpaceWrapper(make_gym_env(TASK, obs_mode="state", max_episode_steps=EPISODE))
    env = TransformedEnv(
        ManiSkillEnv(TASK, obs_mode="state", sim_backend="cpu", max_episode_steps=EPISODE), FlattenActionSpace()
    )
    try:
        spec = env.action_spec
        assert spec.shape == (1, 16)
        assert torch.equal(spec.space.low[0], torch.as_tensor(ref.single_action_space.low))
        assert torch.equal(spec.space.high[0], torch.as_tensor(ref.single_action_space.high))
        obs, _ = ref.reset(seed=5)
        env.set_seed(5)
        td = env.reset()
        assert torch.equal(td["observation"], obs)
        for t, action in enumerate(_actions(1, EPISODE)):
            obs, reward, *_ = ref.step(action)
            td = env.step(td.set("action", action))
            assert torch.equal(td["action"], action), "the user's flat action is left as it was"
            assert torch.equal(td["next", "observation"], obs), f"step {t}"
            assert torch.equal(td["next", "reward"].reshape(-1), reward.reshape(-1).to(td["next", "reward"].dtype))
            td = td["next"]
    finally:
        close_envs([ref, env])


def test_check_env_specs_and_the_batched_cpu_env():
    env = TransformedEnv(
        ManiSkillEnv(TASK, num_envs=2, obs_mode="state", sim_backend="cpu", max_episode_steps=EPISODE),
        FlattenActionSpace(),
    )
    refs = [
        FlattenActionSpaceWrapper(make_gym_env(TASK, obs_mode="state", max_episode_steps=EPISODE)) for _ in range(2)
    ]
    try:
        check_env_specs(env)
        env.set_seed(9)
        actions = _actions(2, EPISODE - 1)
        steps = iter(actions)
        data = env.rollout(EPISODE - 1, lambda td: td.set("action", next(steps)))
        for i, ref in enumerate(refs):
            obs, _ = ref.reset(seed=9 + i)
            assert torch.equal(data[i, 0]["observation"], obs[0])
            for t in range(EPISODE - 1):
                obs, *_ = ref.step(actions[t, i : i + 1])
                assert torch.equal(data[i, t]["next", "observation"], obs[0]), f"env {i}, step {t}"
    finally:
        close_envs([env, *refs])


def test_a_box_action_needs_no_flattening():
    env = TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state", sim_backend="cpu"), FlattenActionSpace())
    try:
        with pytest.raises(TypeError, match="already one"):
            _ = env.action_spec
    finally:
        env.close()
