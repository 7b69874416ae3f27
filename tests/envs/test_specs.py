"""gymnasium spaces and ManiSkill info dicts -> TorchRL specs (no simulator needed)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.data import Bounded, Categorical, Composite, Unbounded

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.envs.maniskill import _info_spec as info_spec_from_infos
from maniskill_torchrl.envs.maniskill import _space_to_spec as space_to_spec

CPU = torch.device("cpu")
B = torch.Size([3])


def test_bounded_box():
    low = np.array([-1.0, -2.0], dtype=np.float32)
    high = np.array([1.0, 0.5], dtype=np.float32)
    spec = space_to_spec(gym.spaces.Box(low, high), B, CPU)
    assert isinstance(spec, Bounded)
    assert spec.shape == (3, 2) and spec.dtype == torch.float32
    assert torch.equal(spec.space.low, torch.tensor(low).expand(3, 2))
    assert torch.equal(spec.space.high, torch.tensor(high).expand(3, 2))
    sample = spec.rand()
    assert spec.is_in(sample)


def test_unbounded_box():
    spec = space_to_spec(gym.spaces.Box(-np.inf, np.inf, (4,), np.float32), B, CPU)
    assert isinstance(spec, Unbounded) and spec.shape == (3, 4) and spec.dtype == torch.float32
    # Partly infinite bounds cannot be a Bounded spec either.
    low = np.array([0.0, -np.inf], dtype=np.float32)
    spec = space_to_spec(gym.spaces.Box(low, np.float32(1.0)), B, CPU)
    assert isinstance(spec, Unbounded)


@pytest.mark.parametrize(
    "np_dtype, torch_dtype",
    [(np.uint8, torch.uint8), (np.int16, torch.int16), (np.float64, torch.float64), (np.int32, torch.int32)],
)
def test_box_dtypes_kept(np_dtype, torch_dtype):
    space = gym.spaces.Box(0, 255 if np_dtype == np.uint8 else 10, (2, 2, 3), np_dtype)
    spec = space_to_spec(space, B, CPU)
    assert spec.dtype == torch_dtype and spec.shape == (3, 2, 2, 3)
    assert spec.space.high.dtype == torch_dtype


def test_bool_box():
    spec = space_to_spec(gym.spaces.Box(0, 1, (2,), dtype=bool), B, CPU)
    assert isinstance(spec, Categorical) and spec.dtype == torch.bool and spec.shape == (3, 2)
    assert spec.is_in(torch.tensor([[True, False]] * 3))


def test_nested_dict():
    space = gym.spaces.Dict(
        agent=gym.spaces.Dict(
            qpos=gym.spaces.Box(-np.inf, np.inf, (9,), np.float32),
            qvel=gym.spaces.Box(-np.inf, np.inf, (9,), np.float32),
        ),
        extra=gym.spaces.Dict(is_grasped=gym.spaces.Box(0, 1, (), dtype=bool)),
        sensor_data=gym.spaces.Dict(base_camera=gym.spaces.Dict(rgb=gym.spaces.Box(0, 255, (8, 8, 3), np.uint8))),
    )
    spec = space_to_spec(space, B, CPU)
    assert isinstance(spec, Composite) and spec.shape == B
    assert spec["agent", "qpos"].shape == (3, 9)
    assert spec["extra", "is_grasped"].shape == (3,) and spec["extra", "is_grasped"].dtype == torch.bool
    assert spec["sensor_data", "base_camera", "rgb"].dtype == torch.uint8
    assert spec["sensor_data", "base_camera"].shape == B
    td = spec.rand()
    assert spec.is_in(td)


@pytest.fixture(scope="module")
def state_env():
    env = ManiSkillEnv("PickCube-v1", obs_mode="state")
    yield env
    env.close()


def test_box_observation_goes_to_observation(state_env):
    spec = state_env.observation_spec
    assert "observation" in spec.keys() and spec["observation"].shape == (1, 42)


def test_empty_batch():
    spec = space_to_spec(gym.spaces.Box(-1, 1, (2,), np.float32), torch.Size([]), CPU)
    assert spec.shape == (2,)


def test_unsupported_space():
    for space in (gym.spaces.Text(5), gym.spaces.Discrete(5)):
        with pytest.raises(TypeError, match="Box and Dict spaces only"):
            space_to_spec(space, B, CPU)


def test_info_spec():
    infos = {
        "success": torch.zeros(3, dtype=torch.bool),
        "elapsed_steps": torch.zeros(3, dtype=torch.int32),
        "dist": torch.zeros(3, 2),
        "reconfigure": False,  # python value: not per-env data
        "scalar": torch.tensor(1.0),  # no batch dim
        "wrong_batch": torch.zeros(4),
        "nested": {"a": torch.ones(3), "skip": "text"},
        "empty": {"skip": 1},
    }
    spec = info_spec_from_infos(infos, B, CPU)
    assert set(spec.keys()) == {"success", "elapsed_steps", "dist", "nested"}
    assert spec["success"].dtype == torch.bool and spec["success"].shape == (3,)
    assert isinstance(spec["success"], Categorical)
    assert spec["elapsed_steps"].dtype == torch.int32
    assert spec["dist"].shape == (3, 2)
    assert list(spec["nested"].keys()) == ["a"]


def test_done_and_reward_specs(state_env):
    d = state_env.full_done_spec
    assert set(d.keys()) == {"done", "terminated", "truncated"}
    for k in d.keys():
        assert d[k].shape == (1, 1) and d[k].dtype == torch.bool
    r = state_env.reward_spec
    assert r.shape == (1, 1) and r.dtype == torch.float32
