"""SAPIEN rendering on a ManiSkill env: the quiet default render backend of a CPU-only machine, the
one render device per process (a :class:`~maniskill_torchrl.errors.RenderDeviceError` that names
both devices and the fixes), a render frame's shape. No TorchRL import."""

from __future__ import annotations

import contextlib
import functools
import platform
import re
import weakref
from collections.abc import Iterator
from typing import Any

__all__ = [
    "RenderDeviceError",
    "default_render_backend",
    "make_maniskill",
    "quiet_maniskill",
    "remember_render_device",
    "render_device_errors",
    "render_device_message",
    "render_devices_in_use",
    "render_frame_shape",
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


@functools.lru_cache(maxsize=1)
def _no_cuda_render_device() -> bool:
    """Whether SAPIEN finds no CUDA device to render with: the probe ManiSkill makes for its
    default ``render_backend="gpu"``, with the same call and the same error (once per process)."""
    import sapien

    try:
        sapien.Device("cuda")
    except RuntimeError as e:
        return str(e) == 'failed to find device "cuda"'
    return False


def default_render_backend(maniskill_kwargs: dict) -> dict:
    """``maniskill_kwargs`` for ``gym.make``, with ``render_backend="cpu"`` when the caller named no
    ``render_backend`` and SAPIEN finds no CUDA device.

    ManiSkill's default, ``"gpu"``, then falls back to the CPU anyway, after warning "Requested to
    use render device "sapien_cuda", but CUDA device was not found" for every env (every CPU
    worker included): asking for the device that exists gives the same env without the warning.
    A machine with CUDA, macOS (where ManiSkill picks the CPU itself) and an explicit
    ``render_backend`` are left as they are. Returns a new dict; the argument is not changed.
    """
    if "render_backend" in maniskill_kwargs or platform.system() == "Darwin" or not _no_cuda_render_device():
        return maniskill_kwargs
    return {**maniskill_kwargs, "render_backend": "cpu"}


# ----------------------------------------------------------------------------- render device
# SAPIEN keeps one render engine per process, on one device, while any scene that renders lives,
# and refuses a RenderSystem on another device meanwhile ("cpu" and "cuda:0" are two devices).
_SINGLE_RENDER_DEVICE = "only supports single-GPU rendering"
_ASKED_DEVICE = re.compile(r'on device "([^"]*)"')
# (ManiSkill env, its task id, its render device) for each env made through make_maniskill:
# what this process renders on, for as long as such an env lives.
_RENDERING: list[tuple[weakref.ref, str, str]] = []


class RenderDeviceError(RuntimeError):
    """A ManiSkill env asked SAPIEN for a render device other than the one this process already
    renders on (public as :class:`maniskill_torchrl.errors.RenderDeviceError`). SAPIEN keeps one
    render device per process while any env that renders lives; the message names both devices
    and the fixes."""


def _device_name(device: Any) -> str:
    """A SAPIEN device as torch names it: ``"cpu"``, ``"cuda:0"``."""
    if device.is_cuda():
        return f"cuda:{device.cuda_id}"
    return "cpu" if device.is_cpu() else str(device.name)


def _render_backend_for(device: str) -> str:
    """The ``render_backend`` that asks ManiSkill for ``device``."""
    return "'cpu'" if device == "cpu" else ("'gpu'" if device in ("cuda", "cuda:0") else f"'{device}'")


def render_devices_in_use() -> dict[str, list[str]]:
    """The render devices of the ManiSkill envs made in this process by the library that are still
    alive (closed or not: a closed env's scene lives until the env is freed), with their task ids."""
    alive: dict[str, list[str]] = {}
    for ref, env_id, device in list(_RENDERING):
        if ref() is None:
            _RENDERING.remove((ref, env_id, device))
        else:
            alive.setdefault(device, []).append(env_id)
    return alive


def render_device_message(env_id: str, asked: str, in_use: dict[str, list[str]], *, batched: bool = False) -> str:
    """What to tell a user whose env ``env_id`` asked SAPIEN to render on ``asked`` while this
    process renders on another device (``in_use``: device -> task ids, from the library's envs)."""
    others = {d: ids for d, ids in in_use.items() if d != asked}
    if others:
        held = "; ".join(
            f'"{d}" (render_backend={_render_backend_for(d)}, for {", ".join(dict.fromkeys(ids))})'
            for d, ids in others.items()
        )
        where = f"this process already renders on {held}"
        backends = sorted({_render_backend_for(asked), *map(_render_backend_for, others)})
        same = ": " + " for all, or ".join(backends) + " for all"
    else:
        where = "this process already renders on another device (an env made with another render_backend is alive)"
        same = ""
    fixes = [
        f"the same render_backend for every ManiSkill env of this process{same} ('gpu', ManiSkill's default "
        "and what leaving render_backend out picks, renders on CUDA where there is CUDA)",
        "close the other env and drop every reference to it (env.close(); del env) before making this one",
        "make this env in another process: a ParallelEnv worker, Collector(make_env, backend='process', ...), "
        "or a subprocess",
    ]
    if batched:
        fixes[-1] += " (the batched CPU-sim env: ManiSkillEnv(..., in_process=False) makes every sub-env in a worker)"
    return (
        f'ManiSkill env {env_id!r} asks SAPIEN to render on "{asked}", but {where}. SAPIEN keeps one '
        'render device per process while any env that renders lives ("cpu" and "cuda" are two devices). '
        "Fix: " + "; ".join(f"({i}) {fix}" for i, fix in enumerate(fixes, 1)) + "."
    )


@contextlib.contextmanager
def render_device_errors(env_id: str, asked: str | None = None, *, batched: bool = False) -> Iterator[None]:
    """While making a ManiSkill env: SAPIEN's refusal of a second render device ("only supports
    single-GPU rendering") becomes a :class:`RenderDeviceError` that names both devices and the
    fixes (``batched``: the in-process sub-env of the batched CPU-sim env, which has one more)."""
    try:
        yield
    except RuntimeError as e:
        if _SINGLE_RENDER_DEVICE not in str(e):
            raise
        match = _ASKED_DEVICE.search(str(e))
        device = match.group(1) if match else str(asked or "gpu")
        raise RenderDeviceError(
            render_device_message(env_id, device, render_devices_in_use(), batched=batched) + f" SAPIEN said: {e}"
        ) from e


def remember_render_device(env: Any, env_id: str) -> None:
    """Keeps ``env``'s render device in mind while it lives (what the next error names)."""
    base = env.unwrapped  # a gym.make env
    device = getattr(getattr(base, "backend", None), "render_device", None)
    if device is not None:
        render_devices_in_use()  # drops the freed ones
        _RENDERING.append((weakref.ref(base), env_id, _device_name(device)))


def make_maniskill(env_id: str, *, batched: bool = False, **kwargs: Any) -> Any:
    """``gym.make(env_id, **kwargs)`` with :func:`render_device_errors`, its render device
    remembered (:func:`remember_render_device`)."""
    import gymnasium as gym

    with render_device_errors(env_id, kwargs.get("render_backend"), batched=batched):
        env = gym.make(env_id, **kwargs)
    remember_render_device(env, env_id)
    return env


class _NoCudaRenderWarning:
    """A logging filter dropping ManiSkill's no-CUDA render-device warning, and its task builders' "No initial pose
    set for actor builder" (a note for task authors: ManiSkill's own tasks' goal markers print it at every build)."""

    def filter(self, record) -> bool:
        message = record.getMessage()
        return "CUDA device was not found" not in message and not message.startswith("No initial pose set for actor")


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
