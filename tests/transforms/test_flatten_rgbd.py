"""FlattenRGBD against ManiSkill's FlattenRGBDObservationWrapper, bit for bit: every option, the specs,
a batched CPU env with partial resets (per env, ManiSkill's wrapper over a lone env), stored data."""

from __future__ import annotations

import pytest
import torch
from mani_skill.utils.wrappers import FlattenObservationWrapper, FlattenRGBDObservationWrapper
from torchrl.envs import TransformedEnv, check_env_specs

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.transforms import CPUUnbatch, FlattenRGBD
from support.helpers import close_envs, make_gym_env

EPISODE = 3


def _pair(task: str, mode: str, **options):
    ref = FlattenRGBDObservationWrapper(
        make_gym_env(task, obs_mode=mode, render_backend="cpu", max_episode_steps=EPISODE), **options
    )
    env = TransformedEnv(
        ManiSkillEnv(task, obs_mode=mode, sim_backend="cpu", max_episode_steps=EPISODE), FlattenRGBD(**options)
    )
    return ref, env


def _same(ref_obs: dict, td, what: str) -> None:
    assert set(ref_obs) <= set(td.keys()), f"{what}: {sorted(ref_obs)} not all in {sorted(td.keys())}"
    for key, value in ref_obs.items():
        assert td[key].dtype == value.dtype and torch.equal(td[key], value), f"{what}: {key!r} differs"


@pytest.mark.pictures  # renders its cameras
@pytest.mark.parametrize(
    "task,mode,options",
    [
        ("PushCube-v1", "rgbd", {}),
        ("PushCube-v1", "rgbd", {"sep_depth": False}),
        ("PushCube-v1", "rgbd", {"rgb": False}),
        ("PushCube-v1", "rgbd", {"state": False}),
        ("PickCube-v1", "rgb", {}),  # no depth camera: the depth option turns itself off; a bool in the state
    ],
)
def test_the_observations_and_specs_are_maniskills(task, mode, options):
    ref, env = _pair(task, mode, **options)
    try:
        obs, _ = ref.reset(seed=4)
        env.set_seed(4)
        td = env.reset()
        _same(obs, td, "reset")
        for key, value in obs.items():
            spec = env.observation_spec[key]
            assert spec.shape == value.shape and spec.dtype == value.dtype and spec.is_in(td[key]), key
        for key in ("sensor_data", "sensor_param", "agent", "extra"):
            assert key not in env.observation_spec.keys() and key not in td.keys(), key
        for t in range(EPISODE + 1):
            action = torch.full((1, env.action_spec.shape[-1]), 0.3 - 0.2 * t)
            obs, *_ = ref.step(action)
            td = env.step(td.set("action", action))["next"]
            _same(obs, td, f"step {t}")
    finally:
        close_envs([ref, env])


@pytest.mark.pictures  # renders its cameras
def test_a_batched_cpu_env_with_partial_resets_is_each_envs_wrapper():
    """ManiSkillEnv(num_envs=2) through TorchRL's auto-reset (partial resets, episodes of different lengths):
    each env's stacked data is ManiSkill's wrapper over a lone env with that env's seeds and actions."""
    env = TransformedEnv(
        ManiSkillEnv("PushCube-v1", num_envs=2, obs_mode="rgbd", sim_backend="cpu", max_episode_steps=EPISODE),
        FlattenRGBD(),
    )
    refs = [
        FlattenRGBDObservationWrapper(
            make_gym_env("PushCube-v1", obs_mode="rgbd", render_backend="cpu", max_episode_steps=EPISODE)
        )
        for _ in range(2)
    ]
    try:
        env.set_seed(8)
        actions = torch.linspace(-1, 1, 2 * 8 * 5).reshape(5, 2, 8)
        steps = iter(actions)
        data = env.rollout(5, lambda td: td.set("action", next(steps)), break_when_any_done=False)
        for i, ref in enumerate(refs):
            obs, _ = ref.reset(seed=8 + i)
            _same({k: v[0] for k, v in obs.items()}, data[i, 0], f"env {i} reset")
            for t in range(5):
                obs, _, term, trunc, _ = ref.step(actions[t, i : i + 1])
                _same({k: v[0] for k, v in obs.items()}, data[i, t]["next"], f"env {i} step {t}")
                if bool(term | trunc):
                    break  # the next episode's seed is the library's draw: the first one is enough here
    finally:
        close_envs([env, *refs])


@pytest.mark.pictures  # renders its cameras
def test_check_env_specs_after_cpu_unbatch_and_on_stored_data():
    env = TransformedEnv(ManiSkillEnv("PushCube-v1", obs_mode="rgbd", sim_backend="cpu"), CPUUnbatch())
    env.append_transform(FlattenRGBD())
    try:
        check_env_specs(env)
        assert env.observation_spec["rgb"].shape == (128, 128, 3)
        # stored data (a replay buffer's transform): the root and "next" alike
        raw = TransformedEnv(ManiSkillEnv("PushCube-v1", obs_mode="rgbd", sim_backend="cpu"), CPUUnbatch())
        try:
            raw.set_seed(2)
            env.set_seed(2)
            stored = raw.rollout(2, lambda td: td.set("action", torch.zeros(8)))
            live = env.rollout(2, lambda td: td.set("action", torch.zeros(8)))
            flat = FlattenRGBD()(stored)
            for key in ("rgb", "depth", "state"):
                assert torch.equal(flat[key], live[key]) and torch.equal(flat["next", key], live["next", key]), key
            assert "sensor_data" not in flat.keys() and "sensor_data" not in flat["next"].keys()
        finally:
            raw.close()
    finally:
        env.close()


def test_an_env_without_cameras_says_which_obs_mode_to_use():
    env = TransformedEnv(ManiSkillEnv("PushCube-v1", obs_mode="state_dict", sim_backend="cpu"), FlattenRGBD())
    try:
        with pytest.raises(KeyError, match="obs_mode='rgb', 'depth' or 'rgbd'"):
            _ = env.observation_spec
    finally:
        env.close()


@pytest.mark.parametrize("task", ["PushCube-v1", "PickCube-v1"])
def test_state_only_is_maniskills_flattened_state(task):
    """rgb=False, depth=False, state_key="observation" on a state_dict env: ManiSkill's flattened state (what
    obs_mode="state" gives, BaseEnv's own flatten_state_dict), its spec, at reset and steps; a bool entry
    (PickCube-v1's is_grasped) promoted as ManiSkill promotes it. ManiSkill 3.0.1's FlattenObservationWrapper
    fails to build (its flatten_state_dict on numpy data: AttributeError); where it builds, it is checked too."""
    try:
        wrapped = FlattenObservationWrapper(make_gym_env(task, obs_mode="state_dict", max_episode_steps=EPISODE))
    except AttributeError:
        wrapped = None
    ref = make_gym_env(task, obs_mode="state", max_episode_steps=EPISODE)
    env = TransformedEnv(
        ManiSkillEnv(task, obs_mode="state_dict", sim_backend="cpu", max_episode_steps=EPISODE),
        FlattenRGBD(rgb=False, depth=False, state_key="observation"),
    )
    try:
        check_env_specs(env)
        obs, _ = ref.reset(seed=6)
        env.set_seed(6)
        td = env.reset()
        spec = env.observation_spec["observation"]
        assert spec.shape == obs.shape and spec.dtype == obs.dtype
        assert td["observation"].dtype == obs.dtype and torch.equal(td["observation"], obs)
        if wrapped is not None:
            assert torch.equal(wrapped.reset(seed=6)[0], obs)
        for t in range(EPISODE):
            action = torch.full((1, 8), 0.25 * (t - 1))
            obs, *_ = ref.step(action)
            td = env.step(td.set("action", action))["next"]
            assert torch.equal(td["observation"], obs), f"step {t}"
            if wrapped is not None:
                assert torch.equal(wrapped.step(action)[0], obs), f"step {t}"
    finally:
        close_envs([e for e in (ref, env, wrapped) if e is not None])
