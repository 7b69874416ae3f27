"""ManiSkill/SAPIEN helpers with no TorchRL import (the gym shim uses them too): the ManiSkill
env under gym wrappers, its render frame shape, the registered task ids, log filters, the
GPU sim's PhysX library, device names, and what a ManiSkill env hands out (reused buffers,
auto-resets)."""

from __future__ import annotations

import contextlib
import functools
import inspect
import platform
import re
import weakref
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

__all__ = [
    "RenderDeviceError",
    "auto_resetting_wrapper",
    "canonical_device",
    "check_assets",
    "default_render_backend",
    "enable_physx_gpu",
    "ignores_terminations",
    "missing_assets",
    "no_asset_prompt",
    "maniskill_base_env",
    "make_maniskill",
    "quiet_maniskill",
    "registered_env_ids",
    "render_devices_in_use",
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
    renders on. SAPIEN keeps one render device per process while any env that renders lives;
    the message names both devices and the fixes."""


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
    base = maniskill_base_env(env)
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


def _robot_uids(env_id: str, maniskill_kwargs: dict) -> list[str]:
    """The robots a task is made with: ``robot_uids`` if given, else the task's default."""
    spec = registered_env_ids()[env_id]
    uids = maniskill_kwargs.get("robot_uids", spec.default_kwargs.get("robot_uids"))
    if uids is None:
        param = inspect.signature(spec.cls.__init__).parameters.get("robot_uids")
        uids = param.default if param is not None and param.default is not param.empty else None
    uids = [uids] if isinstance(uids, str) else list(uids or [])
    return [u for u in uids if isinstance(u, str)]


def missing_assets(env_id: str, maniskill_kwargs: dict | None = None) -> dict[str, list[str]]:
    """The assets that ManiSkill declares for a task and that are not downloaded, by the name that
    fetches them (``python -m mani_skill.utils.download_asset <name>``): the task id for its own
    assets, a robot uid for a robot's. Empty when all are there. Reads files only: no env is made."""
    from mani_skill.utils import assets

    missing: dict[str, list[str]] = {}
    for group in [env_id, *_robot_uids(env_id, maniskill_kwargs or {})]:
        if group not in assets.DATA_GROUPS:
            continue
        ids = assets.expand_data_group_into_individual_data_source_ids(group)
        absent = [i for i in ids if not assets.is_data_source_downloaded(i)]
        if absent:
            missing[group] = absent
    return missing


def missing_assets_message(env_id: str, missing: dict[str, list[str]], asset: str | None = None) -> str:
    """What to tell a user whose task lacks assets: which, and the commands that fetch them.

    ``missing`` maps ``download_asset`` ids to what is absent; empty when ManiSkill asked for an
    asset (``asset``) that belongs to no known id."""
    if missing:
        what = "; ".join(
            f"{group}: {', '.join(ids[:3])}" + (f" and {len(ids) - 3} more" if len(ids) > 3 else "")
            for group, ids in missing.items()
        )
        how = " && ".join(f"python -m mani_skill.utils.download_asset {group}" for group in missing)
        how = f"`{how}`"
    else:
        what = asset or "an asset"
        how = (
            "`python -m mani_skill.utils.download_asset <id>` (`... download_asset -l robot`, `-l scene`, "
            "`-l task_assets` or `-l objects` lists the ids)"
        )
    return (
        f"ManiSkill task {env_id!r} needs assets that are not downloaded ({what}). Fetch them once "
        f"with {how} (into $MS_ASSET_DIR, default ~/.maniskill/data), then make the env again."
    )


def check_assets(env_id: str, maniskill_kwargs: dict | None = None) -> None:
    """Raises a :class:`FileNotFoundError` naming the task, its missing assets and the commands
    that fetch them, when ManiSkill declares assets for it that are not downloaded."""
    missing = missing_assets(env_id, maniskill_kwargs)
    if missing:
        raise FileNotFoundError(missing_assets_message(env_id, missing))


def _data_source_of(path: Path) -> str | None:
    """The ManiSkill data source (a ``download_asset`` id) whose folder holds ``path``, if any."""
    from mani_skill.utils import assets

    for uid, source in assets.DATA_SOURCES.items():
        folder = (Path(source.output_dir) / source.target_path).resolve()
        if path.is_relative_to(folder):
            return uid
    return None


@contextlib.contextmanager
def no_asset_prompt(env_id: str) -> Iterator[None]:
    """While making a ManiSkill env: ManiSkill's ``(y|n)`` download prompt raises a
    :class:`FileNotFoundError` that says what to run, instead of reading standard input (which
    blocks a script, or fails with a bare ``EOFError`` without a terminal); so does a file missing
    under ManiSkill's asset folder."""
    from mani_skill.utils import download_asset

    def refuse(message: str) -> bool:
        from mani_skill.utils import assets

        asset = message.split(" has assets")[0]  # "Robot <uid>", ManiSkill's only prompt in 3.0.1
        uid = asset.split()[-1] if asset else ""
        known = uid in assets.DATA_GROUPS or uid in assets.DATA_SOURCES
        raise FileNotFoundError(missing_assets_message(env_id, {uid: [asset]} if known else {}, asset=asset))

    prompt = download_asset.prompt_yes_no
    download_asset.prompt_yes_no = refuse
    try:
        yield
    except RuntimeError as e:
        # Some tasks check their dataset themselves and say which download_asset id fetches it.
        if "mani_skill.utils.download_asset" not in str(e):
            raise
        raise FileNotFoundError(f"ManiSkill task {env_id!r} needs assets that are not downloaded: {e}") from e
    except FileNotFoundError as e:
        # A task whose assets ManiSkill did not declare (scene datasets): a file missing under its
        # asset folder is a missing download, whatever error the task raises for it.
        from mani_skill import ASSET_DIR

        path = Path(str(e.filename or "")).resolve()
        if e.filename and path.is_relative_to(Path(ASSET_DIR).resolve()):
            source = _data_source_of(path)
            missing = {source: [str(path)]} if source else {}
            raise FileNotFoundError(missing_assets_message(env_id, missing, asset=str(path))) from e
        raise
    finally:
        download_asset.prompt_yes_no = prompt
