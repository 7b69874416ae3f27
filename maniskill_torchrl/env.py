"""ManiSkill 3 tasks as native TorchRL environments: the public home of both env classes.

- :class:`ManiSkillWrapper` (``maniskill_wrapper.py``): wraps a ManiSkill env made with
  ``gym.make`` (or a :class:`~maniskill_torchrl.CPUVectorEnv`).
- :class:`ManiSkillEnv` (``maniskill_env.py``): makes the ManiSkill env from a task id, then wraps it.

``from maniskill_torchrl.env import ManiSkillEnv, ManiSkillWrapper`` keeps working from here.
"""

from __future__ import annotations

from maniskill_torchrl.maniskill_env import ManiSkillEnv
from maniskill_torchrl.maniskill_wrapper import ManiSkillWrapper

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]
