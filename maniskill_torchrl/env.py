"""ManiSkill 3 tasks as native TorchRL environments.

ManiSkill returns batched torch tensors (``[num_envs, ...]``) on the simulation
device; :class:`ManiSkillWrapper` puts them into TensorDicts as they are: no
numpy round trips, no host copies, one TensorDict built per step.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Bounded, Composite
from torchrl.data.utils import DEVICE_TYPING

from maniskill_torchrl._maniskill import (
    enable_physx_gpu,
    maniskill_base_env,
    registered_env_ids,
    render_frame_shape,
    similar_env_ids,
    wrapper_attr,
)
from maniskill_torchrl._private import EnvWrapper, classproperty, new_tensordict
from maniskill_torchrl.cpu_vector import CPUVectorEnv
from maniskill_torchrl.specs import (
    done_spec,
    info_spec_from_infos,
    observation_spec_from_space,
    reward_spec,
    space_to_spec,
)

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]

_has_maniskill = importlib.util.find_spec("mani_skill") is not None

_CPU_BACKENDS = ("cpu", "physx_cpu")


class ManiSkillWrapper(EnvWrapper):
    """A TorchRL env around a ManiSkill 3 env made with ``gym.make``.

    The batch is ManiSkill's ``num_envs`` and the device is the simulation's
    device (``cpu`` for the CPU sim, ``cuda`` for the GPU sim). Each step
    builds one TensorDict from ManiSkill's own tensors:

    - a Box observation space goes to ``"observation"``; a Dict observation
      space (``state_dict``, ``rgb``, ``rgbd``, ``sensor_data``...) keeps its
      nested key paths and dtypes (images stay uint8);
    - a Box action space reads ``"action"``; a Dict action space (multi-agent
      tasks such as TwoRobotPickCube-v1) reads ``("action", <agent>)`` entries;
    - ``reward`` is ``[B, 1]`` float32; ``terminated`` / ``truncated`` /
      ``done`` are ``[B, 1]`` bool (truncation is ManiSkill's time limit);
    - the task's tensor infos (``success``, ``fail``, ``elapsed_steps``...) are
      top-level entries declared in the observation spec, so collectors and
      batched envs keep them. They are learnt from ``env.unwrapped.get_info()``
      without stepping or resetting the env. An info key that collides with an
      observation key is stored as ``"info_<key>"``.

    Seeding: after :meth:`set_seed(s) <set_seed>` the next full reset calls
    ManiSkill's ``reset(seed=s)``; every later full reset is seeded with the next
    draw of ``numpy.random.RandomState(s)``, so a whole run is reproducible
    from ``s``. ``env.reset(seed=s)`` seeds one reset directly. Partial resets
    (a ``"_reset"`` mask that is not all True) reset only those envs through
    ``options={"env_idx": ...}``: unseeded on the GPU sim, as ManiSkill does; on a
    :class:`~maniskill_torchrl.cpu_vector.CPUVectorEnv` seeded with the next draw
    ``d`` (sub-env ``i`` gets ``d + i``), so that CPU runs stay reproducible from
    ``s`` whatever each worker's global torch RNG holds.

    Several CPU envs: wrap a :class:`~maniskill_torchrl.cpu_vector.CPUVectorEnv`
    (``ManiSkillEnv(env_id, num_envs=N)`` does it on the CPU sim): one worker
    process per env, the same batch ``[N]``, keys, specs and dtypes as the GPU sim.

    Partial steps: ManiSkill steps all of its envs together (the GPU sim, and
    the CPU workers of a ``CPUVectorEnv``, which gymnasium steps all at once),
    so a ``"_step"`` mask is not honoured by this env (use a
    :class:`~torchrl.envs.ParallelEnv` of single CPU envs for that).

    Args:
        env: a ManiSkill env, ``gym.make("PickCube-v1", ...)``, possibly
            wrapped in further gym wrappers.

    Keyword Args:
        device: must be the env's device if given (no silent copies).
        from_pixels (bool): add a ``"pixels"`` entry rendered with
            ``env.render()`` at every reset and step; the env must have been
            made with ``render_mode="rgb_array"``.
        pixels_only (bool): keep only ``"pixels"`` as observation.
        info_keys (list of str, optional): the info entries to keep; defaults to
            every tensor entry of ``env.unwrapped.get_info()``.
        allow_done_after_reset (bool): passed to :class:`~torchrl.envs.EnvBase`.

    Examples:
        >>> import gymnasium as gym
        >>> import mani_skill.envs  # registers the tasks
        >>> from maniskill_torchrl import ManiSkillWrapper
        >>> env = ManiSkillWrapper(gym.make("PickCube-v1", num_envs=1, obs_mode="state"))
        >>> env.set_seed(0)
        >>> td = env.rollout(3)
        >>> td["next", "observation"].shape, td["next", "success"].shape
        (torch.Size([1, 3, 42]), torch.Size([1, 3]))
    """

    git_url = "https://github.com/haosulab/ManiSkill"
    libname = "mani_skill"

    @classproperty
    def available_envs(cls) -> list[str]:
        if not _has_maniskill:
            return []
        from mani_skill.utils.registration import REGISTERED_ENVS

        return sorted(REGISTERED_ENVS)

    @classproperty
    def lib(cls):
        import mani_skill

        return mani_skill

    def __init__(
        self,
        env: Any = None,
        *,
        device: DEVICE_TYPING | None = None,
        from_pixels: bool = False,
        pixels_only: bool = False,
        info_keys: list[str] | None = None,
        allow_done_after_reset: bool = False,
        **kwargs,
    ) -> None:
        if env is None:
            raise TypeError(
                "ManiSkillWrapper needs a ManiSkill env: ManiSkillWrapper(gym.make('PickCube-v1')) "
                "or ManiSkillEnv('PickCube-v1')."
            )
        base = env if isinstance(env, CPUVectorEnv) else maniskill_base_env(env)
        if base is None:
            raise TypeError(
                f"ManiSkillWrapper wraps ManiSkill 3 envs only, got {type(env).__name__} "
                f"(unwrapped: {type(getattr(env, 'unwrapped', env)).__name__}). Make one with "
                "gym.make('<Task>-v1', ...) after `import mani_skill.envs`, or CPUVectorEnv('<Task>-v1', N) "
                "for N CPU-sim envs; for other gym envs use torchrl.envs.GymWrapper."
            )
        env_device = torch.device(base.device)
        if device is not None and torch.device(device) != env_device:
            raise ValueError(
                f"device={device} differs from the ManiSkill env's device {env_device}. "
                "Make the env on the device you want (sim_backend='gpu' for CUDA) or omit device: "
                "this wrapper does not copy data between devices."
            )
        if pixels_only and not from_pixels:
            raise ValueError("pixels_only=True needs from_pixels=True.")
        if from_pixels and base.render_mode != "rgb_array":
            raise ValueError(
                "from_pixels=True needs an env made with render_mode='rgb_array' "
                f"(got render_mode={base.render_mode!r})."
            )
        self._seeds_partial_resets = isinstance(base, CPUVectorEnv)
        self._from_pixels = bool(from_pixels)
        self._pixels_only = bool(pixels_only)
        self._requested_info_keys = info_keys
        self._seed_rng: np.random.RandomState | None = None
        self._next_seed: int | None = None
        super().__init__(
            env=env,
            device=env_device,
            batch_size=torch.Size([base.num_envs]),
            allow_done_after_reset=allow_done_after_reset,
            **kwargs,
        )

    # ------------------------------------------------------------------ build
    def _check_kwargs(self, kwargs: dict) -> None:
        if "env" not in kwargs:
            raise TypeError("Expected an 'env' keyword argument.")

    def _build_env(self, env: Any, **kwargs) -> Any:
        if kwargs:
            raise TypeError(f"Unexpected arguments for ManiSkillWrapper: {sorted(kwargs)}")
        return env

    def _init_env(self) -> None:
        return None

    @property
    def base_env(self):
        """The ManiSkill ``BaseEnv`` (``env.unwrapped``)."""
        return self._env.unwrapped

    @property
    def gpu_sim_enabled(self) -> bool:
        return bool(self._env.unwrapped.gpu_sim_enabled)

    def _make_specs(self, env: Any) -> None:
        base = env.unwrapped
        batch, device = self.batch_size, self.device
        obs_space = wrapper_attr(env, "single_observation_space")
        act_space = wrapper_attr(env, "single_action_space")

        obs_spec = observation_spec_from_space(obs_space, batch, device)
        self._obs_is_dict = isinstance(obs_space, gym.spaces.Dict)
        if self._pixels_only:
            obs_spec = Composite(shape=batch, device=device)
        if self._from_pixels:
            obs_spec["pixels"] = self._pixels_spec(base)

        # Info keys come from get_info(): a probe step or reset would change what later seeded resets give.
        infos = base.get_info()
        if self._requested_info_keys is not None:
            missing = [k for k in self._requested_info_keys if k not in infos]
            if missing:
                raise ValueError(
                    f"info_keys {missing} are not reported by {base.spec.id if base.spec else base}: "
                    f"available info keys are {sorted(infos)}."
                )
            infos = {k: infos[k] for k in self._requested_info_keys}
        info_spec = info_spec_from_infos(infos, batch, device)
        reserved = set(obs_spec.keys()) | {"reward", "done", "terminated", "truncated", "action"}
        self._info_map: list[tuple[str, str]] = []
        for key in info_spec.keys():
            td_key = f"info_{key}" if key in reserved else key
            obs_spec[td_key] = info_spec[key]
            self._info_map.append((key, td_key))

        action_spec = space_to_spec(act_space, batch, device)
        self._action_names = list(act_space.spaces.keys()) if isinstance(act_space, gym.spaces.Dict) else None
        self._action_shapes = (
            {k: action_spec[k].shape for k in self._action_names}
            if self._action_names is not None
            else action_spec.shape
        )
        self.observation_spec = obs_spec
        self.full_action_spec = Composite(action=action_spec, shape=batch, device=device)
        self.reward_spec = reward_spec(batch, device)
        self.done_spec = done_spec(batch, device)

    def _pixels_spec(self, base) -> Bounded:
        shape = base.render_frame_shape() if isinstance(base, CPUVectorEnv) else render_frame_shape(base)
        return Bounded(
            low=0,
            high=255,
            shape=self.batch_size + torch.Size(shape),
            dtype=torch.uint8,
            device=self.device,
        )

    # ------------------------------------------------------------------ data
    def _render_batched(self, frame: Any) -> torch.Tensor:
        frame = torch.as_tensor(frame, device=self.device)
        if frame.ndim == 3:
            frame = frame.unsqueeze(0)
        return frame

    def _to_tensordict(self, obs: Any, info: Mapping[str, Any]) -> dict:
        if self._pixels_only:
            source = {}
        elif self._obs_is_dict:
            source = dict(obs)
        else:
            source = {"observation": obs}
        # Info tensors may alias ManiSkill's buffers (elapsed_steps is updated in place): clone them.
        for key, td_key in self._info_map:
            source[td_key] = info[key].clone()
        if self._from_pixels:
            source["pixels"] = self._render_batched(self._env.render())
        return source

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action", None)
        if action is None:
            raise self._missing_action(tensordict, "action")
        if self._action_names is None:
            if action.shape != self._action_shapes:
                raise ValueError(
                    f"ManiSkill action of shape {tuple(action.shape)}, expected "
                    f"{tuple(self._action_shapes)} ([num_envs, *single_action_space.shape])."
                )
        else:
            action = {k: action.get(k, None) for k in self._action_names}
            for k, a in action.items():
                if a is None:
                    raise self._missing_action(tensordict, ("action", k))
                if a.shape != self._action_shapes[k]:
                    raise ValueError(
                        f"ManiSkill action {k!r} of shape {tuple(a.shape)}, expected {tuple(self._action_shapes[k])}."
                    )
        obs, reward, terminated, truncated, info = self._env.step(action)
        source = self._to_tensordict(obs, info)
        # ManiSkill gives [B] tensors: unsqueeze is the cheapest way to [B, 1] (view(shape) costs
        # twice as much on the CPU sim, where each op counts); other shapes go through view.
        done = torch.logical_or(terminated, truncated)
        if reward.ndim == terminated.ndim == truncated.ndim == 1:
            source["reward"] = reward.unsqueeze(-1)
            source["terminated"] = terminated.unsqueeze(-1)
            source["truncated"] = truncated.unsqueeze(-1)
            source["done"] = done.unsqueeze(-1)
        else:
            shape = self.batch_size + (1,)
            source["reward"] = reward.view(shape)
            source["terminated"] = terminated.view(shape)
            source["truncated"] = truncated.view(shape)
            source["done"] = done.view(shape)
        return new_tensordict(source, batch_size=self.batch_size, device=self.device)

    def _missing_action(self, tensordict: TensorDictBase, key: str | tuple[str, str]) -> KeyError:
        keys = sorted(tensordict.keys(include_nested=True, leaves_only=True), key=str)
        return _MissingActionError(
            f"{type(self).__name__}.step() found no action at {key!r} in the tensordict, whose entries are "
            f"{keys}. Set the action entries {self.action_keys} (shapes from env.full_action_spec), e.g. "
            "td = env.rand_action(td) for random actions, or run a policy that writes them."
        )

    def _step_proc_data(self, next_tensordict_out: TensorDictBase) -> TensorDictBase:
        # _step already writes reward and the three done entries with their spec shapes and dtypes,
        # so EnvBase's reshaping and done completion have nothing to do: skip them (a measurable
        # share of the per-step overhead on the CPU sim). Type checks still run when asked for.
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict_out)
        return next_tensordict_out

    def _reset(
        self,
        tensordict: TensorDictBase | None = None,
        *,
        seed: int | None = None,
        options: dict | None = None,
        **kwargs,
    ) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"Unexpected reset arguments: {sorted(kwargs)}")
        options = dict(options) if options else {}
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        if reset is not None:
            reset = reset.reshape(self.batch_size)
            if not reset.any():
                return tensordict.exclude("_reset")
            if not reset.all():
                options["env_idx"] = reset.nonzero().squeeze(-1)
        if "env_idx" not in options:
            if seed is not None:
                self._set_seed(seed)
            seed = self._draw_seed()
        elif self._seeds_partial_resets:
            # CPU sub-envs restart from drawn seeds too: reproducible from set_seed, whatever
            # each worker process's global torch RNG holds (unseeded ManiSkill resets draw from it).
            seed = self._draw_seed() if seed is None else seed
        obs, info = self._env.reset(seed=seed, options=options)
        source = self._to_tensordict(obs, info)
        return new_tensordict(source, batch_size=self.batch_size, device=self.device)

    # --------------------------------------------------------------- seeding
    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            self._seed_rng = self._next_seed = None
            return
        seed = int(seed)
        self._next_seed = seed
        self._seed_rng = np.random.RandomState(seed % 2**32)

    def _draw_seed(self) -> int | None:
        if self._seed_rng is None:
            return None
        if self._next_seed is not None:
            seed, self._next_seed = self._next_seed, None
            return seed
        return int(self._seed_rng.randint(2**31))

    # -------------------------------------------------------------- misc
    def render(self) -> Any:
        """ManiSkill's ``render()`` (batched ``[B, H, W, 3]`` uint8 tensor for ``rgb_array``)."""
        return self._env.render()

    def close(self, *, raise_if_closed: bool = True) -> None:
        env = self.__dict__.get("_env")
        if env is not None and not isinstance(env, _ClosedEnv):
            # A stand-in that says the env is closed: a closed ManiSkill sim fails with AttributeErrors.
            self._env = _ClosedEnv(f"{type(self).__name__}({self._env_name(env)})")
            env.close()
        super().close(raise_if_closed=raise_if_closed)

    @staticmethod
    def _env_name(env: Any) -> str:
        spec = getattr(env.unwrapped, "spec", None)
        return spec.id if spec is not None else type(env.unwrapped).__name__

    def __repr__(self) -> str:
        if isinstance(self._env, _ClosedEnv):
            return f"{self._env.name} (closed)"
        name = self._env_name(self._env)
        return (
            f"{type(self).__name__}(env={name}, num_envs={self.batch_size[0]}, "
            f"device={self.device}, gpu_sim={self.gpu_sim_enabled})"
        )


class _MissingActionError(KeyError):
    """A KeyError whose message prints as written (KeyError prints the repr of its argument)."""

    def __str__(self) -> str:
        return str(self.args[0])


class _ClosedEnv:
    """Takes the ManiSkill env's place after ``close()``: stepping, resetting or rendering says that
    the env is closed (a closed ManiSkill sim fails with unrelated AttributeErrors)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def _closed(self, *args: Any, **kwargs: Any) -> Any:
        raise RuntimeError(
            f"{self.name} is closed: it cannot step, reset or render any more. "
            "Make a new env (ManiSkillEnv(...) or ManiSkillWrapper(gym.make(...))) instead of reusing a closed one."
        )

    step = reset = render = _closed

    @property
    def unwrapped(self) -> Any:
        return self._closed()

    def close(self) -> None:
        return None


class ManiSkillEnv(ManiSkillWrapper):
    """Makes a ManiSkill task with ``gym.make`` and wraps it as a TorchRL env.

    Args:
        env_id (str): a registered ManiSkill task, e.g. ``"PickCube-v1"``.

    Keyword Args:
        num_envs (int): parallel envs, the batch size. On the GPU sim, one
            simulator; on the CPU sim (``sim_backend="cpu"``, or ``"auto"``
            without CUDA), which holds one env per process, ``num_envs > 1``
            runs one worker process per env
            (:class:`~maniskill_torchrl.cpu_vector.CPUVectorEnv`, gymnasium's
            ``AsyncVectorEnv`` underneath) with the same keys, specs and dtypes.
        from_pixels (bool): add ``"pixels"`` (sets ``render_mode="rgb_array"``).
        pixels_only, info_keys, device, allow_done_after_reset: as in
            :class:`ManiSkillWrapper`.
        **maniskill_kwargs: passed to ``gym.make`` (``obs_mode``,
            ``control_mode``, ``sim_backend``, ``render_mode``,
            ``max_episode_steps``...).

    Examples:
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> env = ManiSkillEnv("PickCube-v1", obs_mode="state_dict")
        >>> env.observation_spec["agent", "qpos"].shape
        torch.Size([1, 9])
        >>> td = env.rand_step(env.reset())
        >>> td["next", "reward"].shape
        torch.Size([1, 1])
    """

    def __init__(
        self,
        env_id: str,
        *,
        num_envs: int = 1,
        device: DEVICE_TYPING | None = None,
        from_pixels: bool = False,
        pixels_only: bool = False,
        info_keys: list[str] | None = None,
        allow_done_after_reset: bool = False,
        **maniskill_kwargs,
    ) -> None:
        if env_id not in registered_env_ids():
            close = similar_env_ids(env_id)
            raise ValueError(
                f"Unknown ManiSkill env id {env_id!r}. "
                + (f"Did you mean one of {close}? " if close else "")
                + "ManiSkillEnv.available_envs lists the registered tasks."
            )
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}.")
        if from_pixels:
            maniskill_kwargs.setdefault("render_mode", "rgb_array")
        self._env_id = env_id
        backend = str(maniskill_kwargs.get("sim_backend", "auto")).lower()
        # ManiSkill's "auto" is the CPU sim for one env; for more, the GPU sim when there is CUDA.
        on_cpu = backend in _CPU_BACKENDS or (backend == "auto" and (num_envs == 1 or not torch.cuda.is_available()))
        if num_envs > 1 and on_cpu:
            # The CPU sim holds one env per process: one worker process per env.
            maniskill_kwargs["sim_backend"] = "physx_cpu"
            env = CPUVectorEnv(env_id, num_envs, **maniskill_kwargs)
        else:
            if not on_cpu:
                if not torch.cuda.is_available():
                    raise ValueError(
                        f"sim_backend={maniskill_kwargs['sim_backend']!r} is ManiSkill's GPU sim, which needs "
                        "CUDA, and torch.cuda.is_available() is False: use sim_backend='cpu' (or 'auto')."
                    )
                enable_physx_gpu()
            env = gym.make(env_id, num_envs=num_envs, **maniskill_kwargs)
        super().__init__(
            env,
            device=device,
            from_pixels=from_pixels,
            pixels_only=pixels_only,
            info_keys=info_keys,
            allow_done_after_reset=allow_done_after_reset,
        )

    @property
    def env_id(self) -> str:
        return self._env_id
