"""Boundary helpers of the gym shim: ManiSkill env checks and torch -> unbatched numpy."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch

from maniskill_torchrl._internal.sim import maniskill_base_env

__all__ = ["np_unbatch", "require_maniskill_env"]


def np_unbatch(x: Any) -> Any:
    """``mani_skill.utils.common.unbatch(common.to_numpy(x))`` in one pass, same types.

    Dicts are rebuilt as plain dicts; torch tensors go to numpy (sharing memory on
    the CPU, as ManiSkill's ``to_numpy`` does); a ``(1,)``-shaped array becomes a
    python scalar (``.item()``), any other array with a leading dim of 1 loses it;
    python ``bool`` / ``int`` / ``float`` / ``str`` pass through; anything else goes
    through ``np.array`` first (a numpy scalar becomes a 0-d array).
    """
    if isinstance(x, torch.Tensor):
        try:
            a = x.numpy()  # CPU tensors: a zero-copy view, as ManiSkill's x.cpu().numpy()
        except TypeError:  # on an accelerator
            a = x.cpu().numpy()
    elif isinstance(x, dict):
        return {k: np_unbatch(v) for k, v in x.items()}
    elif isinstance(x, np.ndarray):
        a = x
    elif isinstance(x, (bool, str, float, int)):
        return x
    else:
        a = np.array(x)
    shape = a.shape
    if shape == (1,):
        return a.item()
    if shape and shape[0] == 1:
        return a.squeeze(0)
    return a


def require_maniskill_env(env: Any, wrapper: str):
    """The ManiSkill ``BaseEnv`` under ``env``; a TypeError naming the fix otherwise."""
    base = maniskill_base_env(env) if isinstance(env, gym.Env) else None
    if base is None:
        raise TypeError(
            f"{wrapper} wraps ManiSkill 3 envs only, got {type(env).__name__} "
            f"(unwrapped: {type(getattr(env, 'unwrapped', env)).__name__}). Make the env with "
            "gym.make('PickCube-v1', num_envs=1, ...) after `import mani_skill.envs`."
        )
    return base
