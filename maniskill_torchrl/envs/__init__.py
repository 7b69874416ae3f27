"""ManiSkill tasks as TorchRL envs.

- :mod:`maniskill_torchrl.envs.maniskill`: the TorchRL adapter, one self-contained file bound for
  TorchRL's tree (``torchrl/envs/libs/maniskill.py``; see ``upstream/``).
- :mod:`maniskill_torchrl.envs.engine_env`: this library's :class:`ManiSkillWrapper` and
  :class:`ManiSkillEnv`, the adapter plus the batched CPU engine and the hooks of
  :mod:`maniskill_torchrl.envs.hooks`: what ``from maniskill_torchrl import ManiSkillEnv`` gives.
"""

from __future__ import annotations

from maniskill_torchrl import _register_dataset_prefix
from maniskill_torchrl.envs.engine_env import ManiSkillEnv, ManiSkillWrapper

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]

_register_dataset_prefix()  # TorchRL is imported now: the maniskill: prefix of its load_dataset
