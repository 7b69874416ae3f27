"""Finding the ManiSkill env under gym wrappers (no TorchRL import: the gym shim uses it too)."""
from __future__ import annotations

from typing import Any

__all__ = ["maniskill_base_env", "wrapper_attr"]


def maniskill_base_env(env: Any):
    """The ManiSkill ``BaseEnv`` under ``env`` (through any gym wrappers), or ``None``."""
    from mani_skill.envs.sapien_env import BaseEnv

    base = getattr(env, "unwrapped", None)
    return base if isinstance(base, BaseEnv) else None


def wrapper_attr(env: Any, name: str) -> Any:
    """An attribute from the outermost gym wrapper that defines it (ManiSkill's wrappers may override spaces)."""
    get = getattr(env, "get_wrapper_attr", None)
    return get(name) if get is not None else getattr(env, name)
