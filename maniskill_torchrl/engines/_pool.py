"""The worker processes of :class:`~maniskill_torchrl.CPUVectorEnv`, seen from the parent: start
them, wake them for a step, send them the rarer calls, collect their answers, and, when one
fails, say which and stop them all (the others would wait forever for a sub-env that is gone).

One duplex pipe per worker; the worker's loop (``_worker.serve``, given as ``target``) is the
other end. A step is one byte each way (``_protocol.py``); the data lies in the shared
block (``_shared.py``). Like ``cpu_vector.py``, this module imports neither TorchRL nor the rest
of the library.
"""

from __future__ import annotations

import multiprocessing
import pickle
import selectors
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from maniskill_torchrl.engines._interrupts import HELD
from maniskill_torchrl.engines._protocol import DONE, STEP, STEP_RESET

__all__ = ["DONE", "STEP", "STEP_RESET", "WorkerFailure", "WorkerPool"]


class WorkerFailure(Exception):
    """A worker raised or died. ``what`` says which and how, ``where`` where to look;
    ``error`` is the worker's own exception where it could be sent."""

    def __init__(self, what: str, where: str, error: BaseException | None = None) -> None:
        super().__init__(what)
        self.what, self.where, self.error = what, where, error


class WorkerPool:
    """Worker processes for the sub-envs ``makers[i].index``, started at once (each runs
    ``target(pipe, makers[i])``, which makes its env while the parent goes on); :meth:`ready`
    waits for them."""

    def __init__(self, target: Callable[[Any, Any], None], makers: list[Any], context: str) -> None:
        ctx = multiprocessing.get_context(context)
        self.indices = [make.index for make in makers]
        self.processes: list = []
        self.pipes: list = []
        for make in makers:
            mine, theirs = ctx.Pipe(duplex=True)
            process = ctx.Process(target=target, args=(theirs, make), name=f"CPUVectorEnv-{make.index}", daemon=True)
            self.processes.append(process)
            self.pipes.append(mine)
            process.start()
            theirs.close()  # the worker's end lives in the worker only: its death closes the pipe
        # One selector over every pipe, registered once (split phase): a wait is one epoll call, where
        # multiprocessing.connection.wait registers each pipe again on every call.
        self._selector = selectors.DefaultSelector()
        for i, pipe in enumerate(self.pipes):
            self._selector.register(pipe, selectors.EVENT_READ, i)
        self.closed = False
        #: the workers that owe an answer: set with each message sent, cleared with each answer read, both
        #: with Ctrl-C held, so it is exact wherever a KeyboardInterrupt lands; :meth:`catch_up` reads the
        #: answers a call cut by Ctrl-C left owed
        self.owed = np.zeros(len(self.pipes), dtype=np.bool_)
        #: seconds spent waiting in :meth:`readable` (the split phase's idle time in the parent)
        self.waited = 0.0

    def ready(self) -> list[tuple]:
        """Each worker's ``(result space, action space, render mode)``, once it has made its env."""
        return [self._answer(i) for i in range(len(self.pipes))]

    def attach(self, layout: Any, name: str) -> None:
        """Every worker maps the shared block ``name`` laid out as ``layout``."""
        self.send_all("attach", layout, name)
        self.collect_all()

    # ------------------------------------------------------------- a step
    def wake(self) -> None:
        """Every worker steps with its row of the block's actions."""
        with HELD:
            for pipe in self.pipes:
                pipe.send_bytes(STEP)
            self.owed[:] = True

    def wait(self) -> None:
        """Returns once every worker has written its step (interrupted: as :meth:`_gather`)."""
        for i, answer in self._gather(range(len(self.pipes))).items():
            if answer != DONE:
                self._raise(i, answer)

    # ------------------------------------------------------------- split phase
    def wake_some(self, positions: list[int], message: bytes) -> None:
        """The workers at ``positions`` get ``message`` (:data:`STEP` or :data:`STEP_RESET`)."""
        pipes, owed = self.pipes, self.owed
        with HELD:
            for i in positions:
                pipes[i].send_bytes(message)
                owed[i] = True

    def readable(self, timeout: float | None) -> list[int]:
        """The positions whose worker has an answer to read (waits up to ``timeout`` s for one;
        None: until one has; 0: a poll)."""
        start = time.perf_counter()
        ready = [key.data for key, _ in self._selector.select(timeout)]
        self.waited += time.perf_counter() - start
        return ready

    def take_done(self, i: int) -> None:
        """Worker ``i``'s answer to a step (in its pipe already): :data:`DONE`, or its failure raised."""
        with HELD:
            answer = self.pipes[i].recv_bytes()
            self.owed[i] = False
        if answer != DONE:
            self._raise(i, answer)

    def take_answer(self, i: int) -> Any:
        """Worker ``i``'s answer to a pickled command (in its pipe already): its value, or its failure raised."""
        with HELD:
            answer = self.pipes[i].recv_bytes()
            self.owed[i] = False
        return self._value(i, answer)

    # ------------------------------------------------------------- other calls
    def send(self, i: int, command: str, *args: Any, **kwargs: Any) -> None:
        """``command`` to worker ``i`` (its position here, not its sub-env index)."""
        message = pickle.dumps((command, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
        with HELD:
            self.pipes[i].send_bytes(message)
            self.owed[i] = True

    def send_all(self, command: str, *args: Any, **kwargs: Any) -> None:
        message = pickle.dumps((command, args, kwargs), protocol=pickle.HIGHEST_PROTOCOL)
        with HELD:
            for pipe in self.pipes:
                pipe.send_bytes(message)
            self.owed[:] = True

    def collect(self, positions: list[int]) -> list:
        """The answers of the workers at ``positions``, in that order (interrupted: as :meth:`_gather`)."""
        answers = self._gather(positions)
        return [self._value(i, answers[i]) for i in positions]

    def _gather(self, positions: Any) -> dict[int, bytes]:
        """The next message of each worker at ``positions``, each read whole: the wait stays open to
        Ctrl-C and cuts nothing, and the answers it found are read with Ctrl-C held (``_interrupts.py``).
        A ``KeyboardInterrupt`` leaves the answers still owed in :attr:`owed`, for :meth:`catch_up`."""
        left = dict.fromkeys(positions)
        got: dict[int, bytes] = {}
        pipes, owed, select = self.pipes, self.owed, self._selector.select
        while left:
            ready = [key.data for key, _ in select(None)]
            with HELD:
                for i in ready:
                    if i not in left:  # not asked: a worker that died (EOFError, read), or one out of step
                        pipes[i].recv_bytes()
                        raise WorkerFailure(
                            f"the worker of sub-env {self.indices[i]} sent an answer nobody waits for",
                            "the engine is out of step with its workers (a bug: please report it)",
                        )
                    got[i] = pipes[i].recv_bytes()
                    owed[i] = False
                    del left[i]
        return got

    def catch_up(self) -> None:
        """Reads and drops the answers still owed, left by a call that Ctrl-C cut short (the workers
        ignore SIGINT and finish their call)."""
        owed = np.flatnonzero(self.owed).tolist()
        if owed:
            self._gather(owed)

    def collect_all(self) -> list:
        return self.collect(list(range(len(self.pipes))))

    def _answer(self, i: int) -> Any:  # a message no call asked for: the worker's first
        return self._value(i, self.pipes[i].recv_bytes())

    def _value(self, i: int, answer: bytes) -> Any:
        status, *value = pickle.loads(answer)
        if status == "error":
            self._raise(i, answer)
        return value[0] if len(value) == 1 else tuple(value)

    def _raise(self, i: int, answer: bytes) -> None:
        _, error, name, message = pickle.loads(answer)
        raise WorkerFailure(
            f"worker(s) of sub-env(s) [{self.indices[i]}] raised {name}: {message}",
            "the worker's traceback is printed above",
            error,
        )

    # ------------------------------------------------------------- failures and the end
    def describe(self, err: BaseException) -> WorkerFailure:
        """What ``err`` (from a pipe) means: a worker that died, or a message that could not be sent."""
        if isinstance(err, WorkerFailure):
            return err
        dead = [index for index, p in zip(self.indices, self.processes) if not p.is_alive()]
        if not dead and isinstance(err, (EOFError, OSError)):  # a worker that closed its pipe is exiting
            for process in self.processes:
                process.join(0.5)
            dead = [index for index, p in zip(self.indices, self.processes) if not p.is_alive()]
        if dead:
            return WorkerFailure(
                f"worker(s) of sub-env(s) {dead} died",
                "look for the worker's own error above (a crash in the simulator, or out of memory)",
            )
        return WorkerFailure(
            f"sending to the workers failed ({type(err).__name__}: {err})",
            "what was sent could not be pickled to the workers",
        )

    def _close_selector(self) -> None:
        if self._selector is not None:
            self._selector.close()
            self._selector = None

    def kill(self, positions: list[int]) -> None:
        """SIGKILLs the workers at ``positions`` (stuck ones: a stopped process cannot act on SIGTERM)."""
        for i in positions:
            if self.processes[i].is_alive():
                self.processes[i].kill()

    def stop(self) -> None:
        """Terminates every live worker and closes the pipes (after a failure)."""
        self.closed = True
        self._close_selector()
        for process in self.processes:
            if process.is_alive():
                process.terminate()
        for pipe in self.pipes:
            pipe.close()
        for process in self.processes:
            process.join(5)
            if process.is_alive():  # stopped, or deaf to SIGTERM: SIGKILL ends it whatever its state
                process.kill()
                process.join(5)

    def close(self, timeout: float = 5.0) -> None:
        """Asks every worker to close its env, waits for them, and stops what is left."""
        if self.closed:
            return
        self.closed = True
        for pipe in self.pipes:
            try:
                pipe.send_bytes(pickle.dumps(("close", (), {})))
            except (OSError, EOFError):
                pass
        for pipe in self.pipes:
            try:
                if pipe.poll(timeout):
                    pipe.recv_bytes()
            except (OSError, EOFError):
                pass
        for process in self.processes:
            process.join(timeout)
        self.stop()
