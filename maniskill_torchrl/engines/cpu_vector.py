"""N ManiSkill CPU-sim envs, one per process, behind ManiSkill's batched torch API.

ManiSkill's CPU sim holds one env per process. :class:`CPUVectorEnv` runs ``N``
of them, sub-env 0 in this process and the others in gymnasium's
:class:`~gymnasium.vector.AsyncVectorEnv` (the engine ManiSkill's own CPU baselines
use), and answers like one GPU-sim env of ``num_envs=N``: ``step`` / ``reset`` take
and return batched torch tensors (``[N, ...]``), ``reset(options={"env_idx": ...})``
resets some envs only, and ``get_info()`` describes the info entries.
:class:`~maniskill_torchrl.ManiSkillWrapper` wraps it as it wraps a GPU-sim env, so CPU
and GPU users write the same code.

This process steps sub-env 0 while the workers step the others, instead of sleeping
until they are done: one process fewer to wake and to send actions to per step.
Each worker writes its whole step (observation, reward, flags, tensor infos) into
gymnasium's shared-memory buffers with ManiSkill's own dtypes; only the actions and
an empty info dict cross the pipes. Nothing is rounded on the way: every sub-env
equals a lone ManiSkill env given the same seed and actions, bit for bit.

The worker side (the gym wrapper each worker runs, its factory, the buffers' layout) is in
``_worker.py``. Neither module imports TorchRL or the rest of the library beyond
``_maniskill``: the workers import them, and start faster without them.

The env core (:class:`~maniskill_torchrl.ManiSkillWrapper`) never imports this module: it reads
the capabilities this engine declares (:attr:`CPUVectorEnv.returns_copies`,
:attr:`~CPUVectorEnv.runs_inference_mode`, :attr:`~CPUVectorEnv.seeds_partial_resets`,
:attr:`~CPUVectorEnv.reconfigures_partially`, :attr:`~CPUVectorEnv.repeats_actions`,
:meth:`~CPUVectorEnv.render_frame_shape`), and ``ManiSkillEnv`` picks it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AsyncVectorEnv, AutoresetMode
from gymnasium.vector.utils import create_empty_array

from maniskill_torchrl._maniskill import check_assets
from maniskill_torchrl.engines._failures import describe_failure, stop_workers
from maniskill_torchrl.engines._trace import COLLECT_END, HERE_END, SEND, StepTrace, summarize
from maniskill_torchrl.engines._worker import (
    INFO,
    OBS,
    REWARD,
    SUB_ENV_STATES,
    TERMINATED,
    TRUNCATED,
    MakeWorker,
    join_rows,
    join_states,
    split_first,
    to_numpy,
    write_row,
    zeros_tree,
)

__all__ = ["CPUVectorEnv"]


class CPUVectorEnv:
    """``num_envs`` ManiSkill CPU-sim envs, one per process, with a GPU-sim env's batched API.

    Args:
        env_id (str): a registered ManiSkill task, e.g. ``"PickCube-v1"``.
        num_envs (int): sub-envs, one per process.

    Keyword Args:
        in_process (bool): sub-env 0 runs in this process, stepped while the workers step
            the others (default: ``num_envs - 1`` worker processes). False: ``num_envs``
            workers, and this process only waits for them.
        context (str): the multiprocessing start method of the workers. ``"forkserver"``
            (default) or ``"spawn"``; ``"fork"`` hangs once SAPIEN is loaded in this process.
        trace_steps (int): keep timestamps of the last ``trace_steps`` steps in shared memory
            (the parent's send and collect, each sub-env's wake and sim end), read with
            :meth:`trace` (default 0: none).
        **maniskill_kwargs: passed to every sub-env's ``gym.make`` (``obs_mode``,
            ``control_mode``, ``max_episode_steps``, ``render_mode``...).

    The API is the one of ``gym.make(env_id, num_envs=N)`` on the GPU sim, without
    auto-reset: ``step(action)`` with ``[N, ...]`` actions gives ``[N, ...]`` torch
    observations, reward ``[N]`` (float32), terminated / truncated ``[N]`` (bool) and an
    info dict of ``[N, ...]`` tensors, all fresh copies. Seeding follows gymnasium's vector
    envs: ``reset(seed=s)`` resets sub-env ``i`` with ``seed=s + i``, and so does
    ``reset(seed=s, options={"env_idx": idx})`` for the sub-envs in ``idx`` only (the
    others keep running). Without a seed, a sub-env's reset is ManiSkill's unseeded
    reset, which draws from its process's global torch RNG (this process's, for sub-env 0).
    All sub-envs are stepped together: gymnasium's ``AsyncVectorEnv`` has no partial step.
    After :meth:`set_repeat` ``(k)`` each ``step`` repeats its action up to ``k`` times in
    every sub-env, which stops at its own episode's end (ManiSkill's ``ActionRepeatWrapper``
    per sub-env): one round trip per ``step``, no physics after an end.

    Every call into ManiSkill runs under :func:`torch.inference_mode`, sub-env 0's too; only
    numpy copies leave the sub-envs. A failure is raised here, by the call that met it: sub-env
    0's exception as is, gymnasium re-raises a worker's Python exception, and a worker that
    died makes the call raise a ``RuntimeError`` naming its sub-env, after the other workers
    are stopped.
    """

    gpu_sim_enabled = False

    # The capabilities the env core reads (``getattr(base, name, False)``), instead of importing
    # this class; a ManiSkill ``BaseEnv`` has none of them.
    #: Every output is a fresh, normal tensor (numpy copies from the sub-envs), which nothing
    #: later writes into and nothing made under inference mode.
    returns_copies = True
    #: Every call into ManiSkill runs under :func:`torch.inference_mode` inside the engine, so
    #: the caller need not enter it.
    runs_inference_mode = True
    #: ``reset(seed=s, options={"env_idx": idx})`` seeds the sub-envs in ``idx`` (``s + i``).
    seeds_partial_resets = True
    #: Each sub-env is its own ManiSkill env, so a partial reset may reconfigure the sub-envs it
    #: resets (``reconfiguration_freq``), which one batched ManiSkill env cannot.
    reconfigures_partially = True
    #: The sub-envs repeat each action themselves (:attr:`repeat` and :meth:`set_repeat`).
    repeats_actions = True

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        *,
        in_process: bool = True,
        context: str = "forkserver",
        trace_steps: int = 0,
        **maniskill_kwargs: Any,
    ) -> None:
        if context == "fork":
            raise ValueError(
                "CPUVectorEnv(context='fork') hangs once SAPIEN is loaded in this process; "
                "use context='forkserver' (default) or 'spawn'."
            )
        if maniskill_kwargs.pop("num_envs", 1) != 1:
            raise ValueError("num_envs is the second argument of CPUVectorEnv; do not pass it in maniskill_kwargs.")
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"CPUVectorEnv: num_envs must be a positive int, got {num_envs!r}.")
        maniskill_kwargs.setdefault("sim_backend", "physx_cpu")
        check_assets(env_id, maniskill_kwargs)  # before any worker starts
        #: the ``gym.make`` arguments of every sub-env (what a trajectory file records)
        self.maniskill_kwargs = dict(maniskill_kwargs)
        self.num_envs = int(num_envs)
        self.device = torch.device("cpu")
        self._first = 1 if in_process else 0  # the sub-env index of the first worker
        self._vec: AsyncVectorEnv | None = None
        self._local = None
        self._closed = False
        self._closed_why = ""
        self._trace = StepTrace(num_envs, trace_steps) if trace_steps else None
        spec = None if self._trace is None else self._trace.spec
        makers = [MakeWorker(env_id, maniskill_kwargs, index=i, trace=spec) for i in range(num_envs)]
        try:
            if num_envs > self._first:
                self._vec = AsyncVectorEnv(
                    makers[self._first :],
                    shared_memory=True,
                    copy=False,  # we copy once, into torch
                    context=context,
                    autoreset_mode=AutoresetMode.DISABLED,
                )
            if in_process:
                self._local = makers[0].make()
                if spec is not None:  # sub-env 0 stamps its columns as a worker does, with its own count
                    self._local.trace = StepTrace(*spec)
        except (EOFError, ConnectionError) as err:  # a worker died before gymnasium's own error handling
            self.close()
            raise RuntimeError(
                f"CPUVectorEnv({env_id!r}, {num_envs}): a worker process died while starting (its traceback is "
                f"printed above). Workers start with context={context!r}, which imports the main script again: "
                "in a script, build envs only under `if __name__ == '__main__':`."
            ) from err
        except BaseException:
            self.close()
            raise
        if self._local is not None:
            space, self.single_action_space = self._local.observation_space, self._local.action_space
            self.render_mode = self._local.render_mode
            self._row = create_empty_array(space, n=1)  # sub-env 0's last step, as a worker's in shared memory
        else:
            space, self.single_action_space = self._vec.single_observation_space, self._vec.single_action_space
            self.render_mode = self._vec.render_mode
            self._row = None
        self.single_observation_space = space[OBS]
        self._info_space = space[INFO]
        self.spec = gym.spec(env_id)
        self._repeat = 1

    @property
    def unwrapped(self) -> CPUVectorEnv:
        return self

    # ---------------------------------------------------------------- data
    def _read(self) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        step = join_rows(self._row, None if self._vec is None else self._vec.observations)
        return step[OBS], step[REWARD], step[TERMINATED], step[TRUNCATED], step[INFO]

    def _together(self, call: str, send: Any, here: Any, collect: Any) -> tuple[Any, Any]:
        """``send(vec)`` to the workers, ``here()`` on sub-env 0 while they work, then
        ``collect(vec)``; returns (``here``'s result, ``collect``'s). ``send=None``: no worker
        takes part; ``here=None``: sub-env 0 does not. The workers' results are collected even
        when sub-env 0 raises, so that no call is left pending; a dead worker is reported."""
        if self._closed:
            raise RuntimeError(
                f"{self!r} is closed" + (f" ({self._closed_why})" if self._closed_why else "") + f": it cannot "
                f"{call}() any more. Make a new env."
            )
        vec = self._vec if send is not None else None
        if vec is not None:
            try:
                send(vec)
            except (EOFError, OSError) as err:
                raise self._worker_died(call, err) from err
        mine = theirs = None
        try:
            if here is not None and self._local is not None:
                mine = here()
        finally:
            if vec is not None:
                try:
                    theirs = collect(vec)
                except (EOFError, OSError) as err:
                    raise self._worker_died(call, err) from err
                except Exception as err:
                    # gymnasium re-raises a worker's exception after shutting that worker down:
                    # the env cannot go on with a sub-env missing.
                    if any(pipe is None for pipe in vec.parent_pipes):
                        raise self._worker_died(call, err) from err
                    raise
        return mine, theirs

    def step(
        self, action: torch.Tensor | Mapping[str, torch.Tensor]
    ) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        action = to_numpy(action)
        first = None
        if self._local is not None:
            first, action = split_first(action)
        trace = self._trace
        if trace is None:
            mine, _ = self._together(
                "step",
                lambda vec: vec.step_async(action),
                lambda: self._local.step(first)[0],  # while the workers step theirs
                lambda vec: vec.step_wait(),
            )
        else:
            trace.stamp(SEND)
            mine, _ = self._together(
                "step",
                lambda vec: vec.step_async(action),
                lambda: (self._local.step(first)[0], trace.stamp(HERE_END))[0],
                lambda vec: vec.step_wait(),
            )
            trace.stamp(COLLECT_END)
            trace.count += 1
        if mine is not None:
            write_row(self._row, mine)
        return self._read()

    def trace(self) -> dict:
        """The traced steps (``CPUVectorEnv(..., trace_steps=T)``: the last ``T``) and their summary:
        ``{"rows": [steps, 3 + 2 * num_envs] timestamps, "summary": ...}`` (``engines/_trace.py``
        says what each column and figure is)."""
        if self._trace is None:
            raise RuntimeError("This CPUVectorEnv keeps no trace: make it with trace_steps=T (the last T steps).")
        rows = self._trace_rows if self._closed else self._trace.rows()
        return {"rows": rows, "summary": summarize(rows)}

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None) -> tuple[Any, dict]:
        options = dict(options) if options else {}
        env_idx = options.pop("env_idx", None)
        mask = np.ones(self.num_envs, dtype=np.bool_)
        if env_idx is not None:
            mask[:] = False
            mask[torch.as_tensor(env_idx, device="cpu").numpy()] = True
        seeds = self._seeds(seed, mask)
        states = options.pop("reset_to_env_states", None)
        if states is not None:
            # ManiSkill's convention: one row of env_states per env being reset, in env order.
            # Every sub-env being reset gets the rows and picks its own (one message to all).
            options[SUB_ENV_STATES] = (np.flatnonzero(mask).tolist(), states["env_states"])
        workers = mask[self._first :]
        worker_options = dict(options)
        if not workers.all():
            worker_options["reset_mask"] = workers
        mine, _ = self._together(
            "reset",
            (lambda vec: vec.reset_async(seed=seeds[self._first :], options=worker_options or None))
            if workers.any()
            else None,
            (lambda: self._local.reset(seed=seeds[0], options=options or None)[0]) if mask[0] else None,
            lambda vec: vec.reset_wait(),
        )
        if mine is not None:
            write_row(self._row, mine)
        obs, _, _, _, info = self._read()
        return obs, info

    def get_state_dict(self) -> dict:
        """Every sub-env's ManiSkill ``get_state_dict()``, joined along the batch: ``[N, ...]``
        tensors, what the GPU sim's ``get_state_dict()`` gives for N envs."""
        return join_states(self.call("get_state_dict"))

    def _seeds(self, seed: int | list[int] | None, mask: np.ndarray) -> list[int | None]:
        """Each sub-env's reset seed: gymnasium's convention (``seed + i``) on the sub-envs in ``mask``."""
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (int, np.integer)):
            return [int(seed) + i if m else None for i, m in enumerate(mask)]
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(f"reset(seed=...) got {len(seeds)} seeds for {self.num_envs} sub-envs.")
        return seeds

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Each sub-env's method ``name`` called with these arguments (its value, for an attribute),
        in sub-env order, as gymnasium's ``AsyncVectorEnv.call``."""

        def here() -> Any:
            attr = self._local.get_wrapper_attr(name)
            return attr(*args, **kwargs) if callable(attr) else attr

        mine, theirs = self._together(
            name, lambda vec: vec.call_async(name, *args, **kwargs), here, lambda vec: vec.call_wait()
        )
        return ((mine,) if self._local is not None else ()) + (tuple(theirs) if theirs is not None else ())

    @property
    def repeat(self) -> int:
        """How many times each ``step`` applies its action in the sub-envs (1: plain steps)."""
        return self._repeat

    def set_repeat(self, repeat: int) -> None:
        """From the next ``step`` on, every sub-env applies the action up to ``repeat`` times.

        Each sub-env steps through the gym shim's
        :class:`~maniskill_torchrl.wrappers.ActionRepeatWrapper` (bit for bit ManiSkill's):
        reward summed, flags OR'ed, observation and infos of the sub-env's last real step, no
        step after its episode's end. ``repeat=1`` restores plain steps. One round trip,
        only when the value changes. :class:`~maniskill_torchrl.ManiSkillWrapper` sets it
        for the steps that :class:`~maniskill_torchrl.transforms.ActionRepeat` hands to the
        sub-envs, and restores the repeat this env had when it was wrapped for the others.

        Raises:
            TypeError: ``repeat`` is not an int.
            ValueError: ``repeat < 1``.
        """
        from maniskill_torchrl.masked_merge import check_repeat  # tensordict: kept out of module import

        repeat = check_repeat(repeat)
        if repeat == self._repeat:
            return
        self.call("set_repeat", repeat)
        self._repeat = repeat

    def get_info(self) -> dict:
        """Zeros shaped as the info entries (``[N, ...]``, ManiSkill's dtypes): the layout, no data."""
        return zeros_tree(self._info_space, self.num_envs)

    def render_frame_shape(self) -> tuple[int, ...]:
        """``(H, W, 3)`` of one sub-env's ``render()`` frame."""
        return self.call("render_frame_shape")[0]

    def render(self) -> torch.Tensor:
        """Every sub-env's ``render()``, concatenated: ``[N, H, W, 3]`` uint8 for ``rgb_array``."""
        return torch.cat([torch.as_tensor(f) for f in self.call("render")])

    def _worker_died(self, call: str, err: BaseException) -> RuntimeError:
        """Stops the sub-envs (the others would wait for the one that failed) and says what happened."""
        what, where = describe_failure(self._vec, self._first, err)
        self._closed = True
        self._closed_why = f"{what} during {call}()"
        stop_workers(self._vec)
        if self._local is not None:
            self._local.close()
        return RuntimeError(
            f"CPUVectorEnv({self.spec.id}): {what} during {call}(); the env is closed ({where}). "
            "Close it and make a new env."
        )

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if self._vec is not None:
                self._vec.close()
            if self._local is not None:
                if self._local.trace is not None:
                    self._local.trace.close()
                self._local.close()
            if self._trace is not None:  # the rows stay readable with trace()
                self._trace_rows = self._trace.rows()
                self._trace.close()

    def __repr__(self) -> str:
        repeat = f", repeat={self._repeat}" if self._repeat != 1 else ""
        return f"CPUVectorEnv({self.spec.id}, num_envs={self.num_envs}{repeat})"
