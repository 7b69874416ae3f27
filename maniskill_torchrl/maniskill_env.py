""":class:`ManiSkillEnv`: makes a ManiSkill 3 task (``gym.make``, or a
:class:`~maniskill_torchrl.CPUVectorEnv`, one process per env, for several CPU-sim envs) and wraps
it as a TorchRL env. The factory picks the engine: the only env module that imports one."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torchrl.data.utils import DEVICE_TYPING

from maniskill_torchrl._maniskill import (
    check_assets,
    default_render_backend,
    enable_physx_gpu,
    make_maniskill,
    no_asset_prompt,
    registered_env_ids,
    similar_env_ids,
)
from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv
from maniskill_torchrl.errors import check_frame_skip, checked_batch_size
from maniskill_torchrl.maniskill_wrapper import ManiSkillWrapper

__all__ = ["ManiSkillEnv"]

_CPU_BACKENDS = ("cpu", "physx_cpu")


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
