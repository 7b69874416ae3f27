"""Drop-in ``ActionRepeatWrapper``: ``mani_skill.utils.wrappers.ActionRepeatWrapper`` on the shared core.

Change ``from mani_skill.utils.wrappers import ActionRepeatWrapper`` to
``from maniskill_torchrl.wrappers import ActionRepeatWrapper``; the batched torch
outputs stay the same. The inner steps are merged by
:func:`maniskill_torchrl.core.merge_step`, the same code as the TorchRL
``ActionRepeat`` transform.
"""
from __future__ import annotations

import numbers
from typing import Any

import gymnasium as gym
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.wrappers.action_repeat import (
    ActionRepeatWrapper as _ManiSkillActionRepeatWrapper,
)
from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper as _ManiSkillCPUGymWrapper
from tensordict import TensorDict, TensorDictBase

from maniskill_torchrl.core import any_done, merge_step
from maniskill_torchrl.wrappers._common import require_maniskill_env

__all__ = ["ActionRepeatWrapper"]

_REWARD_KEYS = ("reward",)
_DONE_KEYS = ("terminated", "truncated")


def _batched_part(d: dict, batch: int) -> dict:
    """The nested dict of ``d``'s tensors with a leading ``batch`` dim (what the merge handles)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, torch.Tensor):
            if v.ndim and v.shape[0] == batch:
                out[k] = v
        elif isinstance(v, dict):
            out[k] = _batched_part(v, batch)
    return out


def _rebuild(first: dict, last: dict, merged: TensorDictBase) -> dict:
    """``first``'s structure with merged tensors; other values from the last inner step.

    As ManiSkill's wrapper: batched tensors are merged per env, any other value
    (python scalars, unbatched tensors) is overwritten by each inner step.
    """
    out = {}
    for k, v in first.items():
        if isinstance(v, dict):
            out[k] = _rebuild(v, last.get(k, v), merged.get(k))
        elif k in merged.keys():
            out[k] = merged.get(k)
        else:
            out[k] = last.get(k, v)
    for k, v in last.items():
        if k not in out:
            out[k] = v
    return out


class ActionRepeatWrapper(_ManiSkillActionRepeatWrapper):
    """Repeats each action up to ``repeat`` times; batched torch in, batched torch out.

    The same wrapper as ManiSkill's ``ActionRepeatWrapper``, which it subclasses.
    One ``step(action)`` steps the env with ``action`` up to ``repeat`` times and
    returns, per env of the batch:

    - ``reward``: the sum over the inner steps the env really took;
    - ``terminated`` / ``truncated``: OR over those steps;
    - observation and info entries: the values at the env's last real step. An
      env that ends at inner step ``k`` keeps step ``k``'s data; nothing after
      its end leaks in. Info values that are not batched tensors come from the
      last inner step.

    It stops early once every env is done. Outputs keep ManiSkill's batched torch
    types (``[num_envs, ...]`` tensors, dict observations as dicts); unlike
    ManiSkill's, the first inner step's tensors are not modified in place.

    Why: a coarser control rate (frame skip) without changing the task.
    ``reset`` is the env's own.

    Args:
        env: a ManiSkill env (``gym.make(...)``), CPU or GPU sim, before any
            ``CPUGymWrapper`` (which turns the outputs into numpy).
        repeat: how many times each action is applied, ``>= 1`` (1: no repeat).

    Raises:
        TypeError: ``env`` is not a ManiSkill env or is already wrapped in a
            ``CPUGymWrapper``; ``repeat`` is not an int.
        ValueError: ``repeat < 1``.

    Examples:
        >>> import gymnasium as gym
        >>> import mani_skill.envs
        >>> from maniskill_torchrl.wrappers import ActionRepeatWrapper
        >>> env = ActionRepeatWrapper(gym.make("PickCube-v1", num_envs=1), repeat=3)
        >>> obs, info = env.reset(seed=0)
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> obs.shape, reward.shape, info["elapsed_steps"].tolist()
        (torch.Size([1, 42]), torch.Size([1]), [3])
        >>> env.close()
    """

    def __init__(self, env: gym.Env, repeat: int) -> None:
        require_maniskill_env(env, "ActionRepeatWrapper")
        inner = env
        while inner is not None:
            if isinstance(inner, _ManiSkillCPUGymWrapper):
                raise TypeError(
                    "ActionRepeatWrapper needs ManiSkill's batched torch outputs, but the env is "
                    f"already wrapped in {type(inner).__name__} (numpy outputs). Apply "
                    "ActionRepeatWrapper first: CPUGymWrapper(ActionRepeatWrapper(env, repeat))."
                )
            inner = getattr(inner, "env", None)
        if isinstance(repeat, bool) or not isinstance(repeat, numbers.Integral):
            raise TypeError(
                f"repeat must be an int >= 1, got {type(repeat).__name__} {repeat!r}; "
                "pass e.g. repeat=2."
            )
        if repeat < 1:
            raise ValueError(
                f"repeat must be >= 1, got {repeat}; repeat=1 applies each action once (no repeat)."
            )
        gym.Wrapper.__init__(self, env)
        self.repeat = int(repeat)

    @property
    def num_envs(self) -> int:
        return self.base_env.num_envs

    @property
    def base_env(self) -> BaseEnv:
        """The ManiSkill ``BaseEnv`` (``env.unwrapped``)."""
        return self.env.unwrapped

    def step(self, action: Any) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        first = self.env.step(action)
        if self.repeat == 1:
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
        batch_size = torch.Size((batch,))
        obs_is_dict = isinstance(obs, dict)

        def pack(o, r, te, tr, inf) -> TensorDict:
            return TensorDict._new_unsafe(
                {
                    "obs": _batched_part(o, batch) if obs_is_dict else o,
                    "reward": r,
                    "terminated": te,
                    "truncated": tr,
                    "info": _batched_part(inf, batch),
                },
                batch_size=batch_size,
            )

        acc = pack(*first)
        running = ~done if n_done else None
        last_obs, last_info = obs, info
        for _ in range(self.repeat - 1):
            last_obs, r, te, tr, last_info = self.env.step(action)
            acc = merge_step(acc, pack(last_obs, r, te, tr, last_info), running, _REWARD_KEYS, _DONE_KEYS)
            done = any_done(acc, _DONE_KEYS)
            n_done = int(done.sum())
            if n_done == done.numel():
                break
            running = ~done if n_done else None

        out_obs = _rebuild(obs, last_obs, acc.get("obs")) if obs_is_dict else acc.get("obs")
        return (
            out_obs,
            acc.get("reward"),
            acc.get("terminated"),
            acc.get("truncated"),
            _rebuild(info, last_info, acc.get("info")),
        )
