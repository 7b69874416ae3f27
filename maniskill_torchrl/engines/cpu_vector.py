"""N ManiSkill CPU-sim envs, one per process, behind ManiSkill's batched torch API.

ManiSkill's CPU sim holds one env per process. :class:`CPUVectorEnv` runs ``N`` of them, sub-env
0 in this process and the others in worker processes, and answers like one GPU-sim env of
``num_envs=N``: ``step`` / ``reset`` take and return batched torch tensors (``[N, ...]``),
``reset(options={"env_idx": ...})`` resets some envs only, and ``get_info()`` describes the info
entries. :class:`~maniskill_torchrl.ManiSkillWrapper` wraps it as it wraps a GPU-sim env, so CPU
and GPU users write the same code.

One shared-memory block holds every sub-env's actions and step results, ``[N, ...]`` per leaf
with ManiSkill's own dtypes (``_shared.py``). A step writes the actions there, wakes each worker
with one byte on its pipe, steps sub-env 0 here while they step theirs, waits for one byte back
from each, and reads the whole batch with one copy: no pickling and no concatenation per step.
Each sub-env, sub-env 0 included, writes its own row. Nothing is rounded on the way: every
sub-env equals a lone ManiSkill env given the same seed and actions, bit for bit.

The worker side (the gym wrapper each worker runs, its factory, its loop) is in ``_worker.py``;
the processes and pipes seen from here in ``_pool.py``. None of these modules imports TorchRL or
the rest of the library beyond ``_internal``: the workers import them, and start faster
without them.

The env core (:class:`~maniskill_torchrl.ManiSkillWrapper`) never imports this module: it reads
the capabilities this engine declares (:attr:`CPUVectorEnv.returns_copies`,
:attr:`~CPUVectorEnv.runs_inference_mode`, :attr:`~CPUVectorEnv.seeds_partial_resets`,
:attr:`~CPUVectorEnv.reconfigures_partially`, :attr:`~CPUVectorEnv.repeats_actions`,
:meth:`~CPUVectorEnv.render_frame_shape`), and ``ManiSkillEnv`` picks it.
"""

from __future__ import annotations

import os
import pickle
import time
import warnings
from collections.abc import Mapping, Sequence
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from maniskill_torchrl._internal.assets import check_assets
from maniskill_torchrl._internal.mp import preload_forkserver
from maniskill_torchrl.engines._interrupts import HELD
from maniskill_torchrl.engines._pool import STEP, STEP_RESET, WorkerFailure, WorkerPool
from maniskill_torchrl.engines._shared import Layout, SharedBlock
from maniskill_torchrl.engines._trace import COLLECT_END, HERE_END, SEND, StepTrace, summarize
from maniskill_torchrl.engines._worker import (
    INFO,
    OBS,
    REWARD,
    SUB_ENV_STATES,
    TERMINATED,
    TRUNCATED,
    MakeWorker,
    join_states,
    serve,
    to_numpy,
    zeros_tree,
)

__all__ = ["CPUVectorEnv", "check_gather_args", "in_process_default"]

# What a sub-env has under way in split phase (one per sub-env).
IDLE, STEPPING, STEPPING_RESET, RESETTING = 0, 1, 2, 3
_KINDS = {"step": STEPPING, "step_reset": STEPPING_RESET, "reset": RESETTING}
_KIND_NAMES = {v: k for k, v in _KINDS.items()}
# Seconds between two looks of the watchdog at the sub-envs that have not answered (warn_after, fail_after).
_WATCH_EVERY = 0.2


def check_gather_args(min_get: int, max_get: int | None, timeout: float | None) -> None:
    """TorchRL's ``AsyncEnvPool`` rules for a receive's ``min_get``, ``max_get`` and ``timeout``."""
    if min_get < 1:
        raise ValueError(f"min_get must be positive, got {min_get}.")
    if max_get is not None and max_get < min_get:
        raise ValueError(
            f"max_get must be greater than or equal to min_get, got min_get={min_get} and max_get={max_get}."
        )
    if timeout is not None and timeout < 0:
        raise ValueError(f"timeout must be non-negative, got {timeout}.")


# What a worker imports before it makes its env (torch, gymnasium, ManiSkill's tasks): most of its
# start. The forkserver imports them once; the workers it forks start without (RESULTS.md, "Worker start").
WORKER_IMPORTS = ("maniskill_torchrl.engines._worker", "mani_skill.envs")


def in_process_default(num_envs: int) -> bool:
    """Whether sub-env 0 runs in the main process when ``in_process`` is not given: yes for one
    sub-env (no worker at all), and otherwise unless this process may use more cores than there
    are sub-envs (then each sub-env gets a worker and a core, and the main process keeps a core
    for its own work: policy, TensorDicts).

    On 2 cores at N = 2, sub-env 0 in the main process measures faster (one process fewer to
    share two cores); on 16 cores at N = 15 the traces had the main process, with its own
    work plus sub-env 0's sim, as the lockstep's straggler (benchmarks/RESULTS.md).
    """
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return num_envs == 1 or cores <= num_envs


class CPUVectorEnv:
    """``num_envs`` ManiSkill CPU-sim envs, one per process, with a GPU-sim env's batched API.

    Args:
        env_id (str): a registered ManiSkill task, e.g. ``"PickCube-v1"``.
        num_envs (int): sub-envs, one per process.

    Keyword Args:
        in_process (bool or None): True: sub-env 0 runs in this process, stepped while the
            workers step the others (``num_envs - 1`` worker processes). False: ``num_envs``
            workers, and this process only waits for them. None (default): decided by the
            machine (:func:`~maniskill_torchrl.engines.cpu_vector.in_process_default`): True
            unless this process may use more cores than there are sub-envs.
        split_phase (bool): every sub-env in a worker (``in_process`` must not be True), and
            the split-phase calls :meth:`step_send` / :meth:`step_recv` and
            :meth:`reset_send` / :meth:`reset_recv` step and reset some sub-envs while the
            caller goes on, receiving whichever are done (default False).
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
    All sub-envs are stepped together (a step is lockstep: it returns when the slowest is done).
    After :meth:`set_repeat` ``(k)`` each ``step`` repeats its action up to ``k`` times in
    every sub-env, which stops at its own episode's end (ManiSkill's ``ActionRepeatWrapper``
    per sub-env): one round trip per ``step``, no physics after an end.

    Split phase (``split_phase=True``): :meth:`step_send` starts a step of some sub-envs and
    returns at once; :meth:`step_recv` returns the rows of whichever sub-envs have finished,
    in the order they finished, waiting for at least ``min_get`` of them. With
    ``autoreset=True``, a sub-env whose step ends its episode resets at once in its worker (with
    the seed given for it) and :meth:`step_recv` returns that reset too. The lockstep calls
    (``step``, ``reset``, ``call``...) need every sub-env idle.

    Every call into ManiSkill runs under :func:`torch.inference_mode`, sub-env 0's too; only
    numpy copies leave the sub-envs. A failure is raised here, by the call that met it: sub-env
    0's exception as is (the env goes on); a worker's exception, or a worker that died, makes the
    call raise a ``RuntimeError`` naming its sub-env, after every worker is stopped and the env
    closed (the worker's exception is its cause, where it could be sent).
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
        in_process: bool | None = None,
        split_phase: bool = False,
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
        if split_phase:
            if in_process:
                raise ValueError(
                    "CPUVectorEnv(split_phase=True) runs every sub-env in a worker: leave in_process unset (or False)."
                )
            in_process = False
        elif in_process is None:
            in_process = in_process_default(int(num_envs))
        maniskill_kwargs.setdefault("sim_backend", "physx_cpu")
        check_assets(env_id, maniskill_kwargs)  # before any worker starts
        #: the ``gym.make`` arguments of every sub-env (what a trajectory file records)
        self.maniskill_kwargs = dict(maniskill_kwargs)
        self.num_envs = int(num_envs)
        self.device = torch.device("cpu")
        self.spec = gym.spec(env_id)
        self._first = 1 if in_process else 0  # the sub-env index of the first worker
        #: whether sub-env 0 runs in this process
        self.in_process = bool(in_process)
        self.split_phase = bool(split_phase)
        # Split phase, one entry per sub-env: the call under way (IDLE, STEPPING, STEPPING_RESET,
        # RESETTING), whether its answer has been read (and its arrival number, for the order of
        # receipt), the seconds a receive has waited for it since it was sent (the watchdog: a pause of
        # the caller between two receives is never the sub-env's) and whether it was warned about.
        self._state = np.zeros(int(num_envs), np.int8)
        self._arrived = np.zeros(int(num_envs), np.bool_)
        self._cut_short = False  # a lockstep call under way, or cut short by Ctrl-C (see _catch_up)
        self._arrival = np.zeros(int(num_envs), np.int64)
        self._arrivals = 0
        self._waited_on = np.zeros(int(num_envs))
        self._warned = np.zeros(int(num_envs), np.bool_)
        self._watch_at = 0.0
        #: Seconds a receive may wait for one sub-env's split-phase call before a warning
        #: (``warn_after``), then before an error that closes the env (``fail_after``: a stuck worker);
        #: None: never. Only the time spent waiting in a receive counts, not the caller's own time.
        self.warn_after: float | None = 30.0
        self.fail_after: float | None = 300.0
        self._pool: WorkerPool | None = None
        self._local = None
        self._block: SharedBlock | None = None
        self._closed = False
        self._closed_why = ""
        self._repeat = 1
        self._trace = StepTrace(num_envs, trace_steps) if trace_steps else None
        spec = None if self._trace is None else self._trace.spec
        makers = [MakeWorker(env_id, maniskill_kwargs, index=i, trace=spec) for i in range(num_envs)]
        try:
            if num_envs > self._first:  # the workers make their envs while this process makes its own
                if context == "forkserver":
                    preload_forkserver(WORKER_IMPORTS)
                self._pool = WorkerPool(serve, makers[self._first :], context)
            if in_process:
                self._local = makers[0].make()
                if spec is not None:  # sub-env 0 stamps its columns as a worker does, with its own count
                    self._local.trace = StepTrace(*spec)
                kinds = (self._local.observation_space, self._local.action_space, self._local.render_mode)
            if self._pool is not None:
                kinds = self._pool.ready()[0]
            space, self.single_action_space, self.render_mode = kinds
            self._block = SharedBlock(Layout(space, self.single_action_space, num_envs, autoreset=split_phase))
            if self._pool is not None:
                self._pool.attach(self._block.layout, self._block.name)
        except (EOFError, OSError) as err:  # a worker died while starting
            self.close()
            raise RuntimeError(
                f"CPUVectorEnv({env_id!r}, {num_envs}): a worker process died while starting (its traceback is "
                f"printed above). Workers start with context={context!r}, which imports the main script again: "
                "in a script, build envs only under `if __name__ == '__main__':`."
            ) from err
        except WorkerFailure as failure:  # a worker's make raised: that error, as the parent's own make would
            self.close()
            if failure.error is not None:
                raise failure.error from None
            raise RuntimeError(f"CPUVectorEnv({env_id!r}, {num_envs}): {failure.what}") from None
        except BaseException:
            self.close()
            raise
        self.single_observation_space = space[OBS]
        self._info_space = space[INFO]

    @property
    def unwrapped(self) -> CPUVectorEnv:
        return self

    # ---------------------------------------------------------------- data
    def _read(self) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        step = self._block.read()
        return step[OBS], step[REWARD], step[TERMINATED], step[TRUNCATED], step[INFO]

    def _check_open(self, call: str) -> None:
        if self._closed:
            raise RuntimeError(
                f"{self!r} is closed" + (f" ({self._closed_why})" if self._closed_why else "") + f": it cannot "
                f"{call}() any more. Make a new env."
            )

    def _together(self, call: str, send: Any, here: Any, collect: Any) -> Any:
        """``send(pool)`` to the workers, ``here()`` on sub-env 0 while they work, then
        ``collect(pool)``; returns ``collect``'s result. ``send=None``: no worker takes part;
        ``here=None``: sub-env 0 does not. The workers' answers are collected even when sub-env
        0 raises, so that none is left pending; a worker that raised or died closes the env. A Ctrl-C
        during the sends comes once they are all sent, and the answers are still collected."""
        self._check_open(call)
        if self._state.any():
            raise RuntimeError(
                f"{self!r}: {call}() steps every sub-env together, and sub-envs {sorted(self.pending)} have a "
                "split-phase call pending: receive them first (step_recv / reset_recv)."
            )
        if self._cut_short:  # a lockstep call Ctrl-C cut short: its answers first
            self._catch_up()
        pool = self._pool if send is not None else None
        sent, theirs = False, None
        try:
            if pool is not None:
                try:
                    with HELD:  # all sent and noted, or none
                        send(pool)
                        sent = self._cut_short = True
                except (EOFError, OSError, pickle.PicklingError, TypeError, AttributeError) as err:
                    raise self._worker_failed(call, err) from err
            if here is not None and self._local is not None:
                here()
        finally:
            if sent:
                try:
                    theirs = collect(pool)
                except (EOFError, OSError, WorkerFailure) as err:
                    raise self._worker_failed(call, err) from getattr(err, "error", None) or err
                self._cut_short = False
        return theirs

    def _catch_up(self) -> None:
        """Reads and drops the answers a lockstep call cut short by Ctrl-C left in the pipes (a
        ``KeyboardInterrupt`` may land on any line; the pool's :attr:`~WorkerPool.owed` says which)."""
        try:
            self._pool.catch_up()
        except (EOFError, OSError, WorkerFailure) as err:
            raise self._worker_failed("catch up after Ctrl-C", err) from err
        self._cut_short = False

    def step(
        self, action: torch.Tensor | Mapping[str, torch.Tensor]
    ) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        self._check_open("step")
        block, trace = self._block, self._trace
        if trace is not None:
            trace.stamp(SEND)
        block.write_actions(to_numpy(action))
        local = self._local

        def here() -> None:
            block.write_row(0, local.step(block.action_row(0))[0])
            if trace is not None:
                trace.stamp(HERE_END)

        self._together("step", WorkerPool.wake, here, WorkerPool.wait)
        if trace is not None:
            trace.stamp(COLLECT_END)
            trace.count += 1
        return self._read()

    # ---------------------------------------------------------------- split phase
    def step_send(
        self,
        action: torch.Tensor | Mapping[str, torch.Tensor],
        env_idx: Sequence[int],
        *,
        autoreset: bool = False,
        reset_seeds: Sequence[int | None] | None = None,
    ) -> None:
        """Starts a step of the sub-envs ``env_idx`` with their ``[k, ...]`` actions, and returns
        at once; :meth:`step_recv` (with the same ``autoreset``) returns the results.

        ``autoreset=True``: a sub-env whose step ends its episode (terminated or truncated)
        resets right away in its worker, with its seed in ``reset_seeds`` (one per sub-env of
        ``env_idx``; None: ManiSkill's unseeded reset).
        """
        rows = self._idle_rows("step_send", env_idx)
        block = self._block
        block.write_action_rows(rows, to_numpy(action))
        if autoreset:
            seeds = [None] * len(rows) if reset_seeds is None else reset_seeds
            if len(seeds) != len(rows):
                raise ValueError(f"step_send: {len(seeds)} reset seeds for {len(rows)} sub-envs.")
            block.seeds[rows] = seeds if isinstance(seeds, np.ndarray) else [-1 if s is None else int(s) for s in seeds]
        with HELD:  # woken and noted woken, or neither (between, answers would be left unread)
            try:
                self._pool.wake_some(rows.tolist(), STEP_RESET if autoreset else STEP)
            except (EOFError, OSError) as err:
                raise self._worker_failed("step_send", err) from err
            self._sent(rows, STEPPING_RESET if autoreset else STEPPING)

    def step_recv(
        self,
        min_get: int = 1,
        *,
        max_get: int | None = None,
        timeout: float | None = None,
        env_idx: Sequence[int] | None = None,
        autoreset: bool = False,
    ) -> tuple[np.ndarray, tuple, tuple | None]:
        """The results of the steps sent with this ``autoreset``: ``(env_idx, (obs, reward,
        terminated, truncated, info), reset)``, each ``[k, ...]``, in sub-env order.

        Waits until at least ``min_get`` have finished, then returns every finished one (TorchRL's
        ``AsyncEnvPool`` rules): at most ``max_get``; with a ``timeout`` (seconds for the whole
        call), what finishes until then, and :class:`TimeoutError` if fewer than ``min_get`` did
        (what arrived is kept for the next call). With ``env_idx``, waits for those sub-envs
        and returns them only. ``reset`` (``autoreset=True``, else None) is ``(done, obs,
        info)``: the ``[k]`` bool mask of the sub-envs that ended an episode and reset, and
        their reset's observations and infos, ``[done.sum(), ...]``.
        """
        rows = self.step_recv_rows(min_get, max_get=max_get, timeout=timeout, env_idx=env_idx, autoreset=autoreset)
        block = self._block
        step = block.read_rows(rows)
        reset = None
        if autoreset:
            done = (step[TERMINATED] | step[TRUNCATED]).numpy()
            again = block.read_rows(rows[done] + self.num_envs) if done.any() else {OBS: None, INFO: None}
            reset = (torch.from_numpy(done), again[OBS], again[INFO])
        return rows, (step[OBS], step[REWARD], step[TERMINATED], step[TRUNCATED], step[INFO]), reset

    def step_recv_rows(
        self,
        min_get: int = 1,
        *,
        max_get: int | None = None,
        timeout: float | None = None,
        env_idx: Sequence[int] | None = None,
        autoreset: bool = False,
    ) -> np.ndarray:
        """:meth:`step_recv` without reading the results: the sub-envs whose step is done, in order.
        Their rows of the block (:attr:`block`; row ``N + i`` for the reset of sub-env ``i``, with
        ``autoreset``) hold their results until their next call."""
        return self._receive(STEPPING_RESET if autoreset else STEPPING, min_get, max_get, timeout, env_idx)

    @property
    def block(self) -> Any:
        """The shared block of actions and results (``engines/_shared.py``'s ``SharedBlock``)."""
        return self._block

    def reset_send(self, env_idx: Sequence[int], seeds: Sequence[int | None] | None = None) -> None:
        """Starts a reset of the sub-envs ``env_idx`` (``seeds``: one per sub-env, None for
        ManiSkill's unseeded reset) and returns at once; :meth:`reset_recv` returns them."""
        rows = self._idle_rows("reset_send", env_idx)
        seeds = [None] * len(rows) if seeds is None else list(seeds)
        if len(seeds) != len(rows):
            raise ValueError(f"reset_send: {len(seeds)} seeds for {len(rows)} sub-envs.")
        with HELD:
            try:
                for i, seed in zip(rows.tolist(), seeds):
                    self._pool.send(i, "reset", seed=None if seed is None else int(seed), options=None)
            except (EOFError, OSError) as err:
                raise self._worker_failed("reset_send", err) from err
            self._sent(rows, RESETTING)

    def reset_recv(
        self,
        min_get: int = 1,
        *,
        max_get: int | None = None,
        timeout: float | None = None,
        env_idx: Sequence[int] | None = None,
    ) -> tuple[np.ndarray, Any, dict]:
        """The sent resets that are done: ``(env_idx, obs, info)``, ``[k, ...]``; ``min_get``,
        ``max_get``, ``timeout`` and ``env_idx`` as in :meth:`step_recv`."""
        rows = self._receive(RESETTING, min_get, max_get, timeout, env_idx)
        step = self._block.read_rows(rows)
        return rows, step[OBS], step[INFO]

    @property
    def closed(self) -> bool:
        """Whether the env is closed (by ``close()``, or after a worker failed)."""
        return self._closed

    @property
    def pending(self) -> dict[int, str]:
        """The sub-envs with a split-phase call under way, and which (``"step"``,
        ``"step_reset"``, ``"reset"``)."""
        return {i: _KIND_NAMES[k] for i, k in enumerate(self._state.tolist()) if k}

    def stepping(self) -> np.ndarray:
        """A ``[num_envs]`` bool mask (a fresh array) of the sub-envs with a split-phase step under way."""
        return (self._state == STEPPING) | (self._state == STEPPING_RESET)

    def count_pending(self, kind: str) -> int:
        """How many sub-envs have a ``kind`` call (``"step"``, ``"step_reset"``, ``"reset"``) under way."""
        return int(np.count_nonzero(self._state == _KINDS[kind]))

    def answered(self, index: int) -> bool:
        """Whether sub-env ``index``'s answer to its split-phase call has arrived (read here if it
        is ready); a receive then returns it without waiting."""
        self._check_open("receive")
        if self._arrived[index]:
            return True
        if self._state[index] == IDLE:
            raise RuntimeError(f"{self!r}: sub-env {index} has no split-phase call under way: send one first.")
        if self._pool.pipes[index].poll(0):
            self._read_answers([index])
            return True
        self._watch()
        return False

    def wait_readable(self, index: int, timeout: float) -> None:
        """Waits up to ``timeout`` s for sub-env ``index``'s worker to answer, without reading it
        (one thread per sub-env may wait so, each on its own; the wait counts for the watchdog)."""
        start = time.monotonic()
        try:
            self._pool.pipes[index].poll(timeout)
        except (OSError, EOFError, ValueError):  # closed meanwhile: answered() says so
            pass
        self._waited_on[index] += time.monotonic() - start

    def _sent(self, rows: np.ndarray, kind: int) -> None:
        self._state[rows] = kind
        self._arrived[rows] = False
        self._waited_on[rows] = 0.0
        self._warned[rows] = False

    def _idle_rows(self, call: str, env_idx: Sequence[int]) -> np.ndarray:
        self._check_open(call)
        if not self.split_phase:
            raise RuntimeError(f"{self!r}: {call}() is a split-phase call: make the env with split_phase=True.")
        if isinstance(env_idx, np.ndarray) and env_idx.ndim == 1:
            rows = env_idx.astype(np.int64, copy=False)
        else:
            rows = np.asarray(torch.as_tensor(env_idx, device="cpu").reshape(-1), dtype=np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= self.num_envs):
            raise IndexError(f"{call}: sub-env indices {rows.tolist()} out of range for {self.num_envs} sub-envs.")
        if rows.size > 1 and np.unique(rows).size != rows.size:
            raise ValueError(f"{call}: sub-env indices {rows.tolist()} repeat an index.")
        if self._cut_short:  # a lockstep call Ctrl-C cut short: its answers first
            self._catch_up()
        busy = self._state[rows]
        if busy.any():
            i = int(rows[np.flatnonzero(busy)[0]])
            raise RuntimeError(
                f"{call}: sub-envs {rows[busy != 0].tolist()} still have a {_KIND_NAMES[int(self._state[i])]} "
                "under way: receive it first."
            )
        return rows

    def _read_answers(self, positions: list[int]) -> None:
        """Reads the answers of the workers at ``positions`` (whatever each was sent; a wait found them in
        their pipes), read and noted arrived with Ctrl-C held; a worker that failed closes the env."""
        state, pool = self._state, self._pool
        try:
            with HELD:
                for i in positions:
                    if state[i] == RESETTING:
                        pool.take_answer(i)
                    else:
                        pool.take_done(i)
                    self._arrived[i] = True
                    self._arrival[i] = self._arrivals
                    self._arrivals += 1
        except (EOFError, OSError, WorkerFailure) as err:
            raise self._worker_failed("receive", err) from getattr(err, "error", None) or err

    def _receive(
        self, kind: int, min_get: int, max_get: int | None, timeout: float | None, only: Sequence[int] | None
    ) -> np.ndarray:
        """Waits for answers of the sub-envs sent ``kind`` (of those in ``only``, if given); returns
        the rows to hand out (see :meth:`step_recv`), in sub-env order, and marks them idle."""
        name = _KIND_NAMES[kind]
        self._check_open(f"{name}_recv")
        mine = self._state == kind
        if only is not None:
            rows = np.asarray(torch.as_tensor(only, device="cpu").reshape(-1), dtype=np.int64)
            missing = rows[~mine[rows]]
            if missing.size:
                raise RuntimeError(
                    f"{self!r}: {name}_recv(env_idx={rows.tolist()}): sub-envs {missing.tolist()} have no {name} "
                    "under way."
                )
            mine = np.zeros_like(mine)
            mine[rows] = True
            min_get = max_get = rows.size
        under_way = int(np.count_nonzero(mine))
        if not under_way:
            raise RuntimeError(f"{self!r}: {name}_recv() with no {name} under way: send one first.")
        check_gather_args(min_get, max_get, timeout)
        if min_get > under_way:
            raise RuntimeError(f"Cannot await {min_get} {name} when only {under_way} are under way.")
        limit = under_way if max_get is None else min(int(max_get), under_way)
        start = time.monotonic()
        deadline = None if timeout is None else start + timeout
        arrived, waited_on = self._arrived, self._waited_on
        while True:
            got = int(np.count_nonzero(arrived & mine))
            if got >= limit:
                break
            now = time.monotonic()
            if got >= min_get:  # enough: what is ready now, or until the deadline
                wait = 0.0 if deadline is None else max(0.0, deadline - now)
            else:
                wait = None if deadline is None else max(0.0, deadline - now)
                if self.warn_after is not None or self.fail_after is not None:
                    wait = _WATCH_EVERY if wait is None else min(wait, _WATCH_EVERY)
            if wait == 0.0:  # a poll, not a wait
                ready = self._pool.readable(0.0)
            else:  # a wait: it counts for the sub-envs not in yet
                before = time.monotonic()
                ready = self._pool.readable(wait)
                now = time.monotonic()
                waited_on[mine & ~arrived] += now - before
                if now >= self._watch_at:  # a few times a second: the envs that keep others waiting
                    self._watch()
                    self._watch_at = now + _WATCH_EVERY
            if ready:
                self._read_answers(ready)
                if deadline is None and np.count_nonzero(arrived & mine) >= min_get:
                    break  # everything ready at that select is in: no second look
                continue
            if got >= min_get and (deadline is None or now >= deadline):
                break
            if deadline is not None and now >= deadline:
                raise TimeoutError(
                    f"{name}_recv: {got} of the {min_get} sub-envs asked for finished within {timeout} s; "
                    "what arrived is kept for the next call."
                )
        taken = np.flatnonzero(arrived & mine)
        if taken.size > limit:  # the first to arrive
            taken = np.sort(taken[np.argsort(self._arrival[taken], kind="stable")[:limit]])
        # Idle first: a Ctrl-C between the two leaves an idle sub-env marked arrived, which nothing reads
        # (a receive looks at the sub-envs with a call under way, and a send clears the mark).
        self._state[taken] = IDLE
        arrived[taken] = False
        return taken

    def _watch(self) -> None:
        """Warns about sub-envs a receive has waited ``warn_after`` s for, and closes the env with an
        error naming them past ``fail_after`` s (a stuck worker: never a hang)."""
        late = (self._state != IDLE) & ~self._arrived
        if not late.any():
            return
        waited = np.where(late, self._waited_on, 0.0)
        if self.fail_after is not None and waited.max() >= self.fail_after:
            stuck = np.flatnonzero(waited >= self.fail_after).tolist()
            pids = [self._pool.processes[i].pid for i in stuck]
            what = f"sub-env(s) {stuck} (pid {pids}) did not answer for {self.fail_after:g} s (fail_after)"
            self._closed_why = f"{what}; their workers were stopped"
            self._pool.kill(stuck)  # at once: a stopped process cannot act on the SIGTERM of close()
            self.close()
            raise RuntimeError(
                f"CPUVectorEnv({self.spec.id}): {what}. Their workers are stuck (a sim that never returns, or a "
                "stopped process); the env is closed and its workers stopped. Make a new env; raise fail_after "
                "if its calls are this slow."
            )
        if self.warn_after is not None:
            slow = late & ~self._warned & (waited >= self.warn_after)
            if slow.any():
                self._warned |= slow
                warnings.warn(
                    f"CPUVectorEnv({self.spec.id}): sub-env(s) {np.flatnonzero(slow).tolist()} have not answered "
                    f"for {self.warn_after:g} s (warn_after); the env is closed with an error after "
                    f"{self.fail_after} s (fail_after).",
                    RuntimeWarning,
                    stacklevel=4,
                )

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
            # ManiSkill's convention: one row of env_states (and of the cached obs, if given) per env
            # being reset, in env order. Every sub-env being reset gets the rows and picks its own
            # (one message to all).
            options[SUB_ENV_STATES] = (np.flatnonzero(mask).tolist(), states["env_states"], states.get("obs"))
        block, local = self._block, self._local
        workers = [i for i in range(self.num_envs - self._first) if mask[self._first + i]]

        def send(pool: WorkerPool) -> None:
            for i in workers:
                pool.send(i, "reset", seed=seeds[self._first + i], options=options or None)

        def here() -> None:
            block.write_row(0, local.reset(seed=seeds[0], options=options or None)[0])

        self._together(
            "reset",
            send if workers else None,
            here if mask[0] else None,
            lambda pool: pool.collect(workers),
        )
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
        mine = []

        def here() -> None:
            attr = self._local.get_wrapper_attr(name)
            mine.append(attr(*args, **kwargs) if callable(attr) else attr)

        theirs = self._together(
            name, lambda pool: pool.send_all("call", name, *args, **kwargs), here, WorkerPool.collect_all
        )
        return tuple(mine) + (tuple(theirs) if theirs is not None else ())

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
        from maniskill_torchrl._internal.repeat import check_repeat  # tensordict: kept out of module import

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

    @property
    def _human_render_camera_configs(self) -> dict:
        """One sub-env's frame size where the TorchRL adapter reads ManiSkill's (one camera of
        ``height`` x ``width``): rendering every sub-env before a reset fails in ManiSkill."""
        height, width, _ = self.render_frame_shape()
        return {"render": SimpleNamespace(height=height, width=width)}

    def render(self) -> torch.Tensor:
        """Every sub-env's ``render()``, concatenated: ``[N, H, W, 3]`` uint8 for ``rgb_array``."""
        return torch.cat([torch.as_tensor(f) for f in self.call("render")])

    def _worker_failed(self, call: str, err: BaseException) -> RuntimeError:
        """Stops the sub-envs (the others would wait for the one that failed) and says what happened."""
        failure = self._pool.describe(err)
        self._closed_why = f"{failure.what} during {call}()"
        self.close()
        return RuntimeError(
            f"CPUVectorEnv({self.spec.id}): {failure.what} during {call}(); the env is closed ({failure.where}). "
            "Close it and make a new env."
        )

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._state[:] = IDLE  # nothing is under way any more
        self._arrived[:] = False
        if self._pool is not None:
            if self._closed_why:  # after a failure: the workers may be anywhere in a call
                self._pool.stop()
            else:
                self._pool.close()
        if self._local is not None:
            if self._local.trace is not None:
                self._local.trace.close()
            self._local.close()
        if self._block is not None:
            self._block.close()
        if self._trace is not None:  # the rows stay readable with trace()
            self._trace_rows = self._trace.rows()
            self._trace.close()

    def __repr__(self) -> str:
        repeat = f", repeat={self._repeat}" if self._repeat != 1 else ""
        return f"CPUVectorEnv({self.spec.id}, num_envs={self.num_envs}{repeat})"
