"""``check_maniskill_env`` checks every compared reset and step against the env's specs and
device, and ``assert_on_device`` as users call it.

The broken tasks are registered here as users register theirs (``@register_env``): a
``PushCube-v1`` whose observation turns float64 from its third reset, and one whose reward holds
two values per env. TorchRL's own ``check_env_specs`` is the oracle for the first: it catches the
float64 observation once it resets that often.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from mani_skill.envs.tasks.tabletop.push_cube import PushCubeEnv
from mani_skill.utils.registration import register_env
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from maniskill_torchrl import ManiSkillEnv, ManiSkillWrapper
from maniskill_torchrl._private import entries, new_tensordict
from maniskill_torchrl.testing import __all__ as testing_all
from maniskill_torchrl.testing import assert_on_device, check_maniskill_env

SEED = 3
EPISODE = 4  # steps per episode: resets come every EPISODE steps


@register_env("TestFloat64ObsFromThirdResetPushCube-v1", max_episode_steps=EPISODE)
class Float64ObsFromThirdReset(PushCubeEnv):
    """PushCube whose flat observation turns float64 from its third reset on (ManiSkill's own
    reset inside ``__init__`` not counted)."""

    resets = None  # None while ManiSkill's __init__ runs

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.resets = 0

    def reset(self, seed=None, options=None):
        if self.resets is not None:
            self.resets += 1
        return super().reset(seed=seed, options=options)

    def get_obs(self, info=None, unflattened=False):
        obs = super().get_obs(info, unflattened)
        if self.resets is not None and self.resets >= 3 and torch.is_tensor(obs):
            return obs.to(torch.float64)
        return obs


@register_env("TestTwoRewardsPushCube-v1", max_episode_steps=EPISODE)
class TwoRewardsPushCube(PushCubeEnv):
    """PushCube whose reward holds two values per env: shape [num_envs, 2]."""

    def compute_normalized_dense_reward(self, obs, action, info):
        reward = super().compute_normalized_dense_reward(obs, action, info)
        return torch.stack([reward, 1 - reward], dim=-1)


# ----------------------------------------------------------------------------- check_maniskill_env
def test_observation_off_its_spec_from_the_third_reset_is_named():
    env_id = "TestFloat64ObsFromThirdResetPushCube-v1"
    # The oracle: TorchRL's check_env_specs sees it once the env has reset three times.
    env = ManiSkillEnv(env_id, obs_mode="state")
    try:
        spec = env.observation_spec["observation"]
        check_env_specs(env, seed=SEED)
        env.reset(seed=SEED)
        with pytest.raises(AssertionError):
            check_env_specs(env, seed=SEED)
    finally:
        env.close()
    third = f"reset 2 with seed {SEED + 2000}"  # reset k uses seed + 1000 k
    shape = list(spec.shape)
    message = re.escape(
        f"check_maniskill_env('{env_id}', num_envs=1), {third}: 'observation' has dtype torch.float64 "
        f"and shape {shape}, off its observation spec {type(spec).__name__}(shape={shape}, "
        f"dtype={spec.dtype}, device=cpu)"
    )
    with pytest.raises(AssertionError, match=message):
        check_maniskill_env(env_id, steps=4 * EPISODE, seed=SEED, obs_mode="state")


def test_reward_of_the_wrong_shape_is_named():
    env_id = "TestTwoRewardsPushCube-v1"
    env = ManiSkillEnv(env_id, obs_mode="state")
    try:
        spec = env.full_reward_spec["reward"]
    finally:
        env.close()
    message = re.escape(
        f"check_maniskill_env('{env_id}', num_envs=1), step 0: 'reward': the task's reward has shape "
        f"[1, 2] (2 values per env), but the reward spec {type(spec).__name__}(shape={list(spec.shape)}, "
        f"dtype={spec.dtype}, device=cpu) holds 1 per env"
    )
    with pytest.raises(AssertionError, match=message):
        check_maniskill_env(env_id, steps=2, seed=SEED, obs_mode="state")


def test_a_leaf_off_the_env_device_is_named(monkeypatch):
    """A step whose TensorDict says CPU while one leaf is elsewhere (a label set without moving the
    leaves, as ``TensorDict._new_unsafe`` allows): named with its device, at its step."""
    step = ManiSkillWrapper._step

    def stray_leaf(self, tensordict):
        out = step(self, tensordict)
        if int(self.unwrapped.elapsed_steps[0]) == 2:
            entries(out)["success"] = out["success"].to("meta")
        return out

    monkeypatch.setattr(ManiSkillWrapper, "_step", stray_leaf)
    with pytest.raises(
        AssertionError,
        match=r"check_maniskill_env\('PushCube-v1', num_envs=1\), step 1: 1 leaf not on cpu: 'success' on meta",
    ):
        check_maniskill_env("PushCube-v1", steps=3, seed=SEED, obs_mode="state")


# ----------------------------------------------------------------------------- assert_on_device
def test_assert_on_device_passes_on_every_kind_of_output():
    td = TensorDict({"obs": torch.zeros(2, 3), ("next", "sensor", "rgb"): torch.zeros(2, 4, dtype=torch.uint8)}, [2])
    assert_on_device(td, "cpu")
    assert_on_device((td, torch.ones(1), {"a": {"b": torch.ones(2)}, "n": 3}, [np.zeros(2)]), torch.device("cpu"))
    assert_on_device(torch.zeros(1, device="meta"), "meta")
    assert "assert_on_device" in testing_all


def test_assert_on_device_lists_every_leaf_elsewhere():
    # The label says CPU; two leaves are on another device (the bug of issue 32, item 3).
    nested = new_tensordict({"rgb": torch.zeros(2, 4, device="meta")}, batch_size=[2], device="cpu")
    td = new_tensordict(
        {"obs": torch.zeros(2, 3), "pixels": torch.zeros(2, 4, device="meta"), "sensor": nested},
        batch_size=[2],
        device="cpu",
    )
    assert td.device == torch.device("cpu")
    with pytest.raises(
        AssertionError, match=r"^reset: 2 leaves not on cpu: 'pixels' on meta, \('sensor', 'rgb'\) on meta$"
    ):
        assert_on_device(td, "cpu", msg="reset")
    # Through tuples and mappings, the path names where; numpy arrays are host memory.
    with pytest.raises(
        AssertionError, match=r"3 leaves not on meta: \(0, 'obs'\) on cpu, \(1,\) on cpu, \(2, 'x'\) on numpy"
    ):
        assert_on_device(({"obs": torch.zeros(1)}, torch.zeros(1), {"x": np.zeros(1)}), "meta")
    with pytest.raises(AssertionError, match=r"1 leaf not on cuda:0: the tensor on cpu"):
        assert_on_device(torch.zeros(1), "cuda:0")
    with pytest.raises(TypeError, match="assert_on_device checks a TensorDict.*got a NoneType"):
        assert_on_device(None, "cpu")
