"""Shared fixtures: ManiSkill envs on the CPU sim are costly to build (about 0.4 s), so
module-scoped fixtures share them where a test allows; every comparison seeds every reset."""
from __future__ import annotations

import warnings

import gymnasium as gym
import pytest
import torch

import mani_skill.envs  # noqa: F401  (registers the tasks)

warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")
warnings.filterwarnings("ignore", module="mani_skill")


def make_gym_env(env_id: str = "PickCube-v1", **kwargs) -> gym.Env:
    """A single CPU ManiSkill env made as users make it."""
    kwargs.setdefault("num_envs", 1)
    return gym.make(env_id, **kwargs)


def random_actions(space: gym.Space, n: int, seed: int = 0) -> list:
    """``n`` reproducible actions (torch tensors, or dicts of them) for an unbatched action space."""
    g = torch.Generator().manual_seed(seed)

    def one(sp):
        if isinstance(sp, gym.spaces.Dict):
            return {k: one(v) for k, v in sp.spaces.items()}
        low = torch.as_tensor(sp.low, dtype=torch.float32)
        high = torch.as_tensor(sp.high, dtype=torch.float32)
        return low + (high - low) * torch.rand(sp.shape, generator=g)

    return [one(space) for _ in range(n)]


@pytest.fixture(scope="session")
def torch_single_thread():
    torch.set_num_threads(1)
