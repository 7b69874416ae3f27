"""Ctrl-C held off the few lines where the parent's view of its workers must not be cut in two.

A terminal's Ctrl-C reaches every process of its group. The workers ignore it (``_worker.serve``); in the
parent, Python raises ``KeyboardInterrupt`` between any two bytecodes. Between reading a worker's answer and
noting it read, or between waking a worker and noting it woken, that leaves the pipes and the engine's
bookkeeping out of step: a ``Connection.recv_bytes`` cut after the 4-byte length of a message leaves its
body in the pipe, and the next read takes that body for a length and waits forever for bytes no worker
sends (a drain after Ctrl-C that never returns). ``with HELD:`` holds SIGINT over such a block and hands it
to the handler that was there (``KeyboardInterrupt``'s default one, or the user's) when the block ends.

A block never spans a wait: the waits for workers (a select, a poll) stay open to Ctrl-C, and a block only
reads answers a wait found in the pipe, or sends. A held Ctrl-C therefore comes within microseconds; one
held over a wait came only when a worker answered, and under load the Ctrl-C example tests hung on it
(issue 59; eb839ab reverted that design). A second Ctrl-C in a block goes through at once all the same.

Nothing lighter holds it: ``pthread_sigmask`` blocks SIGINT in the calling thread only, and the kernel then
hands it to another thread of the process (torch's, a collector's), whose C handler still asks the main
thread to run the Python one at its next bytecode; and no read written in Python is whole under a
``KeyboardInterrupt`` (one may come between ``os.read`` returning and its bytes being kept). The hold costs
two ``signal`` calls of the C module per outermost block (no ``Enum`` conversion); a block inside another
costs a counter.
"""

from __future__ import annotations

import _signal
import threading
from _thread import get_ident
from typing import Any

__all__ = ["HELD"]

_SIGINT = _signal.SIGINT
_getsignal, _setsignal = _signal.getsignal, _signal.signal
_MAIN = threading.main_thread().ident


class _Held:
    """``with HELD: ...``: a SIGINT during the block is handled when the outermost block ends; a second one
    at once. Only in the main thread (Python runs signal handlers there only; elsewhere a block does
    nothing) and only over a Python handler (with ``SIG_IGN`` or ``SIG_DFL`` nothing changes). The handler
    that was there is called as it would have been, once, after the block."""

    __slots__ = ("_depth", "_old", "_caught", "_handler")

    def __init__(self) -> None:
        self._depth = 0  # blocks open in the main thread
        self._old: Any = None  # the handler held off, while the outermost block is open
        self._caught: tuple | None = None  # (signum, frame) of a Ctrl-C during the block
        self._handler = self._hold  # one bound method, installed and compared as is

    def __enter__(self) -> None:
        if get_ident() != _MAIN:
            return
        if not self._depth:  # counted once held: a Ctrl-C before the swap leaves no block counted open
            old = _getsignal(_SIGINT)
            if callable(old) and old is not self._handler:
                _setsignal(_SIGINT, self._handler)
                self._old = old
        self._depth += 1

    def _hold(self, signum: int, frame: Any) -> None:
        old = self._old
        if self._caught is None or old is None:  # the first: at the end of the block
            self._caught = (signum, frame)
            return
        self._old = self._caught = None  # a second: at once, and the block holds nothing more
        _setsignal(_SIGINT, old)
        old(signum, frame)

    def __exit__(self, *exc: Any) -> None:
        if get_ident() != _MAIN:
            return
        self._depth -= 1
        if self._depth:
            return
        old = self._old
        if old is None:
            self._caught = None
            return
        self._old = None
        _setsignal(_SIGINT, old)
        caught = self._caught
        if caught is not None:
            self._caught = None
            old(*caught)


#: The process's one hold (it is the main thread's).
HELD = _Held()
