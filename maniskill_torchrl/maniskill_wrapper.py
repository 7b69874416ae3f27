""":class:`ManiSkillWrapper`: a ManiSkill 3 env made with ``gym.make`` as a native TorchRL env.

ManiSkill returns batched torch tensors (``[num_envs, ...]``) on the simulation
device; :class:`ManiSkillWrapper` puts them into TensorDicts: no numpy round trips, no
host copies, one TensorDict built per step, and a device copy only of what ManiSkill
would overwrite later (the GPU sim's buffers). Its specs and
the entries of each step come from its mixin :class:`~maniskill_torchrl.maniskill_layout.ManiSkillLayout`
(``maniskill_layout.py``); :class:`~maniskill_torchrl.ManiSkillEnv` (``maniskill_env.py``)
builds the ManiSkill env too.
"""

from __future__ import annotations

import contextlib
import importlib.util
from collections.abc import Mapping, Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDictBase
from torchrl.data.utils import DEVICE_TYPING

from maniskill_torchrl._maniskill import canonical_device, reuses_buffers
from maniskill_torchrl._private import EnvWrapper, classproperty, new_tensordict
from maniskill_torchrl.errors import ClosedEnv, check_frame_skip, checked_base_env, checked_batch_size, checked_device
from maniskill_torchrl.maniskill_layout import ManiSkillLayout
from maniskill_torchrl.saved_states import SavedStates, check_set_state
from maniskill_torchrl.seeding import ResetSeeds
from maniskill_torchrl.worker_repeat import WorkerRepeat

if TYPE_CHECKING:
    from mani_skill.envs.sapien_env import BaseEnv

__all__ = ["ManiSkillWrapper"]

_has_maniskill = importlib.util.find_spec("mani_skill") is not None


class ManiSkillWrapper(ManiSkillLayout, SavedStates, WorkerRepeat, EnvWrapper):
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

    The wrapper never imports the CPU engine (``maniskill_torchrl.engines``): it reads the
    capabilities an engine declares (``returns_copies``, ``runs_inference_mode``,
    ``seeds_partial_resets``, ``reconfigures_partially``, ``repeats_actions``,
    ``render_frame_shape()``), which a ManiSkill ``BaseEnv`` does not have.

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
        self._init_worker_repeat(env, base)
        self._init_layout(
            device=device,
            from_pixels=from_pixels,
            pixels_only=pixels_only,
            info_keys=info_keys,
            unbatched=not batch_size,
        )
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
        check_set_state(set_state, env_states)
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

    # -------------------------------------------------------------- misc
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
