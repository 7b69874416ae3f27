"""ManiSkill/SAPIEN helpers with no TorchRL import (the gym shim uses them too): the ManiSkill
env under gym wrappers, its render frame shape, the registered task ids, log filters, and the
GPU sim's PhysX library."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

__all__ = [
    "enable_physx_gpu",
    "maniskill_base_env",
    "quiet_maniskill",
    "registered_env_ids",
    "render_frame_shape",
    "similar_env_ids",
    "wrapper_attr",
]


def quiet_maniskill() -> None:
    """Silences messages that say nothing actionable on a CPU-only machine.

    ManiSkill warns "CUDA device was not found ... Rendering might be disabled"
    for every env although SAPIEN then renders on the CPU (lavapipe) fine.
    """
    import warnings

    warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")
    warnings.filterwarnings("ignore", module="mani_skill")

    from mani_skill.utils.logging_utils import logger

    if not any(isinstance(f, _NoCudaRenderWarning) for f in logger.filters):
        logger.addFilter(_NoCudaRenderWarning())


class _NoCudaRenderWarning:
    """A logging filter dropping ManiSkill's no-CUDA render-device warning only."""

    def filter(self, record) -> bool:
        return "CUDA device was not found" not in record.getMessage()


def registered_env_ids() -> Any:
    """ManiSkill's task registry (``env_id -> EnvSpec``), after registering the tasks."""
    import mani_skill.envs  # noqa: F401  (registers the tasks)
    from mani_skill.utils.registration import REGISTERED_ENVS

    return REGISTERED_ENVS


def similar_env_ids(env_id: str, limit: int = 5) -> list[str]:
    """Registered task ids that contain ``env_id``'s name before the first ``-`` (the "did you mean")."""
    stem = env_id.split("-")[0].lower()
    if not stem:
        return []
    return [e for e in sorted(registered_env_ids()) if stem in e.lower()][:limit]


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


def enable_physx_gpu() -> None:
    """Loads SAPIEN's PhysX GPU library, as ManiSkill's GPU sim does on its first env, but with an
    error that says what to do: SAPIEN downloads the library on first use, which fails offline
    with a bare network or zip traceback."""
    import sapien.physx as physx

    if physx.is_gpu_enabled():
        return
    try:
        physx.enable_gpu()
    except (OSError, zipfile.BadZipFile) as e:  # requests' errors are OSErrors
        folder = Path.home() / ".sapien" / "physx" / physx.version()
        raise RuntimeError(
            f"The GPU sim needs SAPIEN's PhysX GPU library (libPhysXGpu_64.so in {folder}), which SAPIEN "
            f"downloads on first use from its physx-precompiled GitHub release {physx.version()}; that failed: "
            f"{type(e).__name__}: {e}. On a machine without internet access, copy that folder from a "
            "machine where the GPU sim has run once (or unzip the release's linux-so.zip into it), "
            "or use the CPU sim (sim_backend='cpu')."
        ) from e
