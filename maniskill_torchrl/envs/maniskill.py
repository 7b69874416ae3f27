# Copyright (c) Meta Platforms, Inc. and affiliates.
#
# This source code is licensed under the MIT license found in the
# LICENSE file in the root directory of this source tree.
"""ManiSkill 3 environment wrapper.

This module exposes :class:`ManiSkillWrapper`, a TorchRL adapter for a ManiSkill 3
env made with ``gym.make``, and :class:`ManiSkillEnv`, which builds a task from
ManiSkill's registry.
"""

from __future__ import annotations

import importlib.util
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.data.tensor_specs import (
    Bounded,
    Categorical,
    Composite,
    TensorSpec,
    Unbounded,
)
from torchrl.data.utils import DEVICE_TYPING, numpy_to_torch_dtype_dict
from torchrl.envs.common import _EnvPostInit, _EnvWrapper
from torchrl.envs.utils import _classproperty

_has_maniskill = importlib.util.find_spec("mani_skill") is not None

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]

# ManiSkill's sim backend names, read as devices ("physx_cuda:1" is cuda:1).
_DEVICE_ALIASES = {"physx_cpu": "cpu", "physx_cuda": "cuda", "gpu": "cuda"}
# Top-level keys an info entry must not take: it is stored as "info_<key>" instead.
_RESERVED_KEYS = frozenset({"reward", "done", "terminated", "truncated", "action"})


def _canonical_device(device: Any) -> torch.device:
    """``device``, with an index for CUDA; ManiSkill's backend names read as devices."""
    if isinstance(device, str):
        name, sep, index = device.partition(":")
        device = _DEVICE_ALIASES.get(name.lower(), name) + sep + index
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        index = torch.cuda.current_device() if torch.cuda.is_available() else 0
        device = torch.device("cuda", index)
    return device


def _layers(env: Any) -> list[Any]:
    """``env`` and the gym wrappers under it, outermost first."""
    layers = []
    while env is not None and all(env is not seen for seen in layers):
        layers.append(env)
        # gym.Wrapper keeps its env in .env; ManiSkillVectorEnv in ._env.
        inner = getattr(env, "env", None)
        env = inner if inner is not None else getattr(env, "_env", None)
    return layers


def _reuses_buffers(base: Any) -> bool:
    """Whether a ManiSkill ``BaseEnv`` may hand out tensors that it writes into later.

    The GPU sim's (camera buffers, poses written in place at reset), and the CPU
    sim's pictures when it renders with ``sapien_cuda``.
    """
    if getattr(base, "gpu_sim_enabled", False):
        return True
    backend = getattr(getattr(base, "backend", None), "render_backend", None)
    return backend == "sapien_cuda"


def _cpu_sim(num_envs: int, sim_backend: Any) -> bool:
    """Whether ``gym.make`` gives the CPU sim (``"auto"``: one env, or no CUDA)."""
    from mani_skill.envs.utils.system.backend import CPU_SIM_BACKENDS

    backend = str(sim_backend).lower()
    if backend == "auto":
        return num_envs == 1 or not torch.cuda.is_available()
    return backend in CPU_SIM_BACKENDS


def _task_kwargs(
    env_name: str, num_envs: Any, from_pixels: bool, batch_size: Any, kwargs: dict
) -> dict:
    """``gym.make``'s keyword arguments for a task, checked before anything is built."""
    available = ManiSkillWrapper.available_envs
    if env_name not in available:
        stem = env_name.split("-")[0].lower()
        close = [e for e in available if stem and stem in e.lower()][:5]
        raise ValueError(
            f"Unknown ManiSkill env {env_name!r}. "
            + (f"Did you mean one of {close}? " if close else "")
            + "ManiSkillEnv.available_envs lists the registered tasks."
        )
    if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive int, got {num_envs!r}.")
    ManiSkillWrapper._checked_batch_size(batch_size, num_envs)
    kwargs = dict(kwargs)
    if from_pixels and kwargs.get("render_mode") is None:
        # An explicit None (a config's default) asks for no render mode either.
        kwargs["render_mode"] = "rgb_array"
    if from_pixels and kwargs["render_mode"] != "rgb_array":
        raise ValueError(
            "from_pixels=True needs render_mode='rgb_array' "
            f"(got render_mode={kwargs['render_mode']!r})."
        )
    backend = kwargs.get("sim_backend", "auto")
    if _cpu_sim(num_envs, backend):
        return kwargs
    if not torch.cuda.is_available():
        raise ValueError(
            f"sim_backend={backend!r} is ManiSkill's GPU sim, which needs CUDA, and "
            "torch.cuda.is_available() is False: use sim_backend='cpu' (or 'auto')."
        )
    index = str(backend).partition(":")[2]
    if index and not (index.isdigit() and int(index) < torch.cuda.device_count()):
        raise ValueError(
            f"sim_backend={backend!r} names CUDA device {index}, and this machine has "
            f"{torch.cuda.device_count()} (torch.cuda.device_count()): name one of "
            "them, or pass sim_backend='gpu' for the current one."
        )
    return kwargs


def _check_args(from_pixels: bool, pixels_only: bool) -> None:
    if not _has_maniskill:
        raise ImportError(
            "mani_skill python package was not found. Install it with: "
            "pip install mani_skill"
        )
    if pixels_only and not from_pixels:
        raise ValueError("pixels_only=True needs from_pixels=True.")


def _env_id(env: Any) -> str:
    """The task id of a ManiSkill env (its class name where it has no spec)."""
    spec = getattr(env.unwrapped, "spec", None)
    return spec.id if spec is not None else type(env.unwrapped).__name__


def _bool_spec(shape: torch.Size, device: torch.device) -> TensorSpec:
    return Categorical(n=2, shape=shape, dtype=torch.bool, device=device)


def _space_to_spec(
    space: Any, batch_size: torch.Size, device: torch.device
) -> TensorSpec:
    """One (unbatched) gymnasium space as a spec batched by ``batch_size``.

    Not ``torchrl.envs.libs.gym._gym_to_torchrl_spec_transform``: ManiSkill's scalar
    Boxes (``is_grasped``) are ``[B]`` entries, which it declares ``[B, 1]``.
    """
    import gymnasium as gym

    if isinstance(space, gym.spaces.Dict):
        return Composite(
            {k: _space_to_spec(v, batch_size, device) for k, v in space.spaces.items()},
            shape=batch_size,
            device=device,
        )
    if isinstance(space, gym.spaces.Box):
        shape = batch_size + torch.Size(space.shape)
        dtype = numpy_to_torch_dtype_dict[np.dtype(space.dtype)]
        if dtype == torch.bool:
            return _bool_spec(shape, device)
        low, high = np.asarray(space.low), np.asarray(space.high)
        if np.isfinite(low).all() and np.isfinite(high).all():
            return Bounded(
                low=torch.as_tensor(low, device=device).to(dtype).expand(shape),
                high=torch.as_tensor(high, device=device).to(dtype).expand(shape),
                shape=shape,
                dtype=dtype,
                device=device,
            )
        return Unbounded(shape=shape, dtype=dtype, device=device)
    raise TypeError(
        f"Cannot convert the gymnasium space {space!r} into a TorchRL spec: ManiSkill "
        "tasks have Box and Dict spaces only."
    )


def _info_spec(
    infos: Mapping[str, Any], batch_size: torch.Size, device: torch.device
) -> Composite:
    """Specs of the batched tensor infos (not python values such as ``reconfigure``)."""
    out = Composite(shape=batch_size, device=device)
    for key, value in infos.items():
        if isinstance(value, Mapping):
            sub = _info_spec(value, batch_size, device)
            if not sub.is_empty():
                out[key] = sub
        elif not isinstance(value, torch.Tensor):
            continue
        elif value.shape[: len(batch_size)] != batch_size:
            continue
        elif value.dtype == torch.bool:
            out[key] = _bool_spec(value.shape, device)
        else:
            out[key] = Unbounded(shape=value.shape, dtype=value.dtype, device=device)
    return out


class _ResetSeeds:
    """The resets' seeds: ``s`` after ``set(s)``, then ``RandomState(s)``'s draws.

    ManiSkill seeds its episode RNG (and forks torch's) only in a seeded reset: an
    unseeded one, partial ones too, would draw from the process's global RNG.
    """

    def __init__(self) -> None:
        self.set(None)

    def set(self, seed: int | None) -> None:
        self._next = None if seed is None else int(seed)
        self._rng = None if seed is None else np.random.RandomState(int(seed) % 2**32)

    def draw(self) -> int | None:
        if self._rng is None:
            return None
        seed, self._next = self._next, None
        return int(self._rng.randint(2**31)) if seed is None else seed


def _mapped(obs: Mapping[str, Any], leaf: Callable) -> dict:
    """A nested observation dict with ``leaf`` applied to every tensor."""
    return {
        k: leaf(v)
        if isinstance(v, torch.Tensor)
        else _mapped(v, leaf)
        if isinstance(v, Mapping)
        else v
        for k, v in obs.items()
    }


def _sim_action(value: Any, shape: Any, name: Any, unbatched: bool, device: Any) -> Any:
    """An action entry as ManiSkill takes it, its shape checked first.

    With the env dim, on ``device`` (None: where it is). ManiSkill would broadcast a
    misshaped action.
    """
    if value.shape != shape:
        what, hint = f"action {name!r}", ""
        if name is None:
            what, hint = "action", " ([*env.batch_size, *single_action_space.shape])"
        raise ValueError(
            f"ManiSkill {what} of shape {tuple(value.shape)}, expected "
            f"{tuple(shape)}{hint}."
        )
    value = value.unsqueeze(0) if unbatched else value
    return value if device is None else value.to(device)


def _tensor_tree(tree: Mapping, device: torch.device | None = None) -> dict:
    """A nested dict of tensors as plain dicts of normal tensors, copied."""
    return {
        k: _tensor_tree(v, device)
        if isinstance(v, Mapping)
        else torch.as_tensor(v).to(device, copy=True)
        for k, v in tree.items()
    }


class ManiSkillWrapper(_EnvWrapper):
    """TorchRL wrapper for a ManiSkill 3 env made with ``gym.make``.

    ManiSkill (https://github.com/haosulab/ManiSkill) simulates robot manipulation
    tasks on SAPIEN: many envs in one process on the GPU sim, one on the CPU sim. The
    batch is ManiSkill's ``num_envs``. A Box observation space goes to
    ``"observation"``, a Dict one keeps its nested keys and dtypes (images stay
    ``uint8``); a Dict action space (multi-agent tasks) reads ``("action", <agent>)``.
    ``"reward"`` is ``[*batch, 1]`` float32 for every task (some report bool or
    float64 rewards), the done flags ``[*batch, 1]`` bool, truncation being
    ManiSkill's time limit. The tensor infos
    (``"success"``, ``"elapsed_steps"``...) are observation entries, read from
    ``get_info()`` without stepping the env (``"info_<key>"`` where a key collides).

    Every output is on ``env.device``, copied only where ManiSkill writes into its
    tensors later (the GPU sim, the CPU sim rendering with ``sapien_cuda``) or where
    ``env.device`` is not the sim's. Partial resets use ManiSkill's
    ``options={"env_idx": ...}``. After :meth:`set_seed` ``(s)`` the next reset is
    ``reset(seed=s)`` and each later one, partial or full, takes the next draw of
    ``numpy.random.RandomState(s)``. :meth:`get_state` saves the sim state and
    ``env.reset(td, set_state=True, scene_state=state)`` restores it, as Isaac Lab's
    wrapper does. Auto-resetting envs (``ManiSkillVectorEnv(auto_reset=True)``,
    gymnasium's ``Autoreset``) are refused: TorchRL resets done envs itself.

    Args:
        env (gymnasium.Env): a ManiSkill env, e.g. ``gym.make("PickCube-v1")``,
            possibly inside further gym wrappers.

    Keyword Args:
        device (torch.device, optional): where outputs are and actions are read.
            Defaults to the sim's device (``"cpu"`` for the CPU sim, ``"cuda:<i>"``
            for the GPU sim).
        batch_size (torch.Size, optional): ``[num_envs]``, or ``[]`` for one env
            (``num_envs=1``) without the env dim, what
            :class:`~torchrl.envs.ParallelEnv` stacks. Defaults to ``[num_envs]``.
        from_pixels (bool, optional): add the ``render()`` frame under
            ``pixels_key`` at every reset and step; the env must be made with
            ``render_mode="rgb_array"``. Defaults to ``False``.
        pixels_only (bool, optional): keep only the pixels as observation.
            Defaults to ``False``.
        pixels_key (NestedKey, optional): the key of the frames. Defaults to
            ``"pixels"``.
        info_keys (list of str, optional): the info entries to keep. Defaults to
            every tensor entry of ``get_info()``.
        frame_skip (int, optional): steps each action up to ``frame_skip`` times,
            sums the rewards (a bool reward counts its steps) and stops as soon as
            any env is done, as :class:`~torchrl.envs.GymLikeEnv` does: with many
            envs most steps are then single ones, unlike ManiSkill's
            ``ActionRepeatWrapper``. Defaults to ``1``.
        allow_done_after_reset (bool, optional): passed to
            :class:`~torchrl.envs.EnvBase`. Defaults to ``False``.

    ManiSkill reference: Tao et al., "ManiSkill3: GPU Parallelized Robotics
    Simulation and Rendering for Generalizable Embodied AI", arXiv:2410.00425.

    Examples:
        >>> import gymnasium as gym  # doctest: +SKIP
        >>> import mani_skill.envs  # doctest: +SKIP
        >>> from torchrl.envs import ManiSkillWrapper  # doctest: +SKIP
        >>> base = gym.make("PickCube-v1", obs_mode="state")  # doctest: +SKIP
        >>> env = ManiSkillWrapper(base)  # doctest: +SKIP
        >>> _ = env.set_seed(0)  # doctest: +SKIP
        >>> td = env.rollout(3)  # doctest: +SKIP
        >>> td["next", "observation"].shape  # doctest: +SKIP
        torch.Size([1, 3, 42])
        >>> td["next", "success"].shape  # doctest: +SKIP
        torch.Size([1, 3])

    .. seealso:: :class:`ManiSkillEnv`, and
        :class:`~torchrl.trainers.algorithms.configs.envs_libs.ManiSkillEnvConfig`
        for Hydra.
    """

    git_url = "https://github.com/haosulab/ManiSkill"
    libname = "mani_skill"
    _has_frame_skip = True  # _step repeats the action itself, as GymLikeEnv does
    _supports_set_state = True  # reset(td, set_state=True, scene_state=...)

    @_classproperty
    def lib(cls):
        import mani_skill

        return mani_skill

    @_classproperty
    def available_envs(cls) -> list[str]:
        if not _has_maniskill:
            return []
        import mani_skill.envs  # noqa: F401
        from mani_skill.utils.registration import REGISTERED_ENVS

        return sorted(REGISTERED_ENVS)

    def __init__(
        self,
        env: Any = None,
        *,
        device: DEVICE_TYPING | None = None,
        batch_size: Sequence[int] | None = None,
        from_pixels: bool = False,
        pixels_only: bool = False,
        pixels_key: NestedKey = "pixels",
        info_keys: list[str] | None = None,
        allow_done_after_reset: bool = False,
        **kwargs: Any,
    ) -> None:
        _check_args(from_pixels, pixels_only)
        base = getattr(env, "unwrapped", None)
        if getattr(base, "device", None) is None or not hasattr(base, "num_envs"):
            raise TypeError(
                "ManiSkillWrapper wraps ManiSkill 3 envs only, got "
                f"{type(env).__name__}: ManiSkillWrapper(gym.make('PickCube-v1')) "
                "after `import mani_skill.envs`, or ManiSkillEnv('PickCube-v1'). For "
                "other gym envs use torchrl.envs.GymWrapper."
            )
        self._from_pixels = bool(from_pixels)
        self._pixels_only = bool(pixels_only)
        self._pixels_key = pixels_key
        self._info_keys_asked = info_keys
        self._seeds = _ResetSeeds()
        # The sim's device as ManiSkill reports it ("physx_cuda:1" gives cuda:1).
        self._sim_device = _canonical_device(base.device)
        super().__init__(
            env=env,
            device=self._checked_device(device),
            batch_size=self._checked_batch_size(batch_size, base.num_envs),
            allow_done_after_reset=allow_done_after_reset,
            **kwargs,
        )

    def _check_kwargs(self, kwargs: dict) -> None:
        from gymnasium.wrappers import Autoreset
        from mani_skill.envs.sapien_env import BaseEnv
        from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

        env = kwargs["env"]
        base = env.unwrapped
        if not isinstance(base, BaseEnv):
            raise TypeError(
                "ManiSkillWrapper wraps ManiSkill 3 envs only, got "
                f"{type(env).__name__} (unwrapped: {type(base).__name__})."
            )
        if self._from_pixels and base.render_mode != "rgb_array":
            raise ValueError(
                "from_pixels=True needs an env made with render_mode='rgb_array' "
                f"(got render_mode={base.render_mode!r})."
            )
        layers = _layers(env)
        vector = [x for x in layers if isinstance(x, ManiSkillVectorEnv)]
        if any(x.auto_reset for x in vector):
            resetter = "ManiSkillVectorEnv(auto_reset=True)"
        elif any(isinstance(x, Autoreset) for x in layers):
            resetter = "gymnasium.wrappers.Autoreset"
        else:
            resetter = None
        if resetter is not None:
            raise ValueError(
                f"{resetter} resets done envs inside its step and returns the next "
                "episode's first observation in place of the last one: TorchRL resets "
                "done envs itself. Wrap the ManiSkill env without it (gym.make(...), "
                "or ManiSkillVectorEnv(env, auto_reset=False)), or use ManiSkillEnv."
            )
        freq = getattr(base, "reconfiguration_freq", 0) or 0
        if (
            base.num_envs > 1
            and freq
            and not any(x.ignore_terminations for x in vector)
        ):
            raise ValueError(
                f"reconfiguration_freq={freq} with num_envs={base.num_envs}: "
                "ManiSkill cannot reconfigure some of its envs only, and TorchRL "
                "resets each done env on its own. Make the env with "
                "reconfiguration_freq=0, or wrap it in ManiSkillVectorEnv(env, "
                "auto_reset=False, ignore_terminations=True) for episodes that "
                "all end together at the time limit."
            )

    def _build_env(self, env: Any, **kwargs: Any) -> Any:
        if kwargs:
            raise TypeError(
                f"Unexpected arguments for {type(self).__name__}: {sorted(kwargs)}"
            )
        self._unbatched = not self.batch_size
        # Whether ManiSkill hands out tensors that it writes into later: then copied.
        self._copies = _reuses_buffers(env.unwrapped)
        return env

    def _checked_device(self, device: Any) -> torch.device:
        if device is None:
            return self._sim_device
        try:
            device = _canonical_device(device)
        except RuntimeError as err:
            raise ValueError(f"device={device!r} is not a torch device: {err}") from err
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(
                f"device={str(device)!r}, but torch.cuda.is_available() is False: "
                f"leave device out (the sim's device, {self._sim_device}) or install "
                "a CUDA build of torch."
            )
        return device

    @staticmethod
    def _checked_batch_size(batch_size: Any, num_envs: int) -> torch.Size:
        if batch_size is None:
            return torch.Size([num_envs])
        try:
            size = torch.Size(batch_size)
        except TypeError:
            size = None
        if size == torch.Size([num_envs]) or (size == torch.Size([]) and num_envs == 1):
            return size
        raise ValueError(
            f"batch_size={batch_size!r} does not fit a ManiSkill env with "
            f"num_envs={num_envs}: leave it out (batch_size [{num_envs}]), or pass "
            "batch_size=[] with num_envs=1 for one unbatched env."
        )

    def _init_env(self) -> None:
        return None

    @property
    def unwrapped(self) -> Any:
        """The ManiSkill ``BaseEnv`` under the gym wrappers (gymnasium's name)."""
        return self._env.unwrapped

    @property
    def gpu_sim_enabled(self) -> bool:
        return bool(self._env.unwrapped.gpu_sim_enabled)

    @property
    def info_keys(self) -> list[str]:
        """The ManiSkill info keys declared as entries (see ``info_keys`` above)."""
        return [key for key, _ in self._info_map]

    def to(self, device: DEVICE_TYPING) -> ManiSkillWrapper:
        """This env with its outputs on ``device`` from now on, checked as ``device=`` is."""
        return super().to(self._checked_device(device))

    def _make_specs(self, env: Any) -> None:
        import gymnasium as gym

        base = env.unwrapped
        # The spaces of the outermost gym wrapper that has them.
        space = getattr(env, "get_wrapper_attr", lambda name: getattr(env, name))
        obs_space = space("single_observation_space")
        act_space = space("single_action_space")
        batch, device = torch.Size([base.num_envs]), self.device
        obs_spec = _space_to_spec(obs_space, batch, device)
        if not isinstance(obs_spec, Composite):
            obs_spec = Composite(observation=obs_spec, shape=batch, device=device)
        if self._pixels_only:
            obs_spec = Composite(shape=batch, device=device)
        if self._from_pixels:
            # One render camera's size (no public name in ManiSkill), else a render.
            cameras = getattr(base, "_human_render_camera_configs", {}) or {}
            if len(cameras) == 1:
                (cfg,) = cameras.values()
                frame = (cfg.height, cfg.width, 3)
            else:
                frame = tuple(base.render().shape[-3:])
            obs_spec[self._pixels_key] = Bounded(
                low=0, high=255, shape=batch + frame, dtype=torch.uint8, device=device
            )
        # From get_info(): a probe step or reset would change later seeded resets.
        infos, asked = base.get_info(), self._info_keys_asked
        if asked is not None:
            missing = [k for k in asked if k not in infos]
            if missing:
                raise ValueError(
                    f"info_keys {missing} are not reported by {_env_id(base)}: "
                    f"available info keys are {sorted(infos)}."
                )
            infos = {k: infos[k] for k in asked}
        info_spec = _info_spec(infos, batch, device)
        reserved = set(obs_spec.keys()) | _RESERVED_KEYS
        self._info_map: list[tuple[str, str]] = []
        for key in info_spec.keys():
            td_key = f"info_{key}" if key in reserved else key
            obs_spec[td_key] = info_spec[key]
            self._info_map.append((key, td_key))
        action_spec = Composite(
            action=_space_to_spec(act_space, batch, device), shape=batch, device=device
        )
        flag = _bool_spec(batch + (1,), device)
        done_spec = Composite(
            {k: flag.clone() for k in ("done", "terminated", "truncated")},
            shape=batch,
            device=device,
        )
        reward_spec = Unbounded(shape=batch + (1,), dtype=torch.float32, device=device)
        if self._unbatched:
            obs_spec, action_spec = obs_spec.squeeze(0), action_spec.squeeze(0)
            reward_spec, done_spec = reward_spec.squeeze(0), done_spec.squeeze(0)
        self._obs_is_dict = isinstance(obs_space, gym.spaces.Dict)
        if isinstance(act_space, gym.spaces.Dict):
            self._action_names = list(act_space.spaces.keys())
            self._action_shapes = {
                k: action_spec["action", k].shape for k in self._action_names
            }
        else:
            self._action_names = None
            self._action_shapes = action_spec["action"].shape
        self.observation_spec = obs_spec
        self.full_action_spec = action_spec
        self.reward_spec = reward_spec
        self.full_done_spec = done_spec
        # env.action_key, read once: the property costs a microsecond a step.
        self._action_key = self.action_key if self._action_names is None else None

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        # The sim's device, where the actions go (None: they are there already).
        sim = None if self.device == self._sim_device else self._sim_device
        names, shapes = self._action_names, self._action_shapes
        unbatched = self._unbatched
        if names is None:
            value = tensordict[self._action_key]  # a KeyError names the entries
            action = _sim_action(value, shapes, None, unbatched, sim)
        else:
            action = {
                k: _sim_action(tensordict["action", k], shapes[k], k, unbatched, sim)
                for k in names
            }
        obs, reward, terminated, truncated, info = self._env.step(action)
        if self.wrapper_frame_skip > 1 and reward.dtype == torch.bool:
            reward = reward.long()  # GymLikeEnv's 0 + reward: bool + bool stays bool
        for _ in range(self.wrapper_frame_skip - 1):
            if (terminated | truncated).any():
                break
            obs, r, terminated, truncated, info = self._env.step(action)
            reward = reward + r
        source = self._to_source(obs, info, reward, terminated, truncated)
        return TensorDict._new_unsafe(
            self._to_device(source), batch_size=self.batch_size, device=self.device
        )

    def _reset(
        self,
        tensordict: TensorDictBase | None = None,
        *,
        seed: int | None = None,
        options: dict | None = None,
        set_state: bool | None = None,
        scene_state: TensorDictBase | Mapping | None = None,
        **kwargs: Any,
    ) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"Unexpected reset arguments: {sorted(kwargs)}")
        if (scene_state is not None) != bool(set_state):
            raise ValueError(
                "A reset to a saved state takes both set_state=True and scene_state "
                "(from env.get_state()): env.reset(td, set_state=True, "
                "scene_state=state), or env.reset_to_state(state, td)."
            )
        options = dict(options) if options else {}
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        env_idx = None
        if reset is not None:
            # The one host sync of a partial reset on the GPU sim.
            env_idx = reset.reshape(-1).nonzero().squeeze(-1)
            if not env_idx.numel():
                return tensordict.exclude("_reset")
            if env_idx.numel() < reset.numel():
                options["env_idx"] = env_idx.to(self._sim_device)
            else:
                env_idx = None
        if set_state:
            # Nothing is drawn: the saved state makes this episode's start.
            states = self._checked_states(scene_state).to(self._sim_device)
            if env_idx is not None:
                states = states[env_idx]
            # ManiSkill's other entries (its cached "obs" of these envs) as given.
            given = options.get("reset_to_env_states") or {}
            options["reset_to_env_states"] = {**given, "env_states": states.to_dict()}
        else:
            # Partial resets too: ManiSkill seeds torch's RNG only for seeded resets.
            if seed is not None:
                self._seeds.set(seed)
            # States in ManiSkill's options make the starts: unseeded, as CachedResetWrapper's.
            if seed is not None or "reset_to_env_states" not in options:
                seed = self._seeds.draw()
        obs, info = self._env.reset(seed=seed, options=options)
        source = self._to_device(self._to_source(obs, info))
        return TensorDict._new_unsafe(
            source, batch_size=self.batch_size, device=self.device
        )

    def _set_seed(self, seed: int | None) -> None:
        self._seeds.set(seed)

    def _to_source(
        self,
        obs: Any,
        info: Mapping[str, Any],
        reward: torch.Tensor | None = None,
        terminated: torch.Tensor | None = None,
        truncated: torch.Tensor | None = None,
    ) -> dict:
        """The entries of a reset (no reward) or a step, as a nested dict.

        ManiSkill's own tensors: the env dim dropped for batch ``[]``, the reward as
        float32, the ``[B]`` reward and flags as ``[B, 1]``.
        """
        unbatched = self._unbatched
        if self._pixels_only:
            source = {}
        elif self._obs_is_dict:
            source = _mapped(obs, lambda x: x[0]) if unbatched else dict(obs)
        else:
            source = {"observation": obs[0] if unbatched else obs}
        for key, td_key in self._info_map:
            source[td_key] = info[key][0] if unbatched else info[key]
        if self._from_pixels:
            frame = torch.as_tensor(self._env.render())
            frame = frame.unsqueeze(0) if frame.ndim == 3 else frame
            *path, last = (
                self._pixels_key
                if isinstance(self._pixels_key, tuple)
                else (self._pixels_key,)
            )
            node = source
            for k in path:
                node = node.setdefault(k, {})
            node[last] = frame[0] if unbatched else frame
        if reward is not None:
            if reward.dtype != torch.float32:
                reward = reward.to(torch.float32)
            flags = (reward, terminated, truncated, terminated | truncated)
            if not unbatched:
                flags = tuple(x.view(-1, 1) for x in flags)
            keys = ("reward", "terminated", "truncated", "done")
            source.update(zip(keys, flags))
        return source

    def _to_device(self, source: dict) -> dict:
        """The entries of :meth:`_to_source` on ``env.device``.

        Every leaf is copied where ManiSkill writes into its tensors later or
        ``env.device`` is not the sim's, else only the infos (the CPU sim's
        ``elapsed_steps`` is its own state). A subclass may move them otherwise (e.g.
        a step's in one transfer).
        """
        device = self.device
        if self._copies or device != self._sim_device:
            return _mapped(source, lambda x: x.to(device, copy=True))
        for _, td_key in self._info_map:
            source[td_key] = source[td_key].clone()
        return source

    def render(self, *args: Any, **kwargs: Any) -> Any:
        """Renders the env on ``env.device``.

        ManiSkill's frames (``[B, H, W, 3]`` uint8 for ``rgb_array``), copied where
        ManiSkill renders into a reused buffer.
        """
        frame = self._env.render(*args, **kwargs)
        copy = self._copies or self.device != self._sim_device
        if copy and isinstance(frame, torch.Tensor):
            frame = frame.to(self.device, copy=True)
        return frame

    def get_state(self) -> TensorDictBase:
        """Returns every env's sim state, a TensorDict of this env's batch.

        ManiSkill's ``get_state_dict()``: the poses and velocities of its actors and
        articulations, joint positions and velocities; not the controllers' targets.
        On ``env.device``.

        Examples:
            >>> from torchrl.envs import ManiSkillEnv  # doctest: +SKIP
            >>> env = ManiSkillEnv("PickCube-v1", obs_mode="state")  # doctest: +SKIP
            >>> start = env.reset(seed=1)  # doctest: +SKIP
            >>> state = env.get_state()  # doctest: +SKIP
            >>> _ = env.rollout(3)  # doctest: +SKIP
            >>> td = env.reset(set_state=True, scene_state=state)  # doctest: +SKIP
            >>> obs = td["observation"]  # doctest: +SKIP
            >>> (obs == start["observation"]).all().item()  # doctest: +SKIP
            True
        """
        state = self.unwrapped.get_state_dict()
        state = TensorDict._new_unsafe(
            _tensor_tree(state, self.device),
            batch_size=torch.Size([self.unwrapped.num_envs]),
            device=self.device,
        )
        return state[0] if self._unbatched else state

    def reset_to_state(
        self,
        state: TensorDictBase | Mapping,
        tensordict: TensorDictBase | None = None,
        **kwargs: Any,
    ) -> TensorDictBase:
        """Resets every env, or those of ``tensordict``'s ``"_reset"`` mask, to a state.

        ``env.reset(tensordict, set_state=True, scene_state=state)``; called on a
        :class:`~torchrl.envs.TransformedEnv`, it skips the transforms.

        Args:
            state (TensorDictBase or dict): :meth:`get_state`'s layout, one row per
                env, or one env's state without the batch dim (a ManiSkill trajectory
                file's ``env_states`` step), which every env being reset takes. Its
                keys, shapes and dtypes are checked before anything reaches the sim.
            tensordict (TensorDictBase, optional): may hold a ``"_reset"`` mask.

        Keyword Args:
            **kwargs: passed to :meth:`~torchrl.envs.EnvBase.reset`.

        Returns:
            The reset's TensorDict, as :meth:`~torchrl.envs.EnvBase.reset` returns it.
        """
        return self.reset(tensordict, set_state=True, scene_state=state, **kwargs)

    def _checked_states(self, states: TensorDictBase | Mapping) -> TensorDictBase:
        """``states`` as a ``[num_envs]`` TensorDict of the env's state layout."""
        if not isinstance(states, (TensorDictBase, Mapping)):
            raise TypeError(
                "scene_state must be a TensorDict or a dict of tensors "
                f"(env.get_state()), got {type(states).__name__}."
            )
        if not isinstance(states, TensorDictBase):
            states = TensorDict(_tensor_tree(states), batch_size=[])
        # The layout of a read of the sim: a reconfiguration may change it.
        num_envs = self.unwrapped.num_envs
        row = self.get_state()
        row = row if self._unbatched else row[0]
        want, got = set(row.keys(True, True)), set(states.keys(True, True))
        if want != got:
            raise ValueError(
                "scene_state does not have this env's layout (env.get_state()): "
                f"missing {sorted(want - got, key=str)}, unknown "
                f"{sorted(got - want, key=str)}. Pass a state saved from this task "
                "(env.get_state(), or a trajectory file's env_states)."
            )
        out = TensorDict(batch_size=[num_envs])
        for key in sorted(want, key=str):
            ref, value = row.get(key), states.get(key)
            path = "".join(
                f"[{k!r}]" for k in (key if isinstance(key, tuple) else (key,))
            )
            if value.shape == ref.shape:  # one env's state, for every env
                value = value.expand(num_envs, *ref.shape)
            elif value.shape != (num_envs, *ref.shape):
                raise ValueError(
                    f"scene_state{path} has shape {list(value.shape)}; this env takes "
                    f"{[num_envs, *ref.shape]} (one row per env) or {list(ref.shape)} "
                    "(one env's state)."
                )
            if value.dtype != ref.dtype and not (
                value.is_floating_point() and ref.is_floating_point()
            ):
                raise ValueError(
                    f"scene_state{path} has dtype {value.dtype}; this env's is "
                    f"{ref.dtype}."
                )
            # A plain tensor (not a memory-mapped one), copied: the sim reads it later.
            out.set(key, value.as_subclass(torch.Tensor).to(ref.dtype, copy=True))
        return out

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(env={_env_id(self._env)}, "
            f"num_envs={self._env.unwrapped.num_envs}, "
            f"batch_size={list(self.batch_size)}, device={self.device}, "
            f"gpu_sim={self.gpu_sim_enabled})"
        )


class _ManiSkillEnvMeta(_EnvPostInit):
    """Returns a :class:`~torchrl.envs.ParallelEnv` when ``num_workers > 1``."""

    def __call__(cls, *args: Any, num_workers: int | None = None, **kwargs: Any):
        num_workers = 1 if num_workers is None else int(num_workers)
        if num_workers > 1:
            from torchrl.envs import ParallelEnv

            if len(args) > 1 or (not args and "env_name" not in kwargs):
                raise TypeError(
                    f"{cls.__name__} takes the task id, and only it, as a positional "
                    f"argument: {cls.__name__}('PickCube-v1', num_workers=..., ...) "
                    f"(got {len(args)} positional arguments)."
                )
            env_name = args[0] if args else kwargs.pop("env_name")
            if kwargs.get("num_envs", 1) == 1:
                # One unbatched env per worker: the ParallelEnv's batch, [num_workers].
                kwargs.setdefault("batch_size", [])

            def make_env(_env_name=env_name, _kwargs=kwargs):
                return cls(_env_name, **_kwargs)

            return ParallelEnv(num_workers, make_env, metadata_from_workers=True)
        return super().__call__(*args, **kwargs)


class ManiSkillEnv(ManiSkillWrapper, metaclass=_ManiSkillEnvMeta):
    """Builds a ManiSkill 3 task from its registry and wraps it.

    Args:
        env_name (str): a registered task, e.g. ``"PickCube-v1"``
            (``ManiSkillEnv.available_envs`` lists them).

    Keyword Args:
        num_envs (int, optional): envs in the ManiSkill env, the batch size. On the
            CPU sim, which holds one env per process, use ``num_workers`` instead.
            Defaults to ``1``.
        num_workers (int, optional): above 1, a :class:`~torchrl.envs.ParallelEnv`
            of ``num_workers`` such envs, one per process, is returned. Defaults to
            ``1``.
        device (torch.device, optional): see :class:`ManiSkillWrapper`.
        batch_size (torch.Size, optional): see :class:`ManiSkillWrapper`.
        from_pixels (bool, optional): see :class:`ManiSkillWrapper`; it sets
            ``render_mode="rgb_array"``.
        pixels_only (bool, optional): see :class:`ManiSkillWrapper`.
        pixels_key (NestedKey, optional): see :class:`ManiSkillWrapper`.
        info_keys (list of str, optional): see :class:`ManiSkillWrapper`.
        frame_skip (int, optional): see :class:`ManiSkillWrapper`.
        allow_done_after_reset (bool, optional): see :class:`ManiSkillWrapper`.
        **kwargs: passed to ``gym.make``: ``obs_mode``, ``control_mode``,
            ``sim_backend`` (``"auto"``, ``"cpu"``, ``"gpu"``), ``render_mode``,
            ``max_episode_steps``...

    ManiSkill reference: Tao et al., "ManiSkill3: GPU Parallelized Robotics
    Simulation and Rendering for Generalizable Embodied AI", arXiv:2410.00425.

    Examples:
        >>> from torchrl.envs import ManiSkillEnv  # doctest: +SKIP
        >>> env = ManiSkillEnv("PickCube-v1", obs_mode="state_dict")  # doctest: +SKIP
        >>> env.observation_spec["agent", "qpos"].shape  # doctest: +SKIP
        torch.Size([1, 9])
        >>> td = env.rand_step(env.reset())  # doctest: +SKIP
        >>> td["next", "reward"].shape  # doctest: +SKIP
        torch.Size([1, 1])

    .. seealso:: Its Hydra config,
        :class:`~torchrl.trainers.algorithms.configs.envs_libs.ManiSkillEnvConfig`.
    """

    def __init__(
        self,
        env_name: str,
        *,
        num_envs: int = 1,
        device: DEVICE_TYPING | None = None,
        batch_size: Sequence[int] | None = None,
        from_pixels: bool = False,
        pixels_only: bool = False,
        pixels_key: NestedKey = "pixels",
        info_keys: list[str] | None = None,
        frame_skip: int = 1,
        allow_done_after_reset: bool = False,
        **kwargs: Any,
    ) -> None:
        _check_args(from_pixels, pixels_only)
        import gymnasium as gym
        import mani_skill.envs  # noqa: F401

        kwargs = _task_kwargs(env_name, num_envs, from_pixels, batch_size, kwargs)
        if num_envs > 1 and _cpu_sim(num_envs, kwargs.get("sim_backend", "auto")):
            raise ValueError(
                f"num_envs={num_envs} on ManiSkill's CPU sim, which holds one env per "
                f"process: pass num_workers={num_envs} for a ParallelEnv of single "
                "envs, or sim_backend='gpu' on a CUDA machine."
            )
        self._env_id = env_name
        with warnings.catch_warnings():
            # ManiSkill warns that it lowers float64 spaces' precision.
            warnings.filterwarnings("ignore", message=".*precision lowered.*")
            env = gym.make(env_name, num_envs=num_envs, **kwargs)
        try:
            super().__init__(
                env,
                device=device,
                batch_size=batch_size,
                from_pixels=from_pixels,
                pixels_only=pixels_only,
                pixels_key=pixels_key,
                info_keys=info_keys,
                frame_skip=frame_skip,
                allow_done_after_reset=allow_done_after_reset,
            )
        except Exception:
            env.close()
            raise

    @property
    def env_name(self) -> str:
        return self._env_id
