"""Deprecated path of ManiSkillWrapper, kept for one release.

The ManiSkill adapter is one file, ``maniskill_torchrl/envs/maniskill.py``. Import
``from maniskill_torchrl import ManiSkillWrapper`` instead; importing this module warns.
"""

from __future__ import annotations

import warnings

from maniskill_torchrl.envs.maniskill import ManiSkillWrapper

__all__ = ["ManiSkillWrapper"]

warnings.warn(
    "maniskill_torchrl.maniskill_wrapper is deprecated and will be removed in the next release: the ManiSkill adapter "
    "moved to maniskill_torchrl.envs.maniskill. Use `from maniskill_torchrl import ManiSkillWrapper`.",
    DeprecationWarning,
    stacklevel=2,
)
