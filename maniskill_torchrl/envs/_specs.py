"""Gymnasium spaces and ManiSkill info dicts -> TorchRL specs.

ManiSkill describes one sub-env with ``single_observation_space`` /
``single_action_space``; the specs built here prepend the env batch
(``[num_envs]``) and keep every dtype (uint8 images stay uint8, bool flags
stay bool). Dict spaces become nested :class:`~torchrl.data.Composite` specs
with the same key paths.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch
from torchrl.data import (
    Bounded,
    Categorical,
    Composite,
    MultiCategorical,
    TensorSpec,
    Unbounded,
)

__all__ = [
    "space_to_spec",
    "observation_spec_from_space",
    "info_spec_from_infos",
    "pixels_spec",
    "done_spec",
    "reward_spec",
    "EnvSpecs",
    "env_specs",
]

# Top-level tensordict keys that an info entry must not take (it becomes "info_<key>").
_RESERVED_KEYS = frozenset({"reward", "done", "terminated", "truncated", "action"})


def _torch_dtype(dtype: Any) -> torch.dtype:
    if isinstance(dtype, torch.dtype):
        return dtype
    return torch.from_numpy(np.zeros((), dtype=dtype)).dtype


def _bool_spec(shape: torch.Size, device: torch.device) -> TensorSpec:
    return Categorical(n=2, shape=shape, dtype=torch.bool, device=device)


def space_to_spec(space: gym.Space, batch_size: torch.Size, device: torch.device) -> TensorSpec:
    """Converts one (unbatched) gymnasium space into a spec batched by ``batch_size``.

    Box spaces with finite bounds become :class:`~torchrl.data.Bounded`, unbounded
    ones :class:`~torchrl.data.Unbounded`, bool boxes a two-valued
    :class:`~torchrl.data.Categorical`; Dict spaces become nested
    :class:`~torchrl.data.Composite` specs.

    Examples:
        >>> import gymnasium as gym, torch
        >>> from maniskill_torchrl.envs._specs import space_to_spec
        >>> space_to_spec(gym.spaces.Box(-1, 1, (8,)), torch.Size([4]), torch.device("cpu")).shape
        torch.Size([4, 8])
    """
    batch_size = torch.Size(batch_size)
    if isinstance(space, gym.spaces.Dict):
        return Composite(
            {k: space_to_spec(v, batch_size, device) for k, v in space.spaces.items()},
            shape=batch_size,
            device=device,
        )
    if isinstance(space, gym.spaces.Box):
        shape = batch_size + torch.Size(space.shape)
        dtype = _torch_dtype(space.dtype)
        if dtype == torch.bool:
            return _bool_spec(shape, device)
        low, high = np.asarray(space.low), np.asarray(space.high)
        if np.isfinite(low).all() and np.isfinite(high).all():
            low_t = torch.as_tensor(low, device=device).to(dtype).expand(shape)
            high_t = torch.as_tensor(high, device=device).to(dtype).expand(shape)
            return Bounded(low=low_t, high=high_t, shape=shape, dtype=dtype, device=device)
        return Unbounded(shape=shape, dtype=dtype, device=device)
    if isinstance(space, gym.spaces.Discrete):
        return Categorical(n=int(space.n), shape=batch_size, dtype=torch.int64, device=device)
    if isinstance(space, gym.spaces.MultiDiscrete):
        return MultiCategorical(
            nvec=torch.as_tensor(space.nvec),
            shape=batch_size + torch.Size(space.shape),
            dtype=torch.int64,
            device=device,
        )
    raise TypeError(
        f"Cannot convert the gymnasium space {space!r} into a TorchRL spec: only "
        "Box, Discrete, MultiDiscrete and Dict spaces are supported."
    )


def observation_spec_from_space(space: gym.Space, batch_size: torch.Size, device: torch.device) -> Composite:
    """Observation spec: a Box space goes to ``"observation"``, a Dict space keeps its key paths."""
    spec = space_to_spec(space, batch_size, device)
    if isinstance(spec, Composite):
        return spec
    return Composite(observation=spec, shape=batch_size, device=device)


def info_spec_from_infos(infos: Mapping[str, Any], batch_size: torch.Size, device: torch.device) -> Composite:
    """Declares the tensor entries of a ManiSkill info dict (``success``, ``fail``, ``elapsed_steps``...).

    Only tensors whose leading dims match the batch are kept: python values such as
    ``reconfigure`` are per-call metadata, not per-env data.
    """
    batch_size = torch.Size(batch_size)
    out = Composite(shape=batch_size, device=device)
    for key, value in infos.items():
        if isinstance(value, Mapping):
            sub = info_spec_from_infos(value, batch_size, device)
            if not sub.is_empty():
                out[key] = sub
            continue
        if not isinstance(value, torch.Tensor) or value.shape[: len(batch_size)] != batch_size:
            continue
        if value.dtype == torch.bool:
            out[key] = _bool_spec(value.shape, device)
        else:
            out[key] = Unbounded(shape=value.shape, dtype=value.dtype, device=device)
    return out


def pixels_spec(batch_size: torch.Size, frame_shape: tuple[int, ...], device: torch.device) -> Bounded:
    """``pixels``: ``[*batch, H, W, 3]`` uint8 frames of ``frame_shape`` ``(H, W, 3)``."""
    return Bounded(
        low=0,
        high=255,
        shape=torch.Size(batch_size) + torch.Size(frame_shape),
        dtype=torch.uint8,
        device=device,
    )


def done_spec(batch_size: torch.Size, device: torch.device) -> Composite:
    """``done``, ``terminated`` and ``truncated``, each ``[*batch, 1]`` bool."""
    shape = torch.Size(batch_size) + (1,)
    return Composite(
        done=_bool_spec(shape, device),
        terminated=_bool_spec(shape, device),
        truncated=_bool_spec(shape, device),
        shape=batch_size,
        device=device,
    )


def reward_spec(batch_size: torch.Size, device: torch.device) -> Unbounded:
    """``reward``: ``[*batch, 1]`` float32."""
    return Unbounded(shape=torch.Size(batch_size) + (1,), dtype=torch.float32, device=device)


class EnvSpecs(NamedTuple):
    """The specs of one ManiSkill env, as :func:`env_specs` builds them."""

    observation: Composite
    """Observations, ``"pixels"`` and infos."""
    action: Composite
    """The full action spec: ``"action"`` (a Box space) or ``("action", <agent>)`` entries (a Dict space)."""
    reward: Unbounded
    done: Composite
    info_map: list[tuple[str, str]]
    """``(info key, tensordict key)`` for every declared info entry."""


def env_specs(
    obs_space: gym.Space,
    act_space: gym.Space,
    infos: Mapping[str, Any],
    batch_size: torch.Size,
    device: torch.device,
    *,
    frame_shape: tuple[int, ...] | None = None,
    pixels_only: bool = False,
) -> EnvSpecs:
    """Every spec of a ManiSkill env from its single-env spaces and an info dict.

    The observation spec holds the observation space's entries (none with ``pixels_only``),
    ``"pixels"`` when a ``frame_shape`` is given, and the tensor entries of ``infos``
    (:func:`info_spec_from_infos`); an info key that collides with an observation key or with
    ``reward`` / ``done`` / ``terminated`` / ``truncated`` / ``action`` is declared as ``"info_<key>"``.
    """
    batch_size = torch.Size(batch_size)
    obs_spec = observation_spec_from_space(obs_space, batch_size, device)
    if pixels_only:
        obs_spec = Composite(shape=batch_size, device=device)
    if frame_shape is not None:
        obs_spec["pixels"] = pixels_spec(batch_size, frame_shape, device)
    info_spec = info_spec_from_infos(infos, batch_size, device)
    reserved = set(obs_spec.keys()) | _RESERVED_KEYS
    info_map: list[tuple[str, str]] = []
    for key in info_spec.keys():
        td_key = f"info_{key}" if key in reserved else key
        obs_spec[td_key] = info_spec[key]
        info_map.append((key, td_key))
    return EnvSpecs(
        observation=obs_spec,
        action=Composite(action=space_to_spec(act_space, batch_size, device), shape=batch_size, device=device),
        reward=reward_spec(batch_size, device),
        done=done_spec(batch_size, device),
        info_map=info_map,
    )
