"""N ManiSkill CPU-sim envs, one per worker process, behind ManiSkill's batched torch API.

ManiSkill's CPU sim holds one env per process. :class:`CPUVectorEnv` runs ``N``
of them in gymnasium's :class:`~gymnasium.vector.AsyncVectorEnv` (the engine
ManiSkill's own CPU baselines use) and answers like one GPU-sim env of
``num_envs=N``: ``step`` / ``reset`` take and return batched torch tensors
(``[N, ...]``), ``reset(options={"env_idx": ...})`` resets some envs only, and
``get_info()`` describes the info entries. :class:`~maniskill_torchrl.ManiSkillWrapper`
wraps it as it wraps a GPU-sim env, so CPU and GPU users write the same code.

Each worker writes its whole step (observation, reward, flags, tensor infos) into
gymnasium's shared-memory buffers with ManiSkill's own dtypes; only the actions and
an empty info dict cross the pipes. Nothing is rounded on the way: every sub-env
equals a lone ManiSkill env given the same seed and actions, bit for bit.

The worker side (the gym wrapper each worker runs, its factory, the buffers' layout) is in
``cpu_worker.py``. Neither module imports TorchRL or the rest of the library beyond
``_maniskill``: the workers import them, and start faster without them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode

from maniskill_torchrl.cpu_worker import (
    INFO,
    OBS,
    REWARD,
    TERMINATED,
    TRUNCATED,
    MakeWorker,
    copy_tree,
    to_numpy,
    view_tree,
    zeros_tree,
)

__all__ = ["CPUVectorEnv"]


class CPUVectorEnv:
    """``num_envs`` ManiSkill CPU-sim envs in worker processes, with a GPU-sim env's batched API.

    Args:
        env_id (str): a registered ManiSkill task, e.g. ``"PickCube-v1"``.
        num_envs (int): worker processes, one env each.

    Keyword Args:
        context (str): the multiprocessing start method of the workers. ``"forkserver"``
            (default) or ``"spawn"``; ``"fork"`` hangs once SAPIEN is loaded in this process.
        **maniskill_kwargs: passed to every worker's ``gym.make`` (``obs_mode``,
            ``control_mode``, ``max_episode_steps``, ``render_mode``...).

    The API is the one of ``gym.make(env_id, num_envs=N)`` on the GPU sim, without
    auto-reset: ``step(action)`` with ``[N, ...]`` actions gives ``[N, ...]`` torch
    observations, reward ``[N]`` (float32), terminated / truncated ``[N]`` (bool) and an
    info dict of ``[N, ...]`` tensors. Info tensors are views of the shared buffers that
    the next call overwrites (as ManiSkill's ``elapsed_steps`` is updated in place):
    clone what you keep. Seeding follows gymnasium's vector envs: ``reset(seed=s)``
    resets sub-env ``i`` with ``seed=s + i``, and so does
    ``reset(seed=s, options={"env_idx": idx})`` for the sub-envs in ``idx`` only (the
    others keep running). Without a seed, a sub-env's reset is ManiSkill's unseeded
    reset, which draws from its worker's global torch RNG. All sub-envs are stepped
    together: gymnasium's ``AsyncVectorEnv`` has no partial step. After
    :meth:`set_repeat` ``(k)`` each ``step`` repeats its action up to ``k`` times inside
    every worker, which stops at its own episode's end (ManiSkill's ``ActionRepeatWrapper``
    per sub-env): one round trip per ``step``, no physics after an end.

    A failure in a worker is raised here, by the call that met it: gymnasium re-raises
    the worker's Python exception; a worker that died makes the call raise a
    ``RuntimeError`` naming it, after the other workers are stopped.
    """

    gpu_sim_enabled = False

    def __init__(self, env_id: str, num_envs: int, *, context: str = "forkserver", **maniskill_kwargs: Any) -> None:
        if context == "fork":
            raise ValueError(
                "CPUVectorEnv(context='fork') hangs once SAPIEN is loaded in this process; "
                "use context='forkserver' (default) or 'spawn'."
            )
        if maniskill_kwargs.pop("num_envs", 1) != 1:
            raise ValueError("num_envs is the second argument of CPUVectorEnv; do not pass it in maniskill_kwargs.")
        maniskill_kwargs.setdefault("sim_backend", "physx_cpu")
        self.num_envs = int(num_envs)
        self.device = torch.device("cpu")
        try:
            self._vec = AsyncVectorEnv(
                [MakeWorker(env_id, maniskill_kwargs)] * self.num_envs,
                shared_memory=True,
                copy=False,  # we copy once, into torch
                context=context,
                autoreset_mode=AutoresetMode.DISABLED,
            )
        except (EOFError, ConnectionError) as err:  # a worker died before gymnasium's own error handling
            raise RuntimeError(
                f"CPUVectorEnv({env_id!r}, {num_envs}): a worker process died while starting (its traceback is "
                f"printed above). Workers start with context={context!r}, which imports the main script again: "
                "in a script, build envs only under `if __name__ == '__main__':`."
            ) from err
        space = self._vec.single_observation_space
        self.single_observation_space = space[OBS]
        self.single_action_space = self._vec.single_action_space
        self._info_space = space[INFO]
        self.render_mode = self._vec.render_mode
        self.spec = gym.spec(env_id)
        self._closed = False
        self._repeat = 1

    @property
    def unwrapped(self) -> CPUVectorEnv:
        return self

    # ---------------------------------------------------------------- data
    def _read(self) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        buf = self._vec.observations  # numpy views of the shared memory
        obs = copy_tree(buf[OBS])
        info = view_tree(buf[INFO])
        reward = copy_tree(buf[REWARD])
        terminated = copy_tree(buf[TERMINATED])
        truncated = copy_tree(buf[TRUNCATED])
        return obs, reward, terminated, truncated, info

    def step(
        self, action: torch.Tensor | Mapping[str, torch.Tensor]
    ) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        try:
            self._vec.step_async(to_numpy(action))
            self._vec.step_wait()
        except (EOFError, OSError) as err:
            raise self._worker_died("step") from err
        return self._read()

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None) -> tuple[Any, dict]:
        options = dict(options) if options else {}
        env_idx = options.pop("env_idx", None)
        if env_idx is not None:
            mask = np.zeros(self.num_envs, dtype=np.bool_)
            mask[torch.as_tensor(env_idx, device="cpu").numpy()] = True
            if not mask.all():
                options["reset_mask"] = mask
                if isinstance(seed, int):  # gymnasium's convention, on the sub-envs being reset
                    seed = [seed + i if m else None for i, m in enumerate(mask)]
        try:
            self._vec.reset(seed=seed, options=options or None)
        except (EOFError, OSError) as err:
            raise self._worker_died("reset") from err
        obs, _, _, _, info = self._read()
        return obs, info

    @property
    def repeat(self) -> int:
        """How many times each ``step`` applies its action in the workers (1: plain steps)."""
        return self._repeat

    def set_repeat(self, repeat: int) -> None:
        """From the next ``step`` on, every worker applies the action up to ``repeat`` times.

        Each worker steps its env through the gym shim's
        :class:`~maniskill_torchrl.wrappers.ActionRepeatWrapper` (bit for bit ManiSkill's):
        reward summed, flags OR'ed, observation and infos of the sub-env's last real step, no
        step after its episode's end. ``repeat=1`` restores plain steps. One round trip,
        only when the value changes. :class:`~maniskill_torchrl.ManiSkillWrapper` sets it
        for the steps that :class:`~maniskill_torchrl.transforms.ActionRepeat` hands to the
        workers, and restores the repeat this env had when it was wrapped for the others.

        Raises:
            TypeError: ``repeat`` is not an int.
            ValueError: ``repeat < 1``.
        """
        from maniskill_torchrl.masked_merge import check_repeat  # tensordict: kept out of module import

        repeat = check_repeat(repeat)
        if repeat == self._repeat:
            return
        try:
            self._vec.call("set_repeat", repeat)
        except (EOFError, OSError) as err:
            raise self._worker_died("set_repeat") from err
        self._repeat = repeat

    def get_info(self) -> dict:
        """Zeros shaped as the info entries (``[N, ...]``, ManiSkill's dtypes): the layout, no data."""
        return zeros_tree(self._info_space, self.num_envs)

    def render_frame_shape(self) -> tuple[int, ...]:
        """``(H, W, 3)`` of one sub-env's ``render()`` frame, asked of worker 0."""
        return self._vec.call("render_frame_shape")[0]

    def render(self) -> torch.Tensor:
        """Every worker's ``render()``, concatenated: ``[N, H, W, 3]`` uint8 for ``rgb_array``."""
        return torch.cat([torch.as_tensor(f) for f in self._vec.call("render")])

    def _worker_died(self, call: str) -> RuntimeError:
        """Tears the workers down (a dead one would leave the others waiting) and says which died."""
        vec = self._vec
        dead = [i for i, p in enumerate(vec.processes) if not p.is_alive()]
        self._closed = vec.closed = True
        for process in vec.processes:
            if process.is_alive():
                process.terminate()
        for pipe in vec.parent_pipes:
            pipe.close()
        for process in vec.processes:
            process.join(5)
        return RuntimeError(
            f"CPUVectorEnv worker(s) {dead} of {self.spec.id} died during {call}(); the env is closed. "
            "Look for the worker's own error above (a crash in the simulator, or out of memory) and "
            "make a new env."
        )

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._vec.close()

    def __repr__(self) -> str:
        repeat = f", repeat={self._repeat}" if self._repeat != 1 else ""
        return f"CPUVectorEnv({self.spec.id}, num_envs={self.num_envs}{repeat})"
