"""Ctrl-C, SIGTERM and progress lines, shared by the training examples.

- :func:`interruptible`: inside it, SIGTERM raises :class:`Terminated`, a ``KeyboardInterrupt``, as Ctrl-C
  (SIGINT) raises ``KeyboardInterrupt``. The library's CPU engine settles its workers on a
  ``KeyboardInterrupt`` (they ignore SIGINT and finish their call), so an example catches either in its
  loop, keeps the run so far (checkpoint, metrics), closes its envs and collector (their shared memory and
  semaphores: nothing leaks) and exits with the conventional status, :func:`exit_status`: 130 after
  SIGINT, 143 after SIGTERM.
- :class:`Progress`: a line at most every ``every_s`` seconds with frames, frames/s and the last
  finished episodes' mean return, for loops whose own lines are minutes apart.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import time
from collections.abc import Iterator

__all__ = ["Progress", "Terminated", "exit_status", "interruptible", "said", "uninterrupted"]


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread where it arrives."""


def _on_sigterm(signum, frame):
    raise Terminated()


@contextlib.contextmanager
def interruptible() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` inside the block (restored after it)."""
    old = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


@contextlib.contextmanager
def uninterrupted() -> Iterator[None]:
    """SIGINT and SIGTERM wait until the block ends: a checkpoint being written is never cut short, and an
    update is not interrupted inside TorchRL's functional calls (a KeyboardInterrupt raised there comes out
    of tensordict's ``to_module`` as a ``RuntimeError``)."""
    pending: list[int] = []
    old = {s: signal.signal(s, lambda signum, frame: pending.append(signum)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        if pending:
            raise Terminated() if pending[0] == signal.SIGTERM else KeyboardInterrupt()


def exit_status(err: BaseException | None) -> int:
    """0 without ``err``; 143 after SIGTERM, 130 after SIGINT (128 + the signal's number)."""
    if err is None:
        return 0
    return 128 + (signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT)


def said(err: BaseException) -> str:
    """``"SIGTERM"`` or ``"Ctrl-C"``, for the line that says the run stopped."""
    return "SIGTERM" if isinstance(err, Terminated) else "Ctrl-C"


class Progress:
    """``update(frames, last_return)`` prints ``frames ... f/s ... last return ...`` at most every ``every_s``."""

    def __init__(self, every_s: float = 15.0, total: int | None = None, prefix: str = "") -> None:
        self.every_s, self.total, self.prefix = every_s, total, prefix
        self.t0 = self.last = time.perf_counter()

    def update(self, frames: int, last_return: float | None = None, **extra: object) -> None:
        now = time.perf_counter()
        if self.every_s < 0 or now - self.last < self.every_s:
            return
        self.last = now
        of = f"/{self.total}" if self.total else ""
        ret = f"  last return {last_return:.2f}" if last_return is not None else ""
        more = "".join(f"  {k} {v}" for k, v in extra.items())
        print(f"{self.prefix}frames {frames}{of}  {frames / (now - self.t0):.1f} f/s{ret}{more}", flush=True)
        sys.stdout.flush()
