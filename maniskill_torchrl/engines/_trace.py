"""Per-step timestamps of a :class:`~maniskill_torchrl.CPUVectorEnv` in shared memory: who was
the straggler, how long a worker took to wake, how much of a step was serial.

Opt-in (``CPUVectorEnv(..., trace_steps=T)``): the last ``T`` steps are kept in a ring, one row
per step. The parent writes when it starts sending the actions (``send``), when its own sub-env
0 has stepped (``here_end``) and when it has every result (``collect_end``); each sub-env writes
when its step starts (``wake``) and when ManiSkill's step has returned (``sim_end``), in its own
process. Every stamp is :func:`time.perf_counter`, which Linux reads from ``CLOCK_MONOTONIC``:
one clock for every process of the machine. Only numpy and the standard library: the workers
load it.
"""

from __future__ import annotations

import time
from multiprocessing import shared_memory

import numpy as np

__all__ = ["StepTrace", "summarize"]

#: The parent's columns; sub-env ``i``'s are ``3 + 2 * i`` (wake) and ``4 + 2 * i`` (sim_end).
SEND, HERE_END, COLLECT_END = 0, 1, 2


class StepTrace:
    """A ``[steps, 3 + 2 * num_envs]`` float64 ring of timestamps in shared memory (NaN: not
    written). Made by the parent (``name=None``), attached by name in the workers."""

    def __init__(self, num_envs: int, steps: int, name: str | None = None) -> None:
        if steps < 1:
            raise ValueError(f"trace_steps must be a positive int, got {steps!r}.")
        self.num_envs, self.steps = int(num_envs), int(steps)
        width = 3 + 2 * self.num_envs
        self._owner = name is None
        self._shm = shared_memory.SharedMemory(name=name, create=self._owner, size=8 * self.steps * width)
        # Workers (forkserver, spawn) share the parent's resource tracker: an attached segment
        # registered again there is the same entry, unregistered once by the owner's unlink.
        self.table = np.ndarray((self.steps, width), np.float64, buffer=self._shm.buf)
        if self._owner:
            self.table[:] = np.nan
        #: steps stamped by this process (its next row is ``count % steps``)
        self.count = 0

    @property
    def spec(self) -> tuple[int, int, str]:
        """What a worker needs to attach: ``StepTrace(*spec)``."""
        return (self.num_envs, self.steps, self._shm.name)

    def stamp(self, column: int) -> None:
        self.table[self.count % self.steps, column] = time.perf_counter()

    def rows(self) -> np.ndarray:
        """A copy of the stamped rows, oldest first."""
        n = min(self.count, self.steps)
        start = self.count - n
        order = [(start + k) % self.steps for k in range(n)]
        return self.table[order].copy()

    def close(self) -> None:
        self.table = None
        self._shm.close()
        if self._owner:
            self._shm.unlink()


def summarize(rows: np.ndarray) -> dict:
    """Medians over the steps of ``rows`` (from :meth:`StepTrace.rows`), in microseconds:

    - ``step_us``: send to collect_end, the whole step as the parent sees it;
    - ``wake_us`` per sub-env: send to its wake (sub-env 0 in the parent wakes at once);
    - ``sim_us`` per sub-env: its wake to its sim_end;
    - ``collect_after_last_us``: the last sim_end to collect_end (the results' way back);
    - ``straggler_share`` per sub-env: how often it was the last to finish;
    - ``lockstep_wait_share``: the mean over sub-envs of the share of the step each spent not
      stepping (waiting to be woken, or done and waiting for the others).
    """
    n = (rows.shape[1] - 3) // 2
    used = [SEND, COLLECT_END, *range(3, rows.shape[1])]  # here_end: only with sub-env 0 in the parent
    rows = rows[~np.isnan(rows[:, used]).any(axis=1)]
    if not len(rows):
        return {"steps": 0}
    send, collect = rows[:, SEND], rows[:, COLLECT_END]
    wake, sim_end = rows[:, 3::2], rows[:, 4::2]
    step = collect - send
    last = sim_end.argmax(axis=1)
    busy = (sim_end - wake) / step[:, None]

    def us(x: np.ndarray) -> list[float] | float:
        m = np.median(x, axis=0) * 1e6
        return [round(float(v), 1) for v in m] if np.ndim(m) else round(float(m), 1)

    return {
        "steps": int(len(rows)),
        "step_us": us(step),
        "wake_us": us(wake - send[:, None]),
        "sim_us": us(sim_end - wake),
        "collect_after_last_us": us(collect - sim_end.max(axis=1)),
        "straggler_share": [round(float((last == i).mean()), 3) for i in range(n)],
        "lockstep_wait_share": round(float(1 - busy.mean()), 3),
    }
