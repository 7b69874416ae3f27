"""The env core: :class:`ManiSkillWrapper` and :class:`ManiSkillEnv` (``envs/maniskill.py``), one
ManiSkill adapter in one file, as TorchRL keeps its own (``torchrl/envs/libs/``)."""

from __future__ import annotations

from maniskill_torchrl.envs.maniskill import ManiSkillEnv, ManiSkillWrapper

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]
