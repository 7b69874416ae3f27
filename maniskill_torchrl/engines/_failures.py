"""What :class:`~maniskill_torchrl.CPUVectorEnv` does when its workers fail: say which
worker died or raised (or that sending to them failed), and stop them all, since the others
would wait forever for a sub-env that is gone.

Like ``cpu_vector.py``, this module imports neither TorchRL nor the rest of the library.
"""

from __future__ import annotations

from gymnasium.vector import AsyncVectorEnv

__all__ = ["describe_failure", "stop_workers"]


def describe_failure(vec: AsyncVectorEnv, first: int, err: BaseException) -> tuple[str, str]:
    """(what happened, where to look) after ``err`` from a call on ``vec``, whose worker ``i``
    serves sub-env ``i + first``. gymnasium shuts a worker down after re-raising its exception
    (its pipe is then None); a worker that crashed is no longer alive."""
    failed = [i + first for i, pipe in enumerate(vec.parent_pipes) if pipe is None]
    if failed:
        return f"worker(s) of sub-env(s) {failed} raised {type(err).__name__}: {err}", (
            "the worker's traceback is printed above"
        )
    dead = [i + first for i, p in enumerate(vec.processes) if not p.is_alive()]
    if dead:
        return f"worker(s) of sub-env(s) {dead} died", (
            "look for the worker's own error above (a crash in the simulator, or out of memory)"
        )
    return f"sending to the workers failed ({type(err).__name__}: {err})", (
        "what was sent could not be pickled to the workers"
    )


def stop_workers(vec: AsyncVectorEnv) -> None:
    """Terminates every live worker of ``vec``, closes the pipes left and marks it closed."""
    vec.closed = True
    for process in vec.processes:
        if process.is_alive():
            process.terminate()
    for pipe in vec.parent_pipes:
        if pipe is not None:
            pipe.close()
    for process in vec.processes:
        process.join(5)
