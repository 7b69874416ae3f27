"""This library's :class:`ManiSkillEnv` and :class:`ManiSkillWrapper`: the TorchRL adapter
(:mod:`maniskill_torchrl.envs.maniskill`, the file bound for TorchRL's tree) plus what only this
library has.

- ``ManiSkillEnv(env_id, num_envs=N)`` on the CPU sim, which holds one env per process, runs the
  batched CPU engine (:class:`~maniskill_torchrl.CPUVectorEnv`: one process per sub-env, one
  shared-memory block for the batch), with the same batch ``[N]``, keys, specs and dtypes as the
  GPU sim. Partial resets there are seeded with the next draw of the env's seeds, so that runs
  stay reproducible from ``set_seed`` whatever each process's torch RNG holds.
- The hooks of :class:`~maniskill_torchrl.envs.hooks.EnvHooks`: the workers' action repeat
  (:meth:`~ManiSkillWrapper.request_worker_repeat`) and the host values of what a CPU-sim env on
  an accelerator moved up (:meth:`~ManiSkillWrapper.host_value`).
- Clear errors where ManiSkill would prompt for a download (``(y|n)`` on stdin) or SAPIEN refuse
  a second render device (:class:`~maniskill_torchrl.RenderDeviceError`), and no warning for the
  missing CUDA render device of a CPU-only machine.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

from maniskill_torchrl._internal.assets import check_assets, no_asset_prompt
from maniskill_torchrl._internal.mp import entropy_seed
from maniskill_torchrl._internal.rendering import default_render_backend, remember_render_device, render_device_errors
from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv
from maniskill_torchrl.envs import maniskill

__all__ = ["ManiSkillWrapper", "ManiSkillEnv"]


class ManiSkillWrapper(maniskill.ManiSkillWrapper):
    """:class:`torchrl.envs.ManiSkillWrapper <maniskill_torchrl.envs.maniskill.ManiSkillWrapper>`
    that also wraps the batched CPU engine and implements
    :class:`~maniskill_torchrl.envs.hooks.EnvHooks`.

    Args:
        env: a ManiSkill env (``gym.make(...)``, possibly inside gym wrappers), or a
            :class:`~maniskill_torchrl.CPUVectorEnv`.

    Keyword Args:
        see :class:`maniskill_torchrl.envs.maniskill.ManiSkillWrapper`. A ``CPUVectorEnv``'s
        sub-envs run inference mode themselves and return fresh copies, whatever
        ``inference_mode`` says.

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

    _frame_skip_fix = (
        "Use TransformedEnv(env, ActionRepeat(k)) from maniskill_torchrl.transforms, ManiSkill's "
        "ActionRepeatWrapper semantics: rewards summed over the steps each env really took, its last "
        "observation kept."
    )

    def _check_kwargs(self, kwargs: dict) -> None:
        env = kwargs.get("env")
        if isinstance(env, CPUVectorEnv):
            self._check_options(env)
        else:
            super()._check_kwargs(kwargs)

    def _build_env(self, env: Any, **kwargs: Any) -> Any:
        engine = env if isinstance(env, CPUVectorEnv) else None
        if engine is not None:
            self._inference = False  # the sub-envs run it, and only copies leave them
        env = super()._build_env(env, **kwargs)
        self._workers = engine
        if engine is not None:
            self._set_seed(None)
        # The workers' repeat: the one asked for the next step (0: none), else the engine's own.
        self._plain_repeat = engine.repeat if engine is not None else 1
        self._next_repeat = 0
        return env

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

    def _frame_shape(self, base: Any) -> tuple[int, ...]:
        # The engine asks one sub-env: rendering every sub-env before a reset fails in ManiSkill.
        if isinstance(base, CPUVectorEnv):
            return base.render_frame_shape()
        return super()._frame_shape(base)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._workers is not None:
            self._set_worker_repeat()
        return super()._step(tensordict)

    def _reset(
        self, tensordict: TensorDictBase | None = None, *, seed: int | None = None, **kwargs: Any
    ) -> TensorDictBase:
        if self._workers is not None and seed is None and not kwargs.get("set_state"):
            reset = tensordict.get("_reset", None) if tensordict is not None else None
            # A partial reset of CPU sub-envs starts from a drawn seed (sub-env i gets d + i).
            if reset is not None and bool(reset.any()) and not bool(reset.all()):
                seed = self._seeds.draw()
        return super()._reset(tensordict, seed=seed, **kwargs)

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

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        """The host values of ``tensor`` if it is an entry of the last step or reset that came up
        from the host in its one transfer (a CPU-sim env on an accelerator), else None. Valid
        until the next step or reset."""
        gather = self._gather
        return None if gather is None else gather.host_value(tensor)

    def __reduce__(self) -> Any:
        # A live SAPIEN sim (and worker processes) cannot cross a pickle; what makes one can.
        raise TypeError(
            f"{type(self).__name__} holds a live ManiSkill sim and cannot be pickled. Pickle what makes it "
            "instead: functools.partial(ManiSkillEnv, 'PickCube-v1', ...), torchrl.envs.EnvCreator(make_env), "
            "or functools.partial(maniskill_torchrl.pipeline.make_env, 'PickCube-v1', ...) for collectors, "
            "ParallelEnv and Ray."
        )

    def close(self, *, raise_if_closed: bool = True) -> None:
        self._workers = None
        super().close(raise_if_closed=raise_if_closed)


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
        device, batch_size, from_pixels, pixels_only, pixels_key, info_keys, inference_mode,
        num_workers, allow_done_after_reset, **kwargs: as in
            :class:`maniskill_torchrl.envs.maniskill.ManiSkillEnv`. ``render_backend``: SAPIEN
            renders on one device per process while any env that renders lives: asking for
            another raises a :class:`~maniskill_torchrl.RenderDeviceError` naming both and the
            fixes.

    Examples:
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> env = ManiSkillEnv("PickCube-v1", obs_mode="state_dict")
        >>> env.observation_spec["agent", "qpos"].shape
        torch.Size([1, 9])
        >>> td = env.rand_step(env.reset())
        >>> td["next", "reward"].shape
        torch.Size([1, 1])
    """

    def __init__(self, env_name: str, *, num_envs: int = 1, in_process: bool | None = None, **kwargs: Any) -> None:
        self._in_process = in_process
        super().__init__(env_name, num_envs=num_envs, **kwargs)

    def _check_kwargs(self, kwargs: dict) -> None:
        super()._check_kwargs(kwargs)
        env_name = kwargs["env_name"]
        # Before any process or sim starts.
        maniskill_kwargs = {k: v for k, v in kwargs.items() if k not in ("env_name", "num_envs")}
        check_assets(env_name, maniskill_kwargs)

    def _build_env(self, env_name: str, num_envs: int = 1, **kwargs: Any) -> Any:
        if num_envs > 1 and self._on_cpu_sim(num_envs, kwargs):
            # The CPU sim holds one env per process: one process per env.
            kwargs["sim_backend"] = "physx_cpu"
            engine = CPUVectorEnv(env_name, num_envs, in_process=self._in_process, **kwargs)
            return self._wrap_built(engine, on_cpu=True)
        kwargs = default_render_backend(kwargs)
        with no_asset_prompt(env_name), render_device_errors(env_name, kwargs.get("render_backend")):
            env = super()._build_env(env_name, num_envs, **kwargs)
        remember_render_device(env, env_name)
        return env
