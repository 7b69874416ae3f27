"""A ManiSkill env under gym wrappers: its ``BaseEnv``, its attributes, device names. No TorchRL
import (the gym shim and the CPU engine's workers use it)."""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["canonical_device", "enable_physx_gpu", "maniskill_base_env", "wrapper_attr"]


def maniskill_base_env(env: Any):
    """The ManiSkill ``BaseEnv`` under ``env`` (through any gym wrappers), or ``None``."""
    from mani_skill.envs.sapien_env import BaseEnv

    base = getattr(env, "unwrapped", None)
    return base if isinstance(base, BaseEnv) else None


def wrapper_attr(env: Any, name: str) -> Any:
    """An attribute from the outermost gym wrapper that defines it (ManiSkill's wrappers may override spaces)."""
    get = getattr(env, "get_wrapper_attr", None)
    return get(name) if get is not None else getattr(env, name)


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


def enable_physx_gpu() -> None:
    """Loads SAPIEN's PhysX GPU library for ManiSkill's GPU sim.

    SAPIEN downloads it on first use: offline, the error says what to do.
    """
    import zipfile
    from pathlib import Path

    import sapien.physx as physx

    if physx.is_gpu_enabled():
        return
    try:
        physx.enable_gpu()
    except (OSError, zipfile.BadZipFile) as err:
        folder = Path.home() / ".sapien" / "physx" / physx.version()
        raise RuntimeError(
            f"The GPU sim needs SAPIEN's PhysX GPU library (libPhysXGpu_64.so in {folder}), which SAPIEN "
            f"downloads on first use from its physx-precompiled GitHub release {physx.version()}; that failed: "
            f"{type(err).__name__}: {err}. Offline, copy that folder from a machine where the GPU sim has run "
            "once, or use sim_backend='cpu'."
        ) from err
