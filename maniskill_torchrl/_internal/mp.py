"""Process start-up facts for ManiSkill under multiprocessing (no TorchRL import: the gym shim may use it).

Two facts, measured with ManiSkill 3.0.1 / SAPIEN 3 on Mesa lavapipe:

- A process forked from a parent that has created a SAPIEN renderer (any ManiSkill env,
  even one already closed) deadlocks when it builds or frees a SAPIEN scene: the Vulkan
  driver's threads do not survive ``fork`` and the child waits forever on a condition
  variable (``svulkan2::core::Context::~Context`` -> ``pthread_cond_wait``). Importing
  ``mani_skill`` / ``sapien`` alone is harmless; the renderer is what loads the Vulkan
  loader (``libvulkan.so.1``) and driver into the process, which :func:`vulkan_loaded`
  detects.
- CPython pins the global start method to the platform default (``"fork"`` on Linux before
  Python 3.14) the first time any process is started, whatever context started it:
  ``multiprocessing.spawn.get_preparation_data`` calls ``get_start_method()``, which fixes
  the default context. So ``gymnasium.vector.AsyncVectorEnv(..., context="forkserver")``
  leaves ``multiprocessing.get_start_method() == "fork"`` behind, and TorchRL imported after
  that takes it for the user's choice (it only sets ``"spawn"`` when nothing is set), so its
  ``ParallelEnv`` forks: with a SAPIEN renderer in the parent (gymnasium's AsyncVectorEnv
  builds one env in the parent to read the spaces) the workers hang. The library does not set the
  global method (importing it changes no global state, as ManiSkill's own gym wrappers): its own
  workers name their context, and :func:`check_start_method` refuses ``fork`` after a renderer.

And one fact of cost: a worker's imports (torch, TorchRL, ManiSkill's tasks) are most of its
start. :func:`preload_forkserver` has the forkserver import them once; the workers forked from it
start without them.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Sequence

import numpy as np

__all__ = [
    "vulkan_loaded",
    "preload_forkserver",
    "FORK_AFTER_RENDERER",
    "check_start_method",
    "entropy_seed",
]

FORK_AFTER_RENDERER = (
    "This process has created a SAPIEN renderer (a ManiSkill env was built here), and processes "
    "forked from it deadlock when they build a ManiSkill env (SAPIEN's Vulkan driver threads do "
    "not survive fork). Start the workers with 'spawn' or 'forkserver': pass "
    "mp_start_method='spawn' to ParallelEnv, or call multiprocessing.set_start_method('spawn') "
    "at the top of your script, before anything starts a process. (Python fixes the global "
    "start method to 'fork' the first time any process starts, e.g. in gymnasium's "
    "AsyncVectorEnv(context='forkserver'); TorchRL imported after that uses 'fork'.)"
)


def vulkan_loaded() -> bool:
    """Whether the Vulkan loader is mapped into this process (SAPIEN loads it with its renderer).

    Linux only (reads ``/proc/self/maps``); ``False`` where that cannot be read.
    """
    try:
        with open("/proc/self/maps") as f:
            for line in f:
                name = line.rsplit("/", 1)[-1]
                if name.startswith("libvulkan.so") or name.startswith("libvulkan_"):
                    return True
    except OSError:
        return False
    return False


def check_start_method(method: str | None) -> None:
    """Raises ``RuntimeError`` (:data:`FORK_AFTER_RENDERER`) if ``method`` forks a process holding a SAPIEN renderer."""
    if method is None:
        method = mp.get_start_method(allow_none=True) or "spawn"  # TorchRL's default
    if method == "fork" and vulkan_loaded():
        raise RuntimeError(FORK_AFTER_RENDERER)


def preload_forkserver(modules: Sequence[str]) -> bool:
    """Adds ``modules`` to the preload list of ``multiprocessing``'s forkserver, if it is not running yet.

    Every later ``"forkserver"`` process of this process (the library's workers, TorchRL's
    ``ParallelEnv(mp_start_method="forkserver")``, gymnasium's ``AsyncVectorEnv(context="forkserver")``)
    is then forked from a server that has imported them. The modules already listed (the user's, or
    ``"__main__"``, the default) are kept. Importing ManiSkill does not load SAPIEN's renderer (see
    above), so the forked workers may build envs. A forkserver already running keeps the imports it
    has. Returns whether the forkserver will import every one of ``modules``.
    """
    from multiprocessing import forkserver

    server = forkserver._forkserver  # the process-wide server behind every "forkserver" context
    current = list(getattr(server, "_preload_modules", ["__main__"]))
    if getattr(server, "_forkserver_pid", None) is not None:
        return all(name in current for name in modules)
    missing = [name for name in modules if name not in current]
    if missing:
        mp.set_forkserver_preload(current + missing)
    return True


def entropy_seed() -> int:
    """A seed from the operating system's entropy, in ``[0, 2**31)``: the envs of processes forked
    from one process share its RNG state, and would otherwise draw alike."""
    return int(np.random.SeedSequence().entropy % 2**31)
