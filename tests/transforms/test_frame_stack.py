"""ManiSkill's FrameStack is TorchRL's CatFrames after an UnsqueezeTransform (the recipe of
docs/guides/wrappers.md), bit for bit: the layout ``[*batch, num_stack, *obs]``, oldest frame first,
the reset frame repeated at reset; per env on the batched CPU env with partial resets (TorchRL's
auto-reset), which ManiSkill's FrameStack refuses on the GPU sim; after FlattenRGBD, as ManiSkill's
diffusion-policy baseline stacks it."""

from __future__ import annotations

import pytest
import torch
from mani_skill.utils.wrappers import FlattenRGBDObservationWrapper, FrameStack
from torchrl.envs import CatFrames, Compose, TransformedEnv, UnsqueezeTransform

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.transforms import FlattenRGBD
from support.helpers import close_envs, make_gym_env

K, EPISODE = 3, 4


def _stack(key: str, ndim: int) -> list:
    """The recipe for one entry of ``ndim`` dims per env: a new dim before them, then K frames on it."""
    return [UnsqueezeTransform(-ndim - 1, in_keys=[key]), CatFrames(K, dim=-ndim - 1, in_keys=[key])]


def _run(ref, env, steps: int, width: int, keys: list[str]) -> None:
    obs, _ = ref.reset(seed=11)
    env.set_seed(11)
    td = env.reset()
    for t in range(steps):
        for key in keys:
            want = obs[key] if isinstance(obs, dict) else obs
            assert torch.equal(td[key], want), f"step {t}: {key!r}"
        action = torch.full((1, width), 0.4 - 0.15 * t)
        obs, _, term, trunc, _ = ref.step(action)
        td = env.step(td.set("action", action))
        if bool(term | trunc):  # the next episode: both reset with the same seed
            obs, _ = ref.reset(seed=12)
            env.set_seed(12)
            td = env.reset()
        else:
            td = td["next"]


def test_catframes_is_maniskills_frame_stack_on_state():
    ref = FrameStack(make_gym_env("PickCube-v1", obs_mode="state", max_episode_steps=EPISODE), K)
    env = TransformedEnv(
        ManiSkillEnv("PickCube-v1", obs_mode="state", sim_backend="cpu", max_episode_steps=EPISODE),
        Compose(*_stack("observation", 1)),
    )
    try:
        assert env.observation_spec["observation"].shape == ref.observation_space.shape == (1, K, 42)
        _run(ref, env, 2 * EPISODE + 2, 8, ["observation"])
    finally:
        close_envs([ref, env])


def test_partial_resets_stack_each_env_as_a_lone_frame_stack():
    """N=2, env 0 reset alone mid-episode (a "_reset" mask): env 1's frames stay a lone FrameStack's, and
    env 0's stack starts again from its reset frame, K times, as ManiSkill's rule does, then rolls."""
    env = TransformedEnv(
        ManiSkillEnv("PickCube-v1", num_envs=2, obs_mode="state", sim_backend="cpu", max_episode_steps=10),
        Compose(*_stack("observation", 1)),
    )
    ref = FrameStack(make_gym_env("PickCube-v1", obs_mode="state", max_episode_steps=10), K)
    try:
        env.set_seed(3)
        td = env.reset()
        obs = ref.reset(seed=3 + 1)[0]  # env 1's first seed
        latest: list[torch.Tensor] = []  # env 0's frames since its reset
        for t in range(6):
            assert torch.equal(td["observation"][1], obs[0]), f"env 1, step {t}"
            frames = td["observation"][0]
            latest.append(frames[-1])
            padded = [latest[0]] * (K - len(latest)) + latest[-K:]
            assert torch.equal(frames, torch.stack(padded[-K:])), f"env 0, step {t}"
            actions = torch.linspace(-0.5, 0.5, 16).reshape(2, 8) * (t + 1) / 4
            td = env.step(td.set("action", actions))["next"]
            obs = ref.step(actions[1:])[0]
            if t == 2:  # env 0 alone starts a new episode; env 1 goes on
                td = env.reset(td.set("_reset", torch.tensor([[True], [False]])))
                latest = []
    finally:
        close_envs([env, ref])


@pytest.mark.pictures
def test_after_flatten_rgbd_as_maniskills_visual_baselines_stack():
    """FrameStack(FlattenRGBDObservationWrapper(env), K): the rgb, depth and state entries, each stacked."""
    ref = FrameStack(
        FlattenRGBDObservationWrapper(
            make_gym_env("PushCube-v1", obs_mode="rgbd", render_backend="cpu", max_episode_steps=EPISODE)
        ),
        K,
    )
    env = TransformedEnv(
        ManiSkillEnv("PushCube-v1", obs_mode="rgbd", sim_backend="cpu", max_episode_steps=EPISODE),
        Compose(FlattenRGBD(), *_stack("state", 1), *_stack("rgb", 3), *_stack("depth", 3)),
    )
    try:
        for key in ("rgb", "depth", "state"):
            assert env.observation_spec[key].shape == ref.observation_space[key].shape, key
        _run(ref, env, EPISODE + 2, 8, ["rgb", "depth", "state"])
    finally:
        close_envs([ref, env])
