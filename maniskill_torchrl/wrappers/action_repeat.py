"""Drop-in ``ActionRepeatWrapper``: ``mani_skill.utils.wrappers.ActionRepeatWrapper`` on the shared core.

Change ``from mani_skill.utils.wrappers import ActionRepeatWrapper`` to
``from maniskill_torchrl.wrappers import ActionRepeatWrapper``; the batched torch
outputs stay the same. Each step is ``maniskill_torchrl._internal.repeat.repeat_step``:
the inner steps merged by :func:`maniskill_torchrl._internal.repeat.keep_where`, the rule
of the TorchRL ``ActionRepeat`` transform, directly on ManiSkill's dicts (the CPU
engine's workers repeat actions with the same function).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.wrappers.action_repeat import (
    ActionRepeatWrapper as _ManiSkillActionRepeatWrapper,
)
from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper as _ManiSkillCPUGymWrapper

from maniskill_torchrl._internal.repeat import check_repeat, repeat_step
from maniskill_torchrl.wrappers._common import require_maniskill_env

__all__ = ["ActionRepeatWrapper"]


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
        super().__init__(env, check_repeat(repeat))

    @property
    def num_envs(self) -> int:
        return self.base_env.num_envs

    @property
    def base_env(self) -> BaseEnv:
        """The ManiSkill ``BaseEnv`` (``env.unwrapped``)."""
        return self.env.unwrapped

    def step(self, action: Any) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        return repeat_step(self.env, action, self.repeat)
