"""ManiSkill/SAPIEN helpers with no TorchRL import (the gym shim uses them too): the ManiSkill
env under gym wrappers, its render frame shape, the registered task ids, log filters, the
GPU sim's PhysX library, device names, and what a ManiSkill env hands out (reused buffers,
auto-resets)."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "auto_resetting_wrapper",
    "canonical_device",
    "enable_physx_gpu",
    "ignores_terminations",
    "maniskill_base_env",
    "quiet_maniskill",
    "registered_env_ids",
    "render_frame_shape",
    "reuses_buffers",
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


# ManiSkill's sim backend names that are also read as devices ("physx_cuda:1" is cuda:1).
_DEVICE_ALIASES = {"physx_cpu": "cpu", "physx_cuda": "cuda", "gpu": "cuda"}


def canonical_device(device: Any, *, current_cuda: int | None = None) -> torch.device:
    """``device`` as a :class:`torch.device` with an index for CUDA, so that two names of one
    device compare equal: ManiSkill's GPU sim says ``"cuda"``, TorchRL says ``"cuda:0"``.

    ``"cuda"`` (no index) is the current CUDA device, as torch reads it: ``current_cuda`` if
    given, else :func:`torch.cuda.current_device` (0 without CUDA). ManiSkill's sim backend
    names are accepted too: ``"physx_cuda:1"`` is ``cuda:1``, ``"physx_cpu"`` is ``cpu``.

    Examples:
        >>> canonical_device("cuda", current_cuda=0) == canonical_device("cuda:0")
        True
        >>> canonical_device("physx_cuda:1")
        device(type='cuda', index=1)
    """
    if isinstance(device, str):
        name, sep, index = device.partition(":")
        device = _DEVICE_ALIASES.get(name.lower(), name) + sep + index
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        if current_cuda is None:
            current_cuda = torch.cuda.current_device() if torch.cuda.is_available() else 0
        device = torch.device("cuda", current_cuda)
    return device


def reuses_buffers(base: Any) -> bool:
    """Whether ``base`` (a ManiSkill ``BaseEnv``) may return tensors that its later steps, resets
    or renders overwrite in place.

    - The GPU sim: camera pictures are SAPIEN's CUDA buffers, the same tensor at every read
      (``RenderCamera.get_picture``: ``get_picture_cuda(name).torch()``), and a hidden actor's
      pose is its ``before_hide_pose`` tensor, written in place at reset.
    - The CPU sim rendering with ``render_backend="sapien_cuda"`` (the default on a machine with
      CUDA): ManiSkill reads each camera with ``get_picture_cuda`` there too.

    The CPU sim rendering on the CPU (``sapien_cpu``) copies every picture out through numpy.
    """
    if getattr(base, "gpu_sim_enabled", False):
        return True
    return getattr(getattr(base, "backend", None), "render_backend", None) == "sapien_cuda"


def _layers(env: Any) -> list[Any]:
    """``env`` and the gym wrappers under it, outermost first, down to the ManiSkill env."""
    layers = []
    while env is not None and all(env is not seen for seen in layers):
        layers.append(env)
        # gym.Wrapper keeps its env in .env; ManiSkillVectorEnv in ._env.
        inner = getattr(env, "env", None)
        env = inner if inner is not None else getattr(env, "_env", None)
    return layers


def auto_resetting_wrapper(env: Any) -> str | None:
    """The wrapper around ``env``'s ManiSkill env that resets done envs inside its ``step``
    (ManiSkill's ``ManiSkillVectorEnv(auto_reset=True)``, gymnasium's ``Autoreset``), or None."""
    from gymnasium.wrappers import Autoreset
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    for layer in _layers(env):
        if isinstance(layer, ManiSkillVectorEnv) and layer.auto_reset:
            return "ManiSkillVectorEnv(auto_reset=True)"
        if isinstance(layer, Autoreset):
            return "gymnasium.wrappers.Autoreset"
    return None


def ignores_terminations(env: Any) -> bool:
    """Whether a ``ManiSkillVectorEnv(ignore_terminations=True)`` is around ``env``'s ManiSkill env:
    its envs then end together, at the time limit, and never need a partial reset."""
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    return any(isinstance(layer, ManiSkillVectorEnv) and layer.ignore_terminations for layer in _layers(env))
