"""ManiSkill 3 as a first-class TorchRL citizen.

- :class:`ManiSkillEnv` / :class:`ManiSkillWrapper`: ManiSkill tasks as TorchRL envs.
- :mod:`maniskill_torchrl.transforms`: ``ActionRepeat``, ``CPUUnbatch``,
  ``IgnoreTerminations``, ``EpisodeMetrics`` as TorchRL transforms.
- :mod:`maniskill_torchrl.wrappers`: drop-in ``CPUGymWrapper`` / ``ActionRepeatWrapper``.
"""
from maniskill_torchrl.env import ManiSkillEnv, ManiSkillWrapper
from maniskill_torchrl.transforms import (
    ActionRepeat,
    CPUUnbatch,
    EpisodeMetrics,
    IgnoreTerminations,
)

__version__ = "0.1.0"

__all__ = [
    "ActionRepeat",
    "CPUUnbatch",
    "EpisodeMetrics",
    "IgnoreTerminations",
    "ManiSkillEnv",
    "ManiSkillWrapper",
    "__version__",
]
