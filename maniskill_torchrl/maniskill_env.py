"""Deprecated path of ManiSkillEnv, kept for one release.

The ManiSkill adapter is one file, ``maniskill_torchrl/envs/maniskill.py``. Import
``from maniskill_torchrl import ManiSkillEnv`` instead; importing this module warns.
"""

from __future__ import annotations

import warnings

from maniskill_torchrl.envs.maniskill import ManiSkillEnv

__all__ = ["ManiSkillEnv"]

warnings.warn(
    "maniskill_torchrl.maniskill_env is deprecated and will be removed in the next release: the ManiSkill adapter "
    "moved to maniskill_torchrl.envs.maniskill. Use `from maniskill_torchrl import ManiSkillEnv`.",
    DeprecationWarning,
    stacklevel=2,
)
