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

This module imports neither TorchRL nor the rest of the library beyond
``_maniskill``: the workers import it, and start faster without them.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode

from maniskill_torchrl._maniskill import maniskill_base_env, render_frame_shape, wrapper_attr

__all__ = ["CPUVectorEnv"]

_OBS, _INFO, _REWARD, _TERMINATED, _TRUNCATED = "obs", "info", "reward", "terminated", "truncated"


def _numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return torch.empty((), dtype=dtype).numpy().dtype


def _info_space(infos: Mapping[str, Any]) -> gym.spaces.Dict:
    """Spaces for the per-env tensor infos of a one-env ManiSkill info dict (``[1, ...]`` tensors).

    The same entries as :func:`maniskill_torchrl.specs.info_spec_from_infos` keeps:
    python values such as ``reconfigure`` are per-call metadata and are left out.
    """
    spaces: dict[str, gym.Space] = {}
    for key, value in infos.items():
        if isinstance(value, Mapping):
            sub = _info_space(value)
            if sub.spaces:
                spaces[key] = sub
        elif isinstance(value, torch.Tensor) and value.ndim >= 1 and value.shape[0] == 1:
            dtype = _numpy_dtype(value.dtype)
            if dtype == np.bool_:
                spaces[key] = gym.spaces.Box(0, 1, tuple(value.shape[1:]), dtype=np.bool_)
            else:
                spaces[key] = gym.spaces.Box(-np.inf, np.inf, tuple(value.shape[1:]), dtype=dtype)
    return gym.spaces.Dict(spaces)


def _select(infos: Mapping[str, Any], space: gym.spaces.Dict) -> dict:
    """The entries of ``infos`` that ``space`` declares, unbatched to numpy."""
    return {
        k: _select(infos[k], sub) if isinstance(sub, gym.spaces.Dict) else infos[k][0].numpy()
        for k, sub in space.spaces.items()
    }


def _unbatch(x: Any) -> Any:
    if isinstance(x, torch.Tensor):
        return x[0].numpy()
    return {k: _unbatch(v) for k, v in x.items()}


def _batch(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x).unsqueeze(0)
    if isinstance(x, torch.Tensor):
        return x.unsqueeze(0)
    return {k: _batch(v) for k, v in x.items()}


class _StepInObservation(gym.Wrapper):
    """Worker side: one ManiSkill CPU env whose whole step travels as one observation.

    The observation becomes ``{"obs", "info", "reward", "terminated", "truncated"}``,
    unbatched numpy with ManiSkill's dtypes, so gymnasium's shared-memory buffers carry
    all of it; ``step`` returns a dummy reward, dummy flags and an empty info dict (no
    per-step pickling of infos, no merging of info dicts in the parent). Actions arrive
    unbatched (numpy, or dicts of them) and reach ManiSkill as ``[1, ...]`` torch tensors,
    as a batched ManiSkill env expects them.
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        base = maniskill_base_env(env)
        if base is None or base.num_envs != 1 or base.gpu_sim_enabled:
            raise ValueError("CPUVectorEnv workers hold one ManiSkill env on the CPU sim (num_envs=1).")
        self._info_space = _info_space(base.get_info())
        single_obs = wrapper_attr(env, "single_observation_space")
        self.observation_space = gym.spaces.Dict(
            {
                _OBS: single_obs,
                _INFO: self._info_space,
                _REWARD: gym.spaces.Box(-np.inf, np.inf, (), dtype=np.float32),
                _TERMINATED: gym.spaces.Box(0, 1, (), dtype=np.bool_),
                _TRUNCATED: gym.spaces.Box(0, 1, (), dtype=np.bool_),
            }
        )
        self.action_space = wrapper_attr(env, "single_action_space")

    def render_frame_shape(self) -> tuple[int, ...]:
        return render_frame_shape(self.env.unwrapped)

    def _pack(self, obs: Any, info: Mapping, reward: Any, terminated: Any, truncated: Any) -> dict:
        return {
            _OBS: _unbatch(obs),
            _INFO: _select(info, self._info_space),
            _REWARD: reward,
            _TERMINATED: terminated,
            _TRUNCATED: truncated,
        }

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._pack(obs, info, np.float32(0), False, False), {}

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(_batch(action))
        packed = self._pack(obs, info, reward[0].numpy(), terminated[0].numpy(), truncated[0].numpy())
        return packed, 0.0, False, False, {}


class _MakeWorker:
    """Picklable env factory for the forkserver workers."""

    def __init__(self, env_id: str, kwargs: dict) -> None:
        self.env_id, self.kwargs = env_id, kwargs

    def __call__(self) -> gym.Env:
        import mani_skill.envs  # noqa: F401  (registers the tasks in the worker)

        if multiprocessing.parent_process() is not None:  # a worker; gymnasium also calls this in the parent
            _batch_scheduling()
        return _StepInObservation(gym.make(self.env_id, num_envs=1, **self.kwargs))


def _batch_scheduling() -> None:
    """Runs this worker (and the threads it starts) under Linux's ``SCHED_BATCH`` policy.

    Same fair share, but a woken worker does not preempt the running process: the parent
    sends every worker its action before one of them takes its core (the pipe wake-up
    otherwise hands the parent's core to the first worker for a time slice).
    """
    policy = getattr(os, "SCHED_BATCH", None)
    if policy is not None and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, policy, os.sched_param(0))
        except OSError:
            pass


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
    together: gymnasium's ``AsyncVectorEnv`` has no partial step.

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
                [_MakeWorker(env_id, maniskill_kwargs)] * self.num_envs,
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
        self.single_observation_space = space[_OBS]
        self.single_action_space = self._vec.single_action_space
        self._info_space = space[_INFO]
        self.render_mode = self._vec.render_mode
        self.spec = gym.spec(env_id)
        self._closed = False

    @property
    def unwrapped(self) -> CPUVectorEnv:
        return self

    # ---------------------------------------------------------------- data
    def _read(self) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        buf = self._vec.observations  # numpy views of the shared memory
        obs = _copy_tree(buf[_OBS])
        info = _view_tree(buf[_INFO])
        reward = torch.tensor(buf[_REWARD])
        terminated = torch.tensor(buf[_TERMINATED])
        truncated = torch.tensor(buf[_TRUNCATED])
        return obs, reward, terminated, truncated, info

    def step(
        self, action: torch.Tensor | Mapping[str, torch.Tensor]
    ) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        try:
            self._vec.step_async(_to_numpy(action))
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

    def get_info(self) -> dict:
        """Zeros shaped as the info entries (``[N, ...]``, ManiSkill's dtypes): the layout, no data."""
        return _zeros_tree(self._info_space, self.num_envs)

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
        return f"CPUVectorEnv({self.spec.id}, num_envs={self.num_envs})"


def _to_numpy(action: Any) -> Any:
    if isinstance(action, torch.Tensor):
        return action.detach().cpu().numpy()
    return {k: _to_numpy(v) for k, v in action.items()}


def _copy_tree(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return torch.tensor(x)
    return {k: _copy_tree(v) for k, v in x.items()}


def _view_tree(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x)
    return {k: _view_tree(v) for k, v in x.items()}


def _zeros_tree(space: gym.spaces.Dict, n: int) -> dict:
    return {
        k: _zeros_tree(sub, n)
        if isinstance(sub, gym.spaces.Dict)
        else torch.zeros((n, *sub.shape), dtype=torch.from_numpy(np.zeros((), sub.dtype)).dtype)
        for k, sub in space.spaces.items()
    }
