"""This library's :class:`ManiSkillEnv` and :class:`ManiSkillWrapper`: the TorchRL adapter
(:mod:`maniskill_torchrl.envs.maniskill`, the file bound for TorchRL's tree) plus what only this
library has.

- ``ManiSkillEnv(env_id, num_envs=N)`` on the CPU sim, which holds one env per process, runs the
  batched CPU engine (:class:`~maniskill_torchrl.CPUVectorEnv`: one process per sub-env, one
  shared-memory block for the batch), with the same batch ``[N]``, keys, specs and dtypes as the
  GPU sim. Partial resets there are seeded with the next draw of the env's seeds, as the adapter
  seeds them on the GPU sim (sub-env ``i`` takes the draw plus ``i``).
- ManiSkill called under :func:`torch.inference_mode` (by default on the CPU sim).
- A CPU-sim env on an accelerator (``device="cuda"``) moves each step's host outputs up in one
  non-blocking transfer (:class:`~maniskill_torchrl._internal.host_gather.HostGather`).
- The hooks of :class:`~maniskill_torchrl.envs.hooks.EnvHooks`: the workers' action repeat
  (:meth:`~ManiSkillWrapper.request_worker_repeat`), resets to saved states with their cached
  observations (:meth:`~ManiSkillWrapper.request_reset_states`) and the host values of what a CPU-sim env on
  an accelerator moved up (:meth:`~ManiSkillWrapper.host_value`).
- ``frame_skip`` refused for :class:`~maniskill_torchrl.transforms.ActionRepeat`, errors that
  name the fix for a missing action and a closed env, and clear errors where ManiSkill would
  prompt for a download (``(y|n)`` on stdin), SAPIEN refuse a second render device
  (:class:`~maniskill_torchrl.RenderDeviceError`) or the GPU sim lack its PhysX library offline.
"""

from __future__ import annotations

import inspect
from typing import Any

import torch
from tensordict import TensorDictBase

from maniskill_torchrl._internal.assets import check_assets, no_asset_prompt
from maniskill_torchrl._internal.host_gather import HostGather
from maniskill_torchrl._internal.mp import entropy_seed
from maniskill_torchrl._internal.rendering import default_render_backend, remember_render_device, render_device_errors
from maniskill_torchrl._internal.sim import enable_physx_gpu
from maniskill_torchrl._internal.sim_calls import ClosedEnv, InferenceModeEnv
from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv
from maniskill_torchrl.envs import maniskill

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]

# The adapter's own keyword arguments of ManiSkillEnv (the others go to gym.make).
_WRAPPER_KEYWORDS = tuple(
    name
    for name, param in inspect.signature(maniskill.ManiSkillEnv.__init__).parameters.items()
    if param.kind is inspect.Parameter.KEYWORD_ONLY and name != "num_envs"
)


class _MissingActionError(KeyError):
    """A KeyError whose message prints as written."""

    def __str__(self) -> str:
        return str(self.args[0])


class ManiSkillWrapper(maniskill.ManiSkillWrapper):
    """:class:`torchrl.envs.ManiSkillWrapper <maniskill_torchrl.envs.maniskill.ManiSkillWrapper>`
    that also wraps the batched CPU engine and implements
    :class:`~maniskill_torchrl.envs.hooks.EnvHooks`.

    Args:
        env: a ManiSkill env (``gym.make(...)``, possibly inside gym wrappers), or a
            :class:`~maniskill_torchrl.CPUVectorEnv`.

    Keyword Args:
        inference_mode (bool, optional): call ManiSkill's ``step``, ``reset`` and ``render`` under
            :func:`torch.inference_mode`: the same values for less CPU on the CPU sim; outputs are
            then copied out as normal tensors, and your own calls into ``env.unwrapped`` must be
            made in inference mode too. A ``CPUVectorEnv``'s sub-envs run it themselves and
            return fresh copies, whatever this says. Defaults to ``False``.
        device, batch_size, from_pixels, pixels_only, pixels_key, info_keys,
        allow_done_after_reset: see :class:`maniskill_torchrl.envs.maniskill.ManiSkillWrapper`.
            A CPU-sim env with ``device="cuda"`` moves each step's host outputs up in one
            non-blocking transfer and takes its actions there. ``frame_skip`` is refused: use
            :class:`~maniskill_torchrl.transforms.ActionRepeat`.

    On a ``CPUVectorEnv``, all sub-envs step together, so a ``"_step"`` mask is not honoured;
    :class:`~maniskill_torchrl.transforms.ActionRepeat` has the sub-envs repeat each action
    themselves (:meth:`request_worker_repeat`).

    Examples:
        >>> import gymnasium as gym
        >>> import mani_skill.envs
        >>> from maniskill_torchrl import ManiSkillWrapper
        >>> env = ManiSkillWrapper(gym.make("PickCube-v1", num_envs=1, obs_mode="state"))
        >>> _ = env.set_seed(0)
        >>> td = env.rollout(3)
        >>> td["next", "observation"].shape, td["next", "success"].shape
        (torch.Size([1, 3, 42]), torch.Size([1, 3]))
    """

    _workers: CPUVectorEnv | None = None
    _gather: HostGather | None = None
    _next_states: tuple | None = None  # request_reset_states' (states, obs), for the next reset

    _inference = False

    def __init__(self, env: Any = None, *, inference_mode: bool | None = None, **kwargs: Any) -> None:
        frame_skip = kwargs.get("frame_skip", 1)
        if frame_skip != 1:
            # The adapter's frame skip stops every env at the first done one; ManiSkill's
            # ActionRepeatWrapper repeats each env up to its own end.
            raise ValueError(
                f"frame_skip={frame_skip} is not supported: use TransformedEnv(env, ActionRepeat({frame_skip})) "
                "from maniskill_torchrl.transforms, ManiSkill's ActionRepeatWrapper semantics: rewards summed over "
                "the steps each env really took, its last observation kept."
            )
        if inference_mode is not None:  # None: False, or what ManiSkillEnv decided by the sim
            self._inference = inference_mode
        super().__init__(env, **kwargs)

    def _check_kwargs(self, kwargs: dict) -> None:
        engine = kwargs["env"]
        if not isinstance(engine, CPUVectorEnv):
            return super()._check_kwargs(kwargs)
        # Sub-envs made by the engine itself: no gym wrapper, one ManiSkill env each.
        if self._from_pixels and engine.render_mode != "rgb_array":
            raise ValueError(
                f"from_pixels=True needs sub-envs made with render_mode='rgb_array' (got {engine.render_mode!r})."
            )

    def _build_env(self, env: Any, **kwargs: Any) -> Any:
        engine = env if isinstance(env, CPUVectorEnv) else None
        if engine is not None:
            self._inference = False  # the sub-envs run it, and only copies leave them
        elif self._inference:
            env = InferenceModeEnv(env)
        env = super()._build_env(env, **kwargs)
        self._workers = engine
        self._gather = self._host_gather()
        if engine is not None:
            self._set_seed(None)
        # The workers' repeat: the one asked for the next step (0: none), else the engine's own.
        self._plain_repeat = engine.repeat if engine is not None else 1
        self._next_repeat = 0
        return env

    @property
    def info_entries(self) -> dict[str, str]:
        """``{ManiSkill info key: tensordict key}`` of the declared info entries (a key that
        collides with another entry is stored as ``"info_<key>"``)."""
        return dict(self._info_map)

    @property
    def inference_mode(self) -> bool:
        """Whether ManiSkill is called under :func:`torch.inference_mode`."""
        return bool(self._inference)

    # ------------------------------------------------------------------ outputs
    def _host_gather(self) -> HostGather | None:
        """The CPU sim feeding an accelerator: a step's host outputs go up in one transfer."""
        sim, device = self._sim_device, self.device
        return HostGather(device) if sim.type == "cpu" and device != sim else None

    def to(self, device: Any) -> ManiSkillWrapper:
        """This env with its outputs on ``device`` from now on, checked as ``device=`` is (a CPU-sim env's
        outputs then move to it in one transfer)."""
        super().to(device)
        self._gather = self._host_gather()
        return self

    def _to_device(self, source: dict) -> dict:
        gather = self._gather
        if gather is not None:  # copied into its buffer: nothing aliases the sim
            return gather(source)
        if self._inference:  # inference tensors are copied out into normal ones
            device = self.device
            return maniskill._mapped(source, lambda x: x.to(device, copy=True))
        return super()._to_device(source)

    @property
    def _copy_out(self) -> bool:
        """Whether every output is a copy, none ManiSkill's own tensor."""
        return self._inference or self._copies or self.device != self._sim_device

    def render(self, *args: Any, **kwargs: Any) -> Any:
        """Renders the env on ``env.device``: ManiSkill's frames (``[B, H, W, 3]`` uint8 for
        ``rgb_array``), copied where ManiSkill renders into a reused buffer, and normal tensors in
        inference mode."""
        frame = super().render(*args, **kwargs)
        # ManiSkill's own picture, where the adapter did not copy it: out as a normal tensor, on env.device.
        if (
            self._inference
            and isinstance(frame, torch.Tensor)
            and (frame.is_inference() or frame.device != self.device)
        ):
            frame = frame.to(self.device, copy=True)
        return frame

    def _set_seed(self, seed: int | None) -> None:
        # The sub-envs' processes fork from one: without a seed, ManiSkill's unseeded resets would
        # replay one episode in each. A seed from the OS's entropy gives each its own, as gym's
        # AsyncVectorEnv does.
        if seed is None and self._workers is not None:
            seed = entropy_seed()
        super()._set_seed(seed)

    @property
    def max_episode_steps(self) -> int | None:
        """The time limit of the wrapped env, as ManiSkill's ``RecordEpisode`` finds it
        (``find_max_episode_steps_value``: the ``gym.make`` argument, else the task's registered
        one); a :class:`~maniskill_torchrl.CPUVectorEnv`'s from the kwargs of its sub-envs."""
        from mani_skill.utils.gym_utils import find_max_episode_steps_value
        from mani_skill.utils.registration import REGISTERED_ENVS

        if self._workers is None:
            return find_max_episode_steps_value(self._env)
        kwargs = self._workers.maniskill_kwargs
        if kwargs.get("max_episode_steps") is not None:
            return int(kwargs["max_episode_steps"])
        registered = REGISTERED_ENVS.get(self._workers.spec.id)
        return None if registered is None else registered.max_episode_steps

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._workers is not None:
            self._set_worker_repeat()
        try:
            return super()._step(tensordict)
        except KeyError as err:
            keys = ["action"] if "action" not in tensordict.keys() else self.action_keys
            missing = next((k for k in keys if tensordict.get(k, None) is None), None)
            if missing is None:  # not the action's: as raised
                raise
            entries = sorted(tensordict.keys(True, True), key=str)
            raise _MissingActionError(
                f"{type(self).__name__}.step() found no action at {missing!r} in the tensordict, whose entries are "
                f"{entries}. Set the action entries {self.action_keys} (shapes from env.full_action_spec), e.g. "
                "td = env.rand_action(td), or run a policy that writes them."
            ) from err

    def _step_proc_data(self, next_tensordict_out: TensorDictBase) -> TensorDictBase:
        # The adapter's step writes the reward and the done entries with their spec shapes and dtypes: EnvBase's
        # reshaping and done completion have nothing to do (measured: RESULTS.md, "ManiSkillEnv").
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict_out)
        return next_tensordict_out

    # ------------------------------------------------------------------ EnvHooks
    def request_worker_repeat(self, repeat: int) -> bool:
        """Has the next step apply its action up to ``repeat`` times inside the CPU sub-envs.

        Only a :class:`~maniskill_torchrl.CPUVectorEnv` wrapped as is (with no repeat of its own)
        can: returns whether it will. The request holds for the next step only, so a removed
        transform leaves plain steps.
        """
        if self._workers is None or self._plain_repeat != 1:
            return False
        self._next_repeat = repeat
        return True

    def _set_worker_repeat(self) -> None:
        repeat = self._next_repeat
        if repeat:  # taken first: a failing step leaves no request behind
            self._next_repeat = 0
        else:
            repeat = self._plain_repeat
        if self._workers.repeat != repeat:  # a round trip, only when the repeat changes
            self._workers.set_repeat(repeat)

    def request_reset_states(self, states: TensorDictBase, obs: TensorDictBase | None = None) -> bool:
        """Makes the next reset a reset to ``states`` (rows of :meth:`get_state`, one per env
        being reset, in env order), with ``obs``'s observation entries as its observations where
        given: ManiSkill's ``reset_to_env_states`` options, which skip the task's episode
        initialization and, with ``obs``, the observation (camera renders included). The request
        holds for the next reset only; an explicit ``reset(set_state=True, scene_state=...)``
        takes precedence over it.

        ``obs`` is not taken (the sim computes the observations) where ManiSkill's write of them
        into its last observation could reach a tensor this env handed out (outputs not copied: a
        wrapper of a CPU-sim gym env without inference mode), or with ``from_pixels``."""
        self._next_states = (states, obs)
        return True

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        request, self._next_states = self._next_states, None  # taken first: a failing reset leaves none behind
        if request is None or kwargs.get("set_state"):
            return super()._reset(tensordict, **kwargs)
        kwargs.pop("set_state", None)
        return self._reset_to_rows(tensordict, *request, **kwargs)

    def _reset_to_rows(
        self, tensordict: TensorDictBase | None, states: TensorDictBase, obs: TensorDictBase | None, **kwargs: Any
    ) -> TensorDictBase:
        """ManiSkill's ``reset(options={"reset_to_env_states": ...})`` with one row of states (and
        observations) per env being reset, as ManiSkill's ``CachedResetWrapper`` passes them. The
        rows are this env's own ``get_state()`` rows, so the layout check of :meth:`reset_to_state`
        (a read of the sim's state and a copy of every leaf: 5x a plain reset on DrawTriangle-v1's
        hundreds of actors) is skipped. The reset is unseeded, as the wrapper's, and draws nothing from
        the env's seeds: the states make the episodes' starts, and a seeded ManiSkill reset would
        rebuild its RNGs (a third of a cached reset's time)."""
        options = dict(kwargs.pop("options", None) or {})
        cached = {"env_states": states.to(self._sim_device).to_dict()}
        obs = self._maniskill_obs(obs)
        if obs is not None:
            cached["obs"] = obs
        options["reset_to_env_states"] = cached
        return super()._reset(tensordict, options=options, **kwargs)

    def _maniskill_obs(self, obs: TensorDictBase | None) -> Any:
        """ManiSkill's observations (its dict, or the Box observation) from rows of reset tensordicts, or None
        where they cannot be given (see :meth:`request_reset_states`)."""
        if obs is None or self._from_pixels or self._pixels_only or not (self._workers is not None or self._copy_out):
            return None
        obs = obs.to(self._sim_device)
        if not self._obs_is_dict:
            return obs.get("observation")
        infos = {td_key for _, td_key in self._info_map}
        return obs.select(*(k for k in self.observation_spec.keys() if k not in infos)).to_dict()

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        """The host values of ``tensor`` if it is an entry of the last step or reset that came up
        from the host in its one transfer (a CPU-sim env on an accelerator), else None. Valid
        until the next step or reset."""
        gather = self._gather
        return None if gather is None else gather.host_value(tensor)

    def __reduce__(self) -> Any:
        # A live SAPIEN sim (and worker processes) cannot cross a pickle; what makes one can. A wrapper around the
        # user's own gym env has nothing to rebuild it from (ManiSkillEnv pickles as its constructor). The message
        # starts as Python's own ("cannot pickle '...' object"): TorchRL 0.14.1's multi-process collectors re-raise
        # a TypeError at a worker's start only when it says so, and swallow any other (the worker then dies unseen).
        raise TypeError(
            f"cannot pickle {type(self).__name__!r} object: it holds a live ManiSkill sim (the gym env it wraps), "
            "which nothing can rebuild in another process. Pickle what makes it "
            "instead: functools.partial(ManiSkillEnv, 'PickCube-v1', ...), torchrl.envs.EnvCreator(make_env), "
            "or functools.partial(maniskill_torchrl.pipeline.make_env, 'PickCube-v1', ...) for collectors, "
            "ParallelEnv and Ray."
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Closes the ManiSkill env and drops this env's references to it: its scene and SAPIEN's
        render engine are freed with the last one elsewhere. A closed env says so when used."""
        env = self.__dict__.get("_env")
        if env is not None and not isinstance(env, ClosedEnv):
            self._env = ClosedEnv(f"{type(self).__name__}({maniskill._env_id(env)})")
            env.close()
        self._workers = None
        super().close(raise_if_closed=raise_if_closed)
        kwargs = self.__dict__.get("_constructor_kwargs")
        if isinstance(kwargs, dict):
            kwargs.pop("env", None)

    def __repr__(self) -> str:
        if isinstance(self._env, ClosedEnv):
            return f"{self._env.name} (closed)"
        return super().__repr__()


class ManiSkillEnv(maniskill.ManiSkillEnv, ManiSkillWrapper):
    """Makes a ManiSkill task and wraps it: :class:`torchrl.envs.ManiSkillEnv
    <maniskill_torchrl.envs.maniskill.ManiSkillEnv>` with the batched CPU engine.

    Args:
        env_name (str): a registered ManiSkill task, e.g. ``"PickCube-v1"``.

    Keyword Args:
        num_envs (int): parallel envs, the batch size. On the GPU sim, one simulator; on the CPU
            sim (``sim_backend="cpu"``, or ``"auto"`` without CUDA), ``num_envs > 1`` runs one
            process per env, sub-env 0 in this one and the others in workers
            (:class:`~maniskill_torchrl.CPUVectorEnv`), with the same keys, specs and dtypes.
            Defaults to 1.
        in_process (bool, optional): CPU sim with ``num_envs > 1``: True, sub-env 0 steps in this
            process while the workers step the others; False, every sub-env in a worker.
            Defaults to None: decided by the machine
            (:func:`~maniskill_torchrl.engines.cpu_vector.in_process_default`: in this process
            unless it may use more cores than there are sub-envs).
        inference_mode (bool, optional): see :class:`ManiSkillWrapper`. Defaults to ``True`` on
            the CPU sim (this class owns the ManiSkill env, so nothing else calls into it) and
            ``False`` on the GPU sim.
        device, batch_size, from_pixels, pixels_only, pixels_key, info_keys, num_workers,
        allow_done_after_reset, **kwargs: as in
            :class:`maniskill_torchrl.envs.maniskill.ManiSkillEnv`. ``render_backend``: SAPIEN
            renders on one device per process while any env that renders lives: asking for
            another raises a :class:`~maniskill_torchrl.RenderDeviceError` naming both and the
            fixes.

    Pickling: the env pickles as its constructor (its task id and keyword arguments), so TorchRL's collectors,
    ``ParallelEnv`` and Ray can take a live env, e.g. the one a Hydra ``_partial_`` node holds. What unpickles is
    a new env built from those arguments, never stepped or seeded: the pickled env's episode, seed and steps are
    not carried over. A :class:`ManiSkillWrapper` around your own gym env cannot be rebuilt so, and refuses
    pickling (``TypeError: cannot pickle ...``).

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
        env_name: str,
        *,
        num_envs: int = 1,
        in_process: bool | None = None,
        inference_mode: bool | None = None,
        **kwargs: Any,
    ) -> None:
        # What pickling rebuilds the env from (__reduce__).
        constructor = {"num_envs": num_envs, "in_process": in_process, "inference_mode": inference_mode, **kwargs}
        self._init_args = (env_name, constructor)
        keys = {k: kwargs.pop(k) for k in _WRAPPER_KEYWORDS if k in kwargs}
        pixels, batch_size = keys.get("from_pixels", False), keys.get("batch_size")
        kwargs = maniskill._task_kwargs(env_name, num_envs, pixels, batch_size, kwargs)
        check_assets(env_name, kwargs)  # before any process or sim starts
        on_cpu = maniskill._cpu_sim(num_envs, kwargs.get("sim_backend", "auto"))
        # Inference mode by default on the CPU sim: this class owns the ManiSkill env, so nothing else calls into it.
        self._inference = on_cpu if inference_mode is None else inference_mode
        if num_envs > 1 and on_cpu:
            # The CPU sim holds one env per process: one process per env, in the batched CPU engine.
            self._env_id = env_name
            engine = CPUVectorEnv(env_name, num_envs, in_process=in_process, **{**kwargs, "sim_backend": "physx_cpu"})
            try:
                ManiSkillWrapper.__init__(self, engine, **keys)
            except Exception:
                engine.close()
                raise
            return
        if not on_cpu:
            enable_physx_gpu()
        kwargs = default_render_backend(kwargs)
        with no_asset_prompt(env_name), render_device_errors(env_name, kwargs.get("render_backend")):
            super().__init__(env_name, num_envs=num_envs, **keys, **kwargs)
        remember_render_device(self._env, env_name)

    def __reduce__(self) -> Any:
        # Pickles as its constructor (task id and keyword arguments): the sim itself cannot cross a pickle. What
        # unpickles is a new env, built afresh, never stepped or seeded: the pickled env's state (episode, seed,
        # steps taken, a closed env too) is not carried over. So a functools.partial or a Hydra `_partial_` node
        # holding a live ManiSkillEnv works with TorchRL's collectors, ParallelEnv and Ray.
        env_name, kwargs = self._init_args
        return _rebuild_env, (type(self), env_name, kwargs)


def _rebuild_env(cls: type, env_name: str, kwargs: dict) -> Any:
    """A new ``cls(env_name, **kwargs)``: what a pickled :class:`ManiSkillEnv` unpickles as."""
    return cls(env_name, **kwargs)
