"""ManiSkill 3 tasks as native TorchRL environments: :class:`ManiSkillWrapper` and :class:`ManiSkillEnv`.

ManiSkill returns batched torch tensors (``[num_envs, ...]``) on the simulation device;
:class:`ManiSkillWrapper` puts them into TensorDicts: no numpy round trips, no host copies, one
TensorDict built per step, and a device copy only of what ManiSkill would overwrite later (the GPU
sim's buffers) or what must reach another device (a CPU-sim env with ``device="cuda"``). It holds
the whole adapter: specs learnt from the env's spaces and ``get_info()``, the entries of each
reset and step, actions, seeding, saved states (:meth:`~ManiSkillWrapper.get_state`,
:meth:`~ManiSkillWrapper.reset_to_state`, checked before they reach the sim: ManiSkill's
``set_state_dict`` trusts its input), the device rule, and the CPU workers' action repeat.
:class:`ManiSkillEnv` makes the ManiSkill env from a task id first, and is the one place that picks
the CPU engine (:class:`~maniskill_torchrl.CPUVectorEnv`) for several CPU-sim envs; the wrapper only
reads the capabilities an engine declares.

Pure helpers live beside it: spec conversion (``maniskill_torchrl.envs._specs``), argument checks and
errors (``maniskill_torchrl.envs._checks``), ManiSkill / SAPIEN helpers (``maniskill_torchrl._maniskill``),
the one-transfer host gather (``maniskill_torchrl._host_gather``) and the reset seeds
(``envs/_seeding.py``).
"""

from __future__ import annotations

import contextlib
import importlib.util
from collections.abc import Callable, Mapping, Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data.utils import DEVICE_TYPING

from maniskill_torchrl._host_gather import HostGather
from maniskill_torchrl._maniskill import (
    canonical_device,
    check_assets,
    default_render_backend,
    enable_physx_gpu,
    make_maniskill,
    no_asset_prompt,
    registered_env_ids,
    render_frame_shape,
    reuses_buffers,
    similar_env_ids,
    wrapper_attr,
)
from maniskill_torchrl._private import EnvWrapper, classproperty, new_tensordict
from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv
from maniskill_torchrl.envs._checks import (
    ClosedEnv,
    action_error,
    check_frame_skip,
    check_info_keys,
    checked_base_env,
    checked_batch_size,
    checked_device,
)
from maniskill_torchrl.envs._seeding import ResetSeeds
from maniskill_torchrl.envs._specs import env_specs

if TYPE_CHECKING:
    from mani_skill.envs.sapien_env import BaseEnv
    from torchrl.envs import EnvBase

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]

_has_maniskill = importlib.util.find_spec("mani_skill") is not None
_CPU_BACKENDS = ("cpu", "physx_cpu")


class ManiSkillWrapper(EnvWrapper):
    """A TorchRL env around a ManiSkill 3 env made with ``gym.make``.

    The batch is ManiSkill's ``num_envs``. Every leaf of every output (steps, resets,
    ``"pixels"``, ``render()``, infos, :meth:`get_state`) is on ``env.device``: by default the
    sim's device (``cpu`` for the CPU sim, as ManiSkill's ``backend.device``, whatever renders
    its pictures; ``cuda:<index>`` for the GPU sim). Each step builds one TensorDict from
    ManiSkill's own tensors:

    - a Box observation space goes to ``"observation"``; a Dict observation
      space (``state_dict``, ``rgb``, ``rgbd``, ``sensor_data``...) keeps its
      nested key paths and dtypes (images stay uint8);
    - a Box action space reads ``"action"``; a Dict action space (multi-agent
      tasks such as TwoRobotPickCube-v1) reads ``("action", <agent>)`` entries;
    - ``reward`` is ``[B, 1]`` float32 for every task (a task's bool or float64 reward is cast,
      as TorchRL's losses and value estimators expect float rewards of one dtype); ``terminated`` / ``truncated`` /
      ``done`` are ``[B, 1]`` bool (truncation is ManiSkill's time limit);
    - the task's tensor infos (``success``, ``fail``, ``elapsed_steps``...) are
      top-level entries declared in the observation spec, so collectors and
      batched envs keep them. They are learnt from ``env.unwrapped.get_info()``
      without stepping or resetting the env. An info key that collides with an
      observation key is stored as ``"info_<key>"``.

    Nothing this env returns is written into later by the simulator. Where ManiSkill hands out
    buffers that it overwrites (the GPU sim: camera pictures, hidden actors' poses; the CPU sim
    rendering with ``render_backend="sapien_cuda"``, the default on a CUDA machine: camera
    pictures, on the GPU), observations, ``"pixels"``, rewards and done flags are copied, once,
    onto ``env.device``; infos always are. The CPU sim rendering on the CPU returns fresh
    tensors, used as they are when ``env.device`` is the CPU.

    Auto-resetting envs are refused (``ManiSkillVectorEnv(auto_reset=True)``, gymnasium's
    ``Autoreset``): TorchRL resets done envs itself, and an env that already did would lose each
    episode's final observation. ``ManiSkillVectorEnv(env, auto_reset=False)`` is fine.

    Seeding: after :meth:`set_seed(s) <set_seed>` the next full reset calls
    ManiSkill's ``reset(seed=s)``; every later full reset is seeded with the next
    draw of ``numpy.random.RandomState(s)``, so a whole run is reproducible
    from ``s``. ``env.reset(seed=s)`` seeds one reset directly. Partial resets
    (a ``"_reset"`` mask that is not all True) reset only those envs through
    ``options={"env_idx": ...}``: unseeded on the GPU sim, as ManiSkill does; on a
    :class:`~maniskill_torchrl.CPUVectorEnv` seeded with the next draw
    ``d`` (sub-env ``i`` gets ``d + i``), so that CPU runs stay reproducible from
    ``s`` whatever each sub-env's process's global torch RNG holds.

    Several CPU envs: wrap a :class:`~maniskill_torchrl.CPUVectorEnv`
    (``ManiSkillEnv(env_id, num_envs=N)`` does it on the CPU sim): one process per
    env (sub-env 0 in this one), the same batch ``[N]``, keys, specs and dtypes as the GPU sim.

    Partial steps: ManiSkill steps all of its envs together (the GPU sim, and the sub-envs of a
    ``CPUVectorEnv``), so a ``"_step"`` mask is not honoured (a :class:`~torchrl.envs.ParallelEnv`
    of single CPU envs honours it). On a ``CPUVectorEnv``, :class:`~maniskill_torchrl.transforms.ActionRepeat`
    has the sub-envs repeat each action themselves (:meth:`request_worker_repeat`).

    The wrapper never names the CPU engine (``maniskill_torchrl.engines``; only
    :class:`ManiSkillEnv` picks it): it reads the capabilities an engine declares
    (``returns_copies``, ``runs_inference_mode``, ``seeds_partial_resets``,
    ``reconfigures_partially``, ``repeats_actions``, ``render_frame_shape()``), which a ManiSkill
    ``BaseEnv`` does not have.

    Args:
        env: a ManiSkill env, ``gym.make("PickCube-v1", ...)``, possibly
            wrapped in further gym wrappers.

    Keyword Args:
        device: where the outputs are, and where actions are taken (TorchRL's meaning, as
            ``GymWrapper`` moves data): default, the sim's device. ``device="cuda"`` on a
            CPU-sim env feeds a GPU policy: the sim steps on the CPU, its host outputs go to the
            GPU in one non-blocking copy per step (``sapien_cuda`` pictures, already there, are
            copied on the GPU) and actions are moved to the CPU. ``env.to(device)`` later is the
            same. ``"cuda"`` and ``"cuda:0"`` name one device where the current CUDA device is 0.
        from_pixels (bool): add a ``"pixels"`` entry rendered with
            ``env.render()`` at every reset and step; the env must have been
            made with ``render_mode="rgb_array"``.
        pixels_only (bool): keep only ``"pixels"`` as observation.
        info_keys (list of str, optional): the info entries to keep; defaults to
            every tensor entry of ``env.unwrapped.get_info()``.
        allow_done_after_reset (bool): passed to :class:`~torchrl.envs.EnvBase`.
        inference_mode (bool): run ManiSkill's ``step``, ``reset`` and ``render`` under
            :func:`torch.inference_mode` (default False here; :class:`ManiSkillEnv`, which
            builds and owns its ManiSkill env, turns it on for the CPU sim). A CPU-sim step is
            hundreds of small torch ops, and inference mode skips autograd's bookkeeping for
            each: the same values for less CPU. The tensors this env returns are copies made
            outside inference mode, normal tensors. ManiSkill's own state tensors become
            inference tensors, so calling the ManiSkill env's methods yourself, outside
            inference mode, after this env used it raises ``"Inplace update to inference
            tensor outside InferenceMode"`` (PickCube-v1's ``reset`` does): make those calls
            under ``torch.inference_mode()``. A
            :class:`~maniskill_torchrl.CPUVectorEnv`'s sub-envs always use it (only
            numpy copies leave them), whatever this says.
        batch_size (list of int, optional): ``[num_envs]`` (the default), or ``[]`` for one
            ManiSkill env (``num_envs=1``) as an unbatched TorchRL env: specs and entries without
            the env dim (observations ``[*obs]``, infos ``[]``, ``reward`` and done flags ``[1]``,
            ``"action"`` ``[*single_action_space.shape]``), what
            :class:`~torchrl.envs.ParallelEnv` / :class:`~torchrl.envs.SerialEnv` stack. The
            same values as :class:`~maniskill_torchrl.transforms.CPUUnbatch` on the batch-``[1]``
            env, squeezed while each step's TensorDict is built instead of by a transform:
            a ``TransformedEnv`` costs each step more CPU than this env's own step does.
            ``render()`` still returns ManiSkill's batched frames.

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
    def lib(cls) -> ModuleType:
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
        inference_mode: bool = False,
        batch_size: Sequence[int] | None = None,
        **kwargs: Any,
    ) -> None:
        check_frame_skip(kwargs.get("frame_skip"))
        base = checked_base_env(env, from_pixels=from_pixels, pixels_only=pixels_only)
        self._sim_device = canonical_device(base.device)
        device = checked_device(device, self._sim_device)
        batch_size = checked_batch_size(batch_size, base.num_envs)
        # An engine's sub-envs (CPUVectorEnv) run inference mode themselves and return copies.
        self._inference = bool(inference_mode) and not getattr(base, "runs_inference_mode", False)
        self._sim_mode = torch.inference_mode if self._inference else contextlib.nullcontext
        # What leaves this env is copied where ManiSkill may overwrite it later (the GPU sim's
        # buffers, sapien_cuda pictures) or made it under inference mode; nowhere else.
        # An engine that returns fresh copies (CPUVectorEnv) needs none.
        self._copies = self._inference or (not getattr(base, "returns_copies", False) and reuses_buffers(base))
        self._seeds_partial_resets = getattr(base, "seeds_partial_resets", False)
        # The workers' action repeat (request_worker_repeat): only an engine that declares
        # repeats_actions, wrapped as is, has workers. Each step runs with the repeat asked for
        # it, else with the one the env had when wrapped.
        self._workers = base if env is base and getattr(base, "repeats_actions", False) else None
        self._plain_repeat = base.repeat if self._workers is not None else 1
        self._next_repeat = 0  # 0: no request for the next step
        self._from_pixels = bool(from_pixels)
        self._pixels_only = bool(pixels_only)
        self._requested_info_keys = info_keys
        self._unbatched = not batch_size
        self._set_device_rule(device)
        self._seeds = ResetSeeds()
        super().__init__(
            env=env,
            device=device,
            batch_size=batch_size,
            allow_done_after_reset=allow_done_after_reset,
            **kwargs,
        )

    # ------------------------------------------------------------------ build
    def _check_kwargs(self, kwargs: dict[str, Any]) -> None:
        if "env" not in kwargs:
            raise TypeError("Expected an 'env' keyword argument.")

    def _build_env(self, env: Any, **kwargs: Any) -> Any:
        if kwargs:
            raise TypeError(f"Unexpected arguments for ManiSkillWrapper: {sorted(kwargs)}")
        return env

    def _init_env(self) -> None:
        return None

    @property
    def base_env(self) -> BaseEnv | Any:
        """The ManiSkill ``BaseEnv`` (``env.unwrapped``), or the wrapped engine
        (:class:`~maniskill_torchrl.CPUVectorEnv`)."""
        return self._env.unwrapped

    @property
    def inference_mode(self) -> bool:
        """Whether this env calls ManiSkill under :func:`torch.inference_mode` in this process.

        Code that shares the ManiSkill env (``env.base_env``) should make its own calls into it
        under ``torch.inference_mode()`` too when this is True.
        """
        return self._inference

    @property
    def gpu_sim_enabled(self) -> bool:
        return bool(self._env.unwrapped.gpu_sim_enabled)

    # ------------------------------------------------------------------ device rule and specs
    def _set_device_rule(self, device: torch.device) -> None:
        """How outputs reach ``device`` and actions the sim: at build time, and again at every
        ``env.to(device)``."""
        # Every output goes to the env's device. What the sim hands out is copied there once where
        # it must be: ManiSkill may write into it later (the GPU sim, sapien_cuda pictures), it
        # was made under inference mode (the user gets normal tensors), or it is elsewhere
        # (a CPU-sim env with device="cuda"; sapien_cuda pictures of a CPU-sim env on the CPU).
        unbatched = self._unbatched
        self._moves = device != self._sim_device
        self._copy_out = self._copies or self._moves
        # The CPU sim feeding an accelerator: a step's host outputs go up in one transfer
        # (HostGather), its sapien_cuda pictures are copied on the device.
        self._gather = HostGather(device) if self._moves and self._sim_device.type == "cpu" else None
        if self._gather is not None:
            self._obs_leaf = self._info_leaf = _unbatch if unbatched else None
        else:
            self._obs_leaf = _leaf(device, unbatched, self._copy_out)
            self._info_leaf = _leaf(device, unbatched, True)  # infos may alias ManiSkill's (elapsed_steps)

    def to(self, device: Any) -> EnvBase:
        """This env with its outputs on ``device`` from now on, and its actions taken there.

        Every output (steps, resets, ``"pixels"``, :meth:`render`, infos, :meth:`get_state`)
        follows, as if the env had been built with ``device=device``: TorchRL calls this for
        ``Collector(env, policy, device=...)``, ``env_device=``, ``TransformedEnv.to`` and
        ``SerialEnv.to``. Returns this env.
        """
        device = checked_device(device, self._sim_device)
        super().to(device)
        self._set_device_rule(self.device)
        return self

    def _make_specs(self, env: Any) -> None:
        base = env.unwrapped
        obs_space = wrapper_attr(env, "single_observation_space")
        act_space = wrapper_attr(env, "single_action_space")
        frame_shape = None
        if self._from_pixels:
            # An engine (CPUVectorEnv) asks one of its sub-envs; a ManiSkill env has no such method.
            engine_frame_shape = getattr(base, "render_frame_shape", None)
            frame_shape = engine_frame_shape() if callable(engine_frame_shape) else render_frame_shape(base)
        specs = env_specs(
            obs_space,
            act_space,
            self._infos(base),
            torch.Size([base.num_envs]),
            self.device,
            frame_shape=frame_shape,
            pixels_only=self._pixels_only,
        )
        if self._unbatched:
            fields = ("observation", "action", "reward", "done")
            specs = specs._replace(**{f: getattr(specs, f).squeeze(0) for f in fields})
        self._obs_is_dict = isinstance(obs_space, gym.spaces.Dict)
        self._info_map: list[tuple[str, str]] = specs.info_map
        action_spec = specs.action["action"]
        self._action_names = list(act_space.spaces.keys()) if isinstance(act_space, gym.spaces.Dict) else None
        self._action_shapes = (
            {k: action_spec[k].shape for k in self._action_names}
            if self._action_names is not None
            else action_spec.shape
        )
        self.observation_spec = specs.observation
        self.full_action_spec = specs.action
        self.reward_spec = specs.reward
        self.done_spec = specs.done

    def _infos(self, base: Any) -> dict[str, Any]:
        """The info entries to declare: ``info_keys`` (checked) or all of them."""
        # From get_info(): a probe step or reset would change what later seeded resets give.
        infos = base.get_info()
        if self._requested_info_keys is None:
            return infos
        check_info_keys(self._requested_info_keys, infos, base)
        return {k: infos[k] for k in self._requested_info_keys}

    # ------------------------------------------------------------------ step, reset
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._workers is not None:
            self._set_worker_repeat()
        action = self._sim_action(tensordict)
        with self._sim_mode():
            obs, reward, terminated, truncated, info = self._env.step(action)
        source = self._to_tensordict(obs, info)
        # TorchRL's float32 reward for every task: some report bool (DrawTriangle-v1) or float64
        # (RotateValveLevel*) rewards. The cast is a copy; done below is a new tensor. With a
        # gather (_on_device), all stays on the host until its one transfer.
        copy = self._copy_out and self._gather is None
        if copy or reward.dtype != torch.float32:
            reward = reward.to(self.device if copy else None, torch.float32, copy=copy)
        if copy:
            terminated = terminated.to(self.device, copy=True)
            truncated = truncated.to(self.device, copy=True)
        # ManiSkill gives [B] tensors: unsqueeze is the cheapest way to [B, 1] (view(shape) costs
        # twice as much on the CPU sim, where each op counts), and an unbatched env's [1] entries
        # are ManiSkill's [1] tensors as they are; other shapes go through view.
        done = torch.logical_or(terminated, truncated)
        if reward.ndim == terminated.ndim == truncated.ndim == 1:
            if not self._unbatched:
                reward, terminated = reward.unsqueeze(-1), terminated.unsqueeze(-1)
                truncated, done = truncated.unsqueeze(-1), done.unsqueeze(-1)
        else:
            shape = self.batch_size + (1,)
            reward, terminated = reward.view(shape), terminated.view(shape)
            truncated, done = truncated.view(shape), done.view(shape)
        source["reward"] = reward
        source["terminated"] = terminated
        source["truncated"] = truncated
        source["done"] = done
        return new_tensordict(self._on_device(source), batch_size=self.batch_size, device=self.device)

    def _step_proc_data(self, next_tensordict_out: TensorDictBase) -> TensorDictBase:
        # _step already writes reward and the three done entries with their spec shapes and dtypes,
        # so EnvBase's reshaping and done completion have nothing to do: skip them (a measurable
        # share of the per-step overhead on the CPU sim). Type checks still run when asked for.
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict_out)
        return next_tensordict_out

    # ``env.reset(td, set_state=True, env_states=...)``: TorchRL's deterministic-reset convention
    # (as IsaacLabWrapper's ``scene_state``), the saved states passed beside the tensordict.
    _supports_set_state = True

    def _reset(
        self,
        tensordict: TensorDictBase | None = None,
        *,
        seed: int | None = None,
        options: dict | None = None,
        set_state: bool | None = None,
        env_states: TensorDictBase | Mapping | None = None,
        **kwargs: Any,
    ) -> TensorDictBase:
        if kwargs:
            raise TypeError(f"Unexpected reset arguments: {sorted(kwargs)}")
        _check_set_state(set_state, env_states)
        options = dict(options) if options else {}
        reset = tensordict.get("_reset", None) if tensordict is not None else None
        env_idx = None
        if reset is not None:
            # The one host sync of a partial reset on the GPU sim: which envs. None, all or some
            # of them is then read off the index's host-side shape.
            env_idx = reset.reshape(-1).nonzero().squeeze(-1)
            if not env_idx.numel():
                return tensordict.exclude("_reset")
            if env_idx.numel() < reset.numel():
                env_idx = options["env_idx"] = env_idx.to(self._sim_device) if self._moves else env_idx
            else:
                env_idx = None
        if set_state:
            return self._reset_to_states(env_states, env_idx, seed, options)
        if "env_idx" not in options:
            if seed is not None:
                self._seeds.set(seed)
            seed = self._seeds.draw()
        elif self._seeds_partial_resets:
            # CPU sub-envs restart from drawn seeds too: reproducible from set_seed, whatever
            # each sub-env's process's global torch RNG holds (unseeded ManiSkill resets draw from it).
            seed = self._seeds.draw() if seed is None else seed
        with self._sim_mode():
            obs, info = self._env.reset(seed=seed, options=options)
        source = self._on_device(self._to_tensordict(obs, info))
        return new_tensordict(source, batch_size=self.batch_size, device=self.device)

    def _set_seed(self, seed: int | None) -> None:
        self._seeds.set(seed)

    # ------------------------------------------------------------------ entries, render, actions
    def _to_tensordict(self, obs: Any, info: Mapping[str, Any]) -> dict:
        leaf = self._obs_leaf
        if self._pixels_only:
            source = {}
        elif self._obs_is_dict:
            source = dict(obs) if leaf is None else _mapped(obs, leaf)
        else:
            source = {"observation": obs if leaf is None else leaf(obs)}
        leaf = self._info_leaf
        if leaf is None:
            for key, td_key in self._info_map:
                source[td_key] = info[key]
        else:
            for key, td_key in self._info_map:
                source[td_key] = leaf(info[key])
        if self._from_pixels:
            frame = self._render_batched()
            source["pixels"] = frame[0] if self._unbatched else frame
        return source

    def _on_device(self, source: dict) -> dict:
        """``source`` (a step's or reset's entries) on ``env.device``: as it is, or gathered up."""
        return source if self._gather is None else self._gather(source)

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        """The host values of ``tensor`` if it is an entry of this env's last step or reset that
        came up from the host in its one transfer (a CPU-sim env on an accelerator), else None.

        What :class:`~maniskill_torchrl.transforms.EpisodeMetrics` reads rewards and flags from
        instead of the device. Valid until the next step or reset.
        """
        gather = self._gather
        return None if gather is None else gather.host_value(tensor)

    def render(self) -> Any:
        """ManiSkill's ``render()`` (batched ``[B, H, W, 3]`` uint8 tensor for ``rgb_array``) on
        ``env.device``, a copy where ManiSkill renders into a buffer that its next render overwrites."""
        with self._sim_mode():
            frame = self._env.render()
        if self._copy_out and isinstance(frame, torch.Tensor):
            frame = frame.to(self.device, copy=True)
        return frame

    def _render_batched(self) -> torch.Tensor:
        """The ``"pixels"`` frame, batched: on ``env.device``, or as rendered where a gather moves it."""
        if self._gather is None:
            frame = torch.as_tensor(self.render(), device=self.device)
        else:
            with self._sim_mode():
                frame = torch.as_tensor(self._env.render())
        if frame.ndim == 3:
            frame = frame.unsqueeze(0)
        return frame

    def _sim_action(self, tensordict: TensorDictBase) -> Any:
        """The step's action as ManiSkill takes it (batched, on the sim's device), or an error that
        says what is missing or misshaped."""
        action = tensordict.get("action", None)
        if action is None:
            raise self._action_error(tensordict, "action", None)
        if self._action_names is None:
            if action.shape != self._action_shapes:
                raise self._action_error(tensordict, "action", action)
            if self._unbatched:  # ManiSkill's own batch of one
                action = action.unsqueeze(0)
            return action.to(self._sim_device) if self._moves else action
        action = {k: action.get(k, None) for k in self._action_names}
        for k, a in action.items():
            if a is None or a.shape != self._action_shapes[k]:
                raise self._action_error(tensordict, ("action", k), a)
        if self._unbatched:
            action = {k: a.unsqueeze(0) for k, a in action.items()}
        if self._moves:  # actions come on env.device; the sim takes them on its own
            action = {k: a.to(self._sim_device) for k, a in action.items()}
        return action

    def _action_error(self, tensordict: TensorDictBase, key: str | tuple[str, str], action: Any) -> Exception:
        expected = self._action_shapes[key[1]] if isinstance(key, tuple) else self._action_shapes
        keys = sorted(tensordict.keys(include_nested=True, leaves_only=True), key=str)
        return action_error(type(self).__name__, key, action, expected, keys, self.action_keys)

    # ------------------------------------------------------------------ saved states
    _state_row: TensorDictBase | None = None  # one env's state: the layout states are checked against

    def get_state(self) -> TensorDictBase:
        """Every env's ManiSkill sim state (``get_state_dict()``: the poses and velocities of its
        ``actors``, the root poses, velocities and joint positions / velocities of its
        ``articulations``; not the controllers' targets) as a TensorDict of this env's batch on
        ``env.device``, to reset to later with :meth:`reset_to_state` (or
        ``env.reset(td, set_state=True, env_states=state)``).

        Examples:
            >>> from maniskill_torchrl import ManiSkillEnv
            >>> env = ManiSkillEnv("PickCube-v1", obs_mode="state")
            >>> start = env.reset(seed=1)
            >>> state = env.get_state()
            >>> _ = env.rollout(3)
            >>> (env.reset_to_state(state)["observation"] == start["observation"]).all().item()
            True
        """
        with self._sim_mode():
            state = self.base_env.get_state_dict()
        num_envs = self.base_env.num_envs
        state = new_tensordict(_tensor_tree(state, self.device), batch_size=torch.Size([num_envs]), device=self.device)
        if self._state_row is None:
            self._state_row = state[0]
        return state[0] if self._unbatched else state

    def reset_to_state(
        self, env_states: TensorDictBase | Mapping, tensordict: TensorDictBase | None = None, **kwargs: Any
    ) -> TensorDictBase:
        """Resets to saved ManiSkill states: every env, or those of ``tensordict``'s ``"_reset"`` mask.

        ``env_states`` is :meth:`get_state`'s layout (a TensorDict or a nested dict of tensors):
        one row per env (this env's batch; the rows of the envs not being reset are not read), or
        one env's state without a batch dim (a trajectory file's ``data[i]["env_states"]``), which
        every env being reset then takes. Its keys, shapes and dtypes are checked before anything
        reaches the sim: a :class:`ValueError` names the entry that differs.

        The same as ``env.reset(tensordict, set_state=True, env_states=env_states)``; on a
        :class:`~torchrl.envs.TransformedEnv`, call that form on the transformed env so that its
        transforms reset too.
        """
        return self.reset(tensordict, set_state=True, env_states=env_states, **kwargs)

    def _reset_to_states(
        self, env_states: TensorDictBase | Mapping, env_idx: torch.Tensor | None, seed: int | None, options: dict
    ) -> TensorDictBase:
        """``_reset`` to saved states (``options`` may hold ``env_idx``, the envs being reset)."""
        options["reset_to_env_states"] = {"env_states": self._state_rows(env_states, env_idx)}
        # Nothing is drawn: the saved state, not a seed, makes this episode's start.
        with self._sim_mode():
            obs, info = self._env.reset(seed=seed, options=options)
        source = self._on_device(self._to_tensordict(obs, info))
        return new_tensordict(source, batch_size=self.batch_size, device=self.device)

    def _state_rows(self, env_states: TensorDictBase | Mapping, env_idx: torch.Tensor | None) -> dict:
        """ManiSkill's ``reset_to_env_states`` batch: the rows of the envs being reset, on the sim's device."""
        states = self._checked_states(env_states).to(self._sim_device)
        if env_idx is not None:
            states = states[env_idx]  # the envs being reset, in env order
        return states.to_dict()

    def _checked_states(self, env_states: TensorDictBase | Mapping) -> TensorDictBase:
        """``env_states`` as a ``[num_envs]`` TensorDict of the layout of :meth:`get_state`, or an
        error that says what differs."""
        if not isinstance(env_states, (TensorDictBase, Mapping)):
            raise TypeError(
                "env_states must be a TensorDict or a dict of tensors (env.get_state()), "
                f"got {type(env_states).__name__}."
            )
        if not isinstance(env_states, TensorDictBase):
            env_states = TensorDict(_tensor_tree(env_states), batch_size=[])
        if self._state_row is None:
            self.get_state()  # a read of the sim: learns the layout, changes nothing
        row = self._state_row
        want, got = set(row.keys(True, True)), set(env_states.keys(True, True))
        if want != got:
            missing, extra = sorted(want - got, key=str), sorted(got - want, key=str)
            raise ValueError(
                "env_states does not have this env's layout (env.get_state()): "
                + (f"missing {missing}" if missing else "")
                + ("; " if missing and extra else "")
                + (f"unknown {extra}" if extra else "")
                + ". Pass a state saved from this task (env.get_state(), or a trajectory file's env_states)."
            )
        num_envs = self.base_env.num_envs
        out, batches = {}, {}  # batch per entry: None for one env's state without a batch dim
        for key in sorted(want, key=str):
            ref, value = row.get(key), env_states.get(key)
            if value.shape == ref.shape:
                batches[key] = None
            elif value.ndim == ref.ndim + 1 and value.shape[1:] == ref.shape:
                batches[key] = value.shape[0]
            else:
                raise ValueError(
                    f"env_states{_path(key)} has shape {list(value.shape)}; this env's is {list(ref.shape)} per "
                    f"env: pass [{num_envs}, {', '.join(map(str, ref.shape))}] (one row per env) or "
                    f"{list(ref.shape)} (one env's state, for every env being reset)."
                )
            if value.dtype != ref.dtype and not (value.is_floating_point() and ref.is_floating_point()):
                raise ValueError(f"env_states{_path(key)} has dtype {value.dtype}; this env's is {ref.dtype}.")
            # A plain copy: a dataset's rows are memory-mapped tensors, which cannot be sent to CPU workers.
            out[key] = value.as_subclass(torch.Tensor).to(ref.dtype, copy=True)
        rows = set(batches.values())
        if len(rows) > 1:
            raise ValueError(f"env_states' entries have different batches: {batches}.")
        (rows,) = rows
        if rows is None:
            out = {k: v.expand(num_envs, *v.shape) for k, v in out.items()}
        elif rows != num_envs:
            raise ValueError(
                f"env_states has a batch of {rows} and this env has {num_envs} env(s): pass one row per env, "
                "or one env's state without a batch dim (every env being reset then takes it)."
            )
        states = TensorDict(batch_size=[num_envs])
        for key, value in out.items():
            states.set(key, value)
        return states

    # ------------------------------------------------------------------ the CPU workers' action repeat
    def request_worker_repeat(self, repeat: int) -> bool:
        """Has the next step apply its action up to ``repeat`` times inside the CPU sub-envs.

        :class:`~maniskill_torchrl.transforms.ActionRepeat`'s fast path. Only a
        :class:`~maniskill_torchrl.CPUVectorEnv` wrapped as is (with no repeat of its own) can:
        returns whether it will, False otherwise. The request holds for the next step only; any
        step asked for without one runs with the env's own repeat again, so a removed transform
        leaves plain steps.
        """
        if self._workers is None or self._plain_repeat != 1:
            return False
        self._next_repeat = repeat
        return True

    def _set_worker_repeat(self) -> None:
        """Before a step on the workers: the repeat asked for this step, else the env's own."""
        repeat = self._next_repeat
        if repeat:  # taken first, so that a failing step leaves no request behind
            self._next_repeat = 0
        else:  # no write: an nn.Module attribute write costs more than the rest of this block
            repeat = self._plain_repeat
        if self._workers.repeat != repeat:  # a round trip, only when the repeat changes
            self._workers.set_repeat(repeat)

    # ------------------------------------------------------------------ misc
    def close(self, *, raise_if_closed: bool = True) -> None:
        """Closes the ManiSkill env and lets it go: nothing of this closed env holds it any more
        (TorchRL keeps the constructor's ``env`` argument otherwise), so its scene and SAPIEN's
        render engine are freed with the last reference to it elsewhere."""
        env = self.__dict__.get("_env")
        if env is not None and not isinstance(env, ClosedEnv):
            # A stand-in that says the env is closed: a closed ManiSkill sim fails with AttributeErrors.
            self._env = ClosedEnv(f"{type(self).__name__}({self._env_name(env)})")
            self._workers = None
            env.close()
        super().close(raise_if_closed=raise_if_closed)
        kwargs = self.__dict__.get("_constructor_kwargs")
        if isinstance(kwargs, dict):
            kwargs.pop("env", None)

    @staticmethod
    def _env_name(env: Any) -> str:
        spec = getattr(env.unwrapped, "spec", None)
        return spec.id if spec is not None else type(env.unwrapped).__name__

    def __repr__(self) -> str:
        if isinstance(self._env, ClosedEnv):
            return f"{self._env.name} (closed)"
        name = self._env_name(self._env)
        return (
            f"{type(self).__name__}(env={name}, num_envs={self._env.unwrapped.num_envs}, "
            f"batch_size={list(self.batch_size)}, "
            f"device={self.device}, gpu_sim={self.gpu_sim_enabled})"
        )


class ManiSkillEnv(ManiSkillWrapper):
    """Makes a ManiSkill task with ``gym.make`` and wraps it as a TorchRL env.

    Args:
        env_id (str): a registered ManiSkill task, e.g. ``"PickCube-v1"``.

    Keyword Args:
        num_envs (int): parallel envs, the batch size. On the GPU sim, one
            simulator; on the CPU sim (``sim_backend="cpu"``, or ``"auto"``
            without CUDA), which holds one env per process, ``num_envs > 1``
            runs one process per env, sub-env 0 in this one and the others in
            workers (:class:`~maniskill_torchrl.CPUVectorEnv`, one shared-memory
            block for the batch), with the same keys, specs and dtypes.
        from_pixels (bool): add ``"pixels"`` (sets ``render_mode="rgb_array"``).
        inference_mode (bool, optional): run ManiSkill under :func:`torch.inference_mode`
            (see :class:`ManiSkillWrapper`). Default: on for a CPU-sim env in this process
            (``num_envs=1``, and each env of a ``ParallelEnv`` of singles: less CPU per step than
            grad mode, for the same values), off on the GPU sim; the sub-envs of ``num_envs > 1``
            on the CPU sim always use it. Pass False if your code calls ``env.base_env``'s methods itself
            outside inference mode.
        batch_size (list of int, optional): ``[num_envs]`` by default. ``[]`` with ``num_envs=1``
            makes one unbatched env, what :class:`~torchrl.envs.ParallelEnv` and
            :class:`~torchrl.envs.SerialEnv` stack: the same specs and entries as
            ``TransformedEnv(ManiSkillEnv(env_id), CPUUnbatch())``, without a transformed env's
            step on top of each ManiSkill step (see :class:`ManiSkillWrapper`).
        in_process (bool): CPU sim with ``num_envs > 1``: sub-env 0 steps in this process
            while the workers step the others (default). False: every sub-env in a worker
            process, this one only waits. Elsewhere every env is in this process and this is
            not read.
        pixels_only, info_keys, device, allow_done_after_reset: as in
            :class:`ManiSkillWrapper`.
        **maniskill_kwargs: passed to ``gym.make`` (``obs_mode``,
            ``control_mode``, ``sim_backend``, ``render_mode``,
            ``max_episode_steps``...). ``render_backend``: SAPIEN renders on one device
            per process while any env that renders lives (``"cpu"`` and ``"cuda"`` are two):
            an env asking for another device than the process's other envs raises a
            ``RuntimeError`` that names both devices and the fixes (one ``render_backend``
            per process; close and delete the other env; or make this one in another process).

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
        inference_mode: bool | None = None,
        batch_size: Sequence[int] | None = None,
        in_process: bool = True,
        **maniskill_kwargs: Any,
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
        checked_batch_size(batch_size, num_envs)  # before any process or sim is started
        check_frame_skip(maniskill_kwargs.pop("frame_skip", None))
        check_assets(env_id, maniskill_kwargs)
        if from_pixels:
            maniskill_kwargs.setdefault("render_mode", "rgb_array")
        self._env_id = env_id
        backend = str(maniskill_kwargs.get("sim_backend", "auto")).lower()
        # ManiSkill's "auto" is the CPU sim for one env; for more, the GPU sim when there is CUDA.
        on_cpu = backend in _CPU_BACKENDS or (backend == "auto" and (num_envs == 1 or not torch.cuda.is_available()))
        if num_envs > 1 and on_cpu:
            # The CPU sim holds one env per process: one process per env.
            maniskill_kwargs["sim_backend"] = "physx_cpu"
            env = CPUVectorEnv(env_id, num_envs, in_process=in_process, **maniskill_kwargs)
        else:
            if not on_cpu:
                if not torch.cuda.is_available():
                    raise ValueError(
                        f"sim_backend={maniskill_kwargs['sim_backend']!r} is ManiSkill's GPU sim, which needs "
                        "CUDA, and torch.cuda.is_available() is False: use sim_backend='cpu' (or 'auto')."
                    )
                enable_physx_gpu()
            with no_asset_prompt(env_id):
                # SAPIEN renders on one device per process: a second one is a RenderDeviceError.
                env = make_maniskill(env_id, num_envs=num_envs, **default_render_backend(maniskill_kwargs))
        if inference_mode is None:  # this class owns the ManiSkill env: inference mode on the CPU sim
            inference_mode = on_cpu
        super().__init__(
            env,
            device=device,
            from_pixels=from_pixels,
            pixels_only=pixels_only,
            info_keys=info_keys,
            allow_done_after_reset=allow_done_after_reset,
            inference_mode=inference_mode,
            batch_size=batch_size,
        )

    @property
    def env_id(self) -> str:
        return self._env_id


def _mapped(obs: Mapping[str, Any], leaf: Callable[[torch.Tensor], torch.Tensor]) -> dict:
    """A nested observation dict with ``leaf`` applied to every tensor (other values as they are)."""
    return {
        k: leaf(v) if isinstance(v, torch.Tensor) else _mapped(v, leaf) if isinstance(v, Mapping) else v
        for k, v in obs.items()
    }


def _leaf(device: torch.device, unbatched: bool, copy: bool) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """What a ManiSkill tensor goes through to become an entry (None: nothing): the env dim
    dropped for an unbatched env, one copy onto ``device`` where asked."""
    if not copy:
        return _unbatch if unbatched else None
    if unbatched:
        return lambda x: x[0].to(device, copy=True)
    return lambda x: x.to(device, copy=True)


def _unbatch(x: torch.Tensor) -> torch.Tensor:
    return x[0]


def _check_set_state(set_state: bool | None, env_states: Any) -> None:
    """``reset(set_state=True, env_states=...)`` takes both or neither."""
    if (env_states is not None) != bool(set_state):
        raise ValueError(
            "A reset to saved states takes both set_state=True and env_states (from env.get_state()): "
            "env.reset(td, set_state=True, env_states=states), or env.reset_to_state(states, td)."
        )


def _path(key: Any) -> str:
    """``("actors", "cube")`` -> ``["actors", "cube"]``, as a user indexes the TensorDict."""
    key = key if isinstance(key, tuple) else (key,)
    return "".join(f"[{k!r}]" for k in key)


def _tensor_tree(tree: Mapping, device: torch.device | None = None) -> dict:
    """A nested dict of tensors (ManiSkill's state dict) as plain dicts of normal tensors, copied
    (onto ``device`` if given)."""
    return {
        k: _tensor_tree(v, device) if isinstance(v, Mapping) else torch.as_tensor(v).to(device, copy=True)
        for k, v in tree.items()
    }
