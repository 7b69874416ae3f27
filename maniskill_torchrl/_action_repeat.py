"""ManiSkill's masked action repeat on its batched torch outputs, written once.

One step of ManiSkill's ``ActionRepeatWrapper``, merged by
:func:`maniskill_torchrl.masked_merge.keep_where` (the rule of the TorchRL ``ActionRepeat``
transform) directly on ManiSkill's dicts. The gym shim's
:class:`~maniskill_torchrl.wrappers.ActionRepeatWrapper` steps with it, and so does each CPU
engine worker told to repeat actions, which thus needs neither the gym shim nor TorchRL.
"""

from __future__ import annotations

from typing import Any

import torch

from maniskill_torchrl.masked_merge import keep_where

__all__ = ["repeat_step"]


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
