"""Ctrl-C held off the few lines where the parent's view of its workers must not be cut in two.

A terminal's Ctrl-C reaches every process of its group. The workers ignore it (``_worker.serve``); in the
parent, Python raises ``KeyboardInterrupt`` between any two bytecodes. Between reading a worker's answer and
noting it read, or between waking a worker and noting it woken, that leaves the pipes and the engine's
bookkeeping out of step: a ``Connection.recv_bytes`` cut after the 4-byte length of a message leaves its
body in the pipe, and the next read takes that body for a length and waits forever for bytes no worker
sends (a drain after Ctrl-C that never returns). :class:`HeldInterrupt` holds SIGINT over such a block and
raises it (the handler that was there runs) when the block ends. It is only used around work that does not
wait (the answers are in the pipe already) or waits for a worker's answer, which comes: a second Ctrl-C in
the same block goes through at once (a stuck worker must not make Ctrl-C deaf).
"""

from __future__ import annotations

# _signal: the C module behind ``signal``, the same calls without the Enum conversions of every handler,
# which cost ``signal.signal`` about 20 times its system call (this runs a few times per step of the engine).
import _signal
import threading
from typing import Any

__all__ = ["HeldInterrupt"]


class HeldInterrupt:
    """``with HeldInterrupt(): ...``: a SIGINT during the block is handled when it ends.

    Only in the main thread (Python runs signal handlers there only) and only over a Python handler
    (``KeyboardInterrupt``'s default one, or the user's); with ``SIG_IGN`` or ``SIG_DFL`` nothing changes.
    The user's handler is called as it would have been, once, after the block; a block inside another is
    the outer one's."""

    __slots__ = ("_old", "_caught")

    def __enter__(self) -> HeldInterrupt:
        self._old = self._caught = None
        if threading.current_thread() is threading.main_thread():
            old = _signal.getsignal(_signal.SIGINT)
            if callable(old) and not isinstance(getattr(old, "__self__", None), HeldInterrupt):  # not nested
                _signal.signal(_signal.SIGINT, self._hold)
                self._old = old
        return self

    def _hold(self, signum: int, frame: Any) -> None:
        if self._caught is not None:  # a second Ctrl-C: at once
            self._release()(signum, frame)
            return
        self._caught = (signum, frame)

    def _release(self) -> Any:
        old, self._old = self._old, None
        if old is not None:
            _signal.signal(_signal.SIGINT, old)
        return old

    def __exit__(self, *exc: Any) -> None:
        old = self._release()
        if old is not None and self._caught is not None:
            caught, self._caught = self._caught, None
            old(*caught)
