"""``ParallelEnv`` of single CPU ManiSkill envs, with the settings that keep the cores for the workers.

:class:`ManiSkillParallelEnv` is TorchRL's :class:`torchrl.envs.ParallelEnv` with four changes,
each found by profiling ``Collector(ParallelEnv(N, ManiSkillEnv + CPUUnbatch))`` on 2 cores (the
docs' CPU performance guide links the figures). The rest of the gap to gymnasium's
``AsyncVectorEnv`` of ManiSkill's ``CPUGymWrapper`` is TorchRL's per-step work in the collector,
the ``ParallelEnv`` and the worker, on the critical path of every synchronous step, which no
setting removes. Make the workers' envs ``ManiSkillEnv(id, batch_size=[])`` (unbatched by the
env itself: no transformed env's step in each worker when no other transform is needed). For
speed, prefer the batched env ``ManiSkillEnv(id, num_envs=N)`` or ``Collector(make_env,
backend="process", num_collectors=N)``.

1. **Waiting for the workers sleeps instead of spinning.** TorchRL 0.14 waits for a step's
   results by spin-polling one shared-memory flag per worker
   (``ParallelEnv._wait_for_workers``), which keeps a whole core busy for the entire step;
   with as many workers as cores that core is taken from the workers. Here the parent polls
   the same flags with short sleeps (``poll_s``), after a first sleep of 80% of the shortest
   recent wait, and checks every 50 ms that the workers are alive. ``wait="auto"`` (default)
   sleeps when the workers leave the parent no core (fewer usable cores than workers + 1) and
   keeps TorchRL's spin otherwise; ``"sleep"`` / ``"spin"`` force one. Only the shared-buffer
   path (``use_buffers=True``, TorchRL's default) spins; the ``use_buffers=False`` path
   blocks on the pipes already and is left as it is.
2. **Workers run under Linux's ``SCHED_BATCH`` policy** when the parent sleeps
   (``batch_workers``, see :func:`set_batch_policy`): a woken worker no longer preempts the
   parent before it has sent the step command to every worker. Not with a spinning parent: a
   woken batch worker placed on its core would wait for it.
3. **The start method defaults to ``"forkserver"``** (``"spawn"`` where the platform has no
   forkserver), whatever ``multiprocessing``'s global start method says, unless
   ``mp_start_method`` is given, and the forkserver imports TorchRL's worker and ManiSkill's
   tasks once (``WORKER_IMPORTS``, when this process starts it): a worker forked from it
   starts without importing them, most of a ``"spawn"`` worker's start (the figures are in
   RESULTS.md, "Worker start"). Python pins the global method to ``"fork"`` the first time any
   process starts (gymnasium's ``AsyncVectorEnv(context="forkserver")`` does), and ManiSkill
   workers forked from a parent that has built a ManiSkill env hang forever (see
   ``maniskill_torchrl._internal.mp``); the forkserver, started clean, builds no env.
4. **Forking a parent that holds a SAPIEN renderer fails at once** with a ``RuntimeError``
   that says what to do, instead of hanging (``mp_start_method="fork"`` after a ManiSkill env
   was built in this process).

Everything else (specs, seeding, ``"_reset"`` / ``"_step"`` masks, collectors, ``close``) is
TorchRL's: the data are the same as ``torchrl.envs.ParallelEnv``'s, bit for bit. It overrides
two private hooks of ``torchrl.envs.ParallelEnv`` 0.14, ``_wait_for_workers`` and
``_start_workers`` (wrapped); the private attributes it reads as TorchRL's own wait does go
through ``maniskill_torchrl._private``.

Examples:
    >>> from maniskill_torchrl import ManiSkillEnv
    >>> from maniskill_torchrl.parallel import ManiSkillParallelEnv
    >>> def make_env():
    ...     return ManiSkillEnv("PickCube-v1", obs_mode="state", batch_size=[])  # unbatched
    >>> env = ManiSkillParallelEnv(2, make_env)  # batch [2]; a drop-in for torchrl.envs.ParallelEnv
    >>> env.rollout(3)["next", "observation"].shape
    torch.Size([2, 3, 42])
    >>> env.close()
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Literal

from torchrl.envs import ParallelEnv as _TorchRLParallelEnv

from maniskill_torchrl import _private
from maniskill_torchrl._internal.mp import check_start_method, preload_forkserver

__all__ = ["ManiSkillParallelEnv", "set_batch_policy", "usable_cores"]

# What a worker imports before it builds its env: TorchRL's worker loop, the library's env and
# ManiSkill's tasks. The forkserver imports them once for every worker.
WORKER_IMPORTS = ("torchrl.envs.batched_envs", "maniskill_torchrl.envs", "mani_skill.envs")
DEFAULT_START_METHOD = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"

WaitMode = Literal["auto", "sleep", "spin"]

# Between two checks of worker liveness and of the timeout while sleeping (s).
_HEALTH_CHECK_S = 0.05
# The first sleep of a wait covers this share of the shortest of the last _RECENT waits (the rest
# is polled): steps vary (an episode's reset step takes longer), and oversleeping delays the
# whole batch, so a short wait must not be followed by a long first sleep.
_FIRST_SLEEP_SHARE = 0.8
_RECENT = 16


def set_batch_policy(pid: int) -> bool:
    """Puts every thread of process ``pid`` under Linux's ``SCHED_BATCH`` policy; ``False`` where unsupported.

    ``SCHED_BATCH`` keeps the normal fair share (same nice weight) but a thread that wakes up
    does not preempt the running one. A ParallelEnv parent sends its step command to each worker
    in turn through a pipe; pipe wake-ups are "synchronous" hints, so the kernel tends to run the
    woken worker on the parent's core at once, and the parent waits a whole time slice before
    it can send the next command. With the workers
    as batch threads, the parent finishes sending first. Unprivileged; ignores threads that exit
    meanwhile.
    """
    policy = getattr(os, "SCHED_BATCH", None)
    if policy is None or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        tids = [pid]
    done = False
    for tid in tids:
        try:
            os.sched_setscheduler(tid, policy, os.sched_param(0))
            done = True
        except OSError:
            pass
    return done


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


class ManiSkillParallelEnv(_TorchRLParallelEnv):
    """TorchRL's ``ParallelEnv`` whose parent sleeps while its workers step (see the module docstring).

    The output of every step is the same as ``torchrl.envs.ParallelEnv``'s.

    Args:
        num_workers (int): worker processes, one env each.
        create_env_fn (callable or list of callables): builds one worker's env.

    Keyword Args:
        create_env_kwargs (dict or list of dicts, optional): as in TorchRL.
        wait (str): ``"auto"`` (default: ``"sleep"`` when ``usable_cores() < num_workers + 1``,
            else ``"spin"``), ``"sleep"`` or ``"spin"`` (TorchRL's wait).
        poll_s (float): the sleep between two polls of the workers' done flags, in seconds
            (default 100 us; Linux adds its ~50 us timer slack).
        batch_workers (bool, optional): put the worker processes under ``SCHED_BATCH`` once
            started (a no-op where the OS has no such policy). Default: when the parent sleeps
            (with a spinning parent a woken batch worker could wait behind it).
        mp_start_method (str, optional): ``"forkserver"`` when not given (``"spawn"``, TorchRL's
            documented default, where the platform has no forkserver), even if
            ``multiprocessing``'s global method is ``"fork"``.
            ``"fork"`` raises ``RuntimeError`` at start if this process has built a ManiSkill env.
        **kwargs: any other :class:`torchrl.envs.ParallelEnv` argument (``use_buffers``,
            ``num_threads``, ``metadata_from_workers``, ``shutdown_timeout``...).
    """

    def __init__(
        self,
        num_workers: int,
        create_env_fn: Callable[..., Any] | Sequence[Callable[..., Any]],
        *,
        create_env_kwargs: dict | Sequence[dict] | None = None,
        wait: WaitMode = "auto",
        poll_s: float = 1e-4,
        batch_workers: bool | None = None,
        mp_start_method: str | None = None,
        **kwargs: Any,
    ) -> None:
        if wait not in ("auto", "sleep", "spin"):
            raise ValueError(f"wait must be 'auto', 'sleep' or 'spin', got {wait!r}.")
        if not poll_s > 0:
            raise ValueError(f"poll_s must be > 0, got {poll_s!r}.")
        # Set before super().__init__: metadata_from_workers=True starts the workers in there.
        self._wait_mode: WaitMode = wait
        self._sleeps = wait == "sleep" or (wait == "auto" and usable_cores() < num_workers + 1)
        self._poll_s = float(poll_s)
        # Batch workers only help a parent that sleeps: a spinning parent on the workers' core
        # would keep a woken batch worker waiting (it no longer preempts the spinner).
        self._batch_workers = self._sleeps if batch_workers is None else bool(batch_workers)
        self._recent_waits: deque[float] = deque(maxlen=_RECENT)
        super().__init__(
            num_workers,
            create_env_fn,
            create_env_kwargs=create_env_kwargs,
            mp_start_method=DEFAULT_START_METHOD if mp_start_method is None else mp_start_method,
            **kwargs,
        )

    @property
    def wait(self) -> str:
        """``"sleep"`` or ``"spin"``, the wait strategy in use."""
        return "sleep" if self._sleeps else "spin"

    def _start_workers(self) -> None:
        method = _private.start_method(self)
        check_start_method(method)
        if method == "forkserver":
            preload_forkserver(WORKER_IMPORTS)
        super()._start_workers()
        if self._batch_workers:
            for worker in _private.workers(self):
                set_batch_policy(worker.pid)

    def _wait_for_workers(self, workers_range) -> None:
        if not (self._sleeps and _private.uses_buffers(self)):
            return super()._wait_for_workers(workers_range)
        # The same shared-memory flags TorchRL's wait spins on (set to 1 by a worker when its
        # step / reset is written), polled between sleeps.
        flags, indices = _private.done_flags(self)
        pending = list(workers_range)
        t0 = time.perf_counter()
        first = _FIRST_SLEEP_SHARE * min(self._recent_waits, default=0.0)
        if first > 2 * self._poll_s:
            time.sleep(min(first, _HEALTH_CHECK_S))
        poll, sleep = self._poll_s, time.sleep
        next_check = t0 + _HEALTH_CHECK_S
        while True:
            pending = [i for i in pending if not flags[indices[i]]]
            if not pending:
                break
            now = time.perf_counter()
            if now >= next_check:
                self._check_workers(pending, now - t0)
                next_check = now + _HEALTH_CHECK_S
            sleep(poll)
        for i in workers_range:
            flags[indices[i]] = 0
        self._recent_waits.append(time.perf_counter() - t0)

    def _check_workers(self, pending: list[int], waited_s: float) -> None:
        """Raises (as TorchRL's wait does) if a pending worker died or the pipe timeout passed."""
        timeout = self.BATCHED_PIPE_TIMEOUT
        if waited_s > timeout:
            raise RuntimeError(
                f"Failed to run all workers within the {timeout} sec time limit. This "
                "threshold can be increased via the BATCHED_PIPE_TIMEOUT env variable."
            )
        flags, indices = _private.done_flags(self)
        for i in pending:
            worker = _private.workers(self)[i]
            if not worker.is_alive() and not flags[indices[i]]:
                try:
                    _private.shutdown_workers(self)
                except Exception:  # noqa: BLE001 - the dead worker is the error to report
                    pass
                raise RuntimeError(f"Cannot proceed, worker {i} dead (exit code {worker.exitcode}).")
