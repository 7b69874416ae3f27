"""Action repeat's rules, written once, on torch alone: the core of the transform, the gym shim
and the engine.

- :func:`check_repeat`: the one check of a repeat count (the transform, the gym shim, the engine).
- :func:`keep_where`: an env that has ended keeps its last real step; the rule per tensor of the
  TorchRL :class:`~maniskill_torchrl.transforms.ActionRepeat` transform (its ``merge_step`` on
  TensorDicts) and of :func:`repeat_step`.
- :func:`repeat_step`: one step of ManiSkill's ``ActionRepeatWrapper`` directly on ManiSkill's
  dicts. The gym shim's :class:`~maniskill_torchrl.wrappers.ActionRepeatWrapper` steps with it,
  and so does each CPU engine worker told to repeat actions, which thus needs neither the gym
  shim nor TorchRL nor tensordict (1-2 s of imports): keep this module on torch alone.
"""

from __future__ import annotations

import numbers
from typing import Any

import torch

__all__ = ["check_repeat", "expand_mask", "keep_where", "repeat_step"]


def check_repeat(repeat: object) -> int:
    """``repeat`` as an int >= 1.

    Raises:
        TypeError: ``repeat`` is not an int (``bool`` included; numpy ints are fine).
        ValueError: ``repeat < 1``.
    """
    if isinstance(repeat, bool) or not isinstance(repeat, numbers.Integral):
        raise TypeError(
            "repeat must be an int >= 1 (inner steps per step; 1 means no repeat), got "
            f"{type(repeat).__name__} {repeat!r}; pass e.g. repeat=2."
        )
    if repeat < 1:
        raise ValueError(
            f"repeat must be >= 1, got {repeat}: an int >= 1 counts the inner steps per step (1 means no repeat)."
        )
    return int(repeat)


def expand_mask(mask: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``mask`` (batch-shaped) with trailing dims of 1 to broadcast against ``like``."""
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))


def keep_where(mask: torch.Tensor, new: torch.Tensor, old: torch.Tensor) -> torch.Tensor:
    """``new`` for the envs in ``mask`` (batch-shaped, leading dims), ``old`` for the others."""
    return torch.where(expand_mask(mask, new), new, old)


def _merge(acc: Any, new: Any, running: torch.Tensor | None, batch: int) -> Any:
    """``new`` for the envs in ``running`` (all if ``None``), ``acc`` for the others; a new object.

    As ManiSkill's wrapper: batched tensors (leading dim ``batch``) are merged per
    env, dicts key by key (``acc``'s keys first), and any other value (python
    scalars, unbatched tensors) is the last inner step's.
    """
    if isinstance(new, dict) and isinstance(acc, dict):
        out = dict(acc)
        for k, v in new.items():
            out[k] = _merge(acc[k], v, running, batch) if k in acc else v
        return out
    if (
        running is not None
        and isinstance(new, torch.Tensor)
        and isinstance(acc, torch.Tensor)
        and new.ndim
        and new.shape[0] == batch
    ):
        return keep_where(running, new, acc)
    return new


def repeat_step(env: Any, action: Any, repeat: int) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
    """``env.step(action)`` up to ``repeat`` times, per env never past its episode's end.

    Per env of the batch: reward summed over the inner steps it really took, ``terminated`` /
    ``truncated`` OR'ed, observation and info entries of its last real step (info values that
    are not batched tensors: the last inner step's). Stops once every env is done.

    Raises:
        TypeError: ``env``'s outputs are not ManiSkill's batched torch tensors.
    """
    first = env.step(action)
    if repeat == 1:
        return first
    obs, reward, terminated, truncated, info = first
    if not isinstance(terminated, torch.Tensor):
        raise TypeError(
            "ActionRepeatWrapper needs ManiSkill's batched torch outputs, got terminated of "
            f"type {type(terminated).__name__}. Apply it before CPUGymWrapper or any wrapper "
            "that converts to numpy."
        )
    done = terminated | truncated
    # One host sync per inner step: the number of envs done.
    n_done = int(done.sum())
    if n_done == done.numel():
        return first
    batch = done.shape[0]
    running = ~done if n_done else None
    for _ in range(repeat - 1):
        o, r, te, tr, inf = env.step(action)
        obs, info = _merge(obs, o, running, batch), _merge(info, inf, running, batch)
        if running is None:  # every env ran: a plain fold
            reward, terminated, truncated = reward + r, terminated | te, truncated | tr
        else:
            reward = keep_where(running, reward + r, reward)
            terminated = keep_where(running, terminated | te, terminated)
            truncated = keep_where(running, truncated | tr, truncated)
        done = terminated | truncated
        n_done = int(done.sum())
        if n_done == done.numel():
            break
        running = ~done if n_done else None
    return obs, reward, terminated, truncated, info
