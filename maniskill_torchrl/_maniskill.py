"""Finding the ManiSkill env under gym wrappers (no TorchRL import: the gym shim uses it too)."""
from __future__ import annotations

from typing import Any

__all__ = ["maniskill_base_env", "render_frame_shape", "wrapper_attr"]


def maniskill_base_env(env: Any):
    """The ManiSkill ``BaseEnv`` under ``env`` (through any gym wrappers), or ``None``."""
    from mani_skill.envs.sapien_env import BaseEnv

    base = getattr(env, "unwrapped", None)
    return base if isinstance(base, BaseEnv) else None


def wrapper_attr(env: Any, name: str) -> Any:
    """An attribute from the outermost gym wrapper that defines it (ManiSkill's wrappers may override spaces)."""
    get = getattr(env, "get_wrapper_attr", None)
    return get(name) if get is not None else getattr(env, name)


def render_frame_shape(base: Any) -> tuple[int, ...]:
    """The ``(H, W, 3)`` of one env's ``render()`` frame, from the camera config when there is one camera.

    ManiSkill tiles several render cameras into one frame: only a render tells that layout.
    Rendering does not step the env.
    """
    configs = getattr(base, "_human_render_camera_configs", {}) or {}
    if len(configs) == 1:
        (cfg,) = configs.values()
        return (cfg.height, cfg.width, 3)
    return tuple(base.render().shape[-3:])
