"""Deprecated path of :class:`~maniskill_torchrl.CPUVectorEnv`, kept for one release.

The CPU engine moved to ``maniskill_torchrl.engines`` (``engines/cpu_vector.py``). Import
``from maniskill_torchrl import CPUVectorEnv`` (or ``from maniskill_torchrl.engines import
CPUVectorEnv``) instead; importing this module warns.
"""

from __future__ import annotations

import warnings

from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv

__all__ = ["CPUVectorEnv"]

warnings.warn(
    "maniskill_torchrl.cpu_vector is deprecated and will be removed in the next release: the CPU engine "
    "moved to maniskill_torchrl.engines. Use `from maniskill_torchrl import CPUVectorEnv`.",
    DeprecationWarning,
    stacklevel=2,
)
