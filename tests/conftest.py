"""Shared fixtures and the area markers (the shared helpers and doubles live in ``support/``): ManiSkill envs on the CPU
sim are costly to build (about 0.4 s), so module-scoped fixtures share them where a test allows;
every comparison seeds every reset."""

from __future__ import annotations

import multiprocessing
import sys
import warnings
from pathlib import Path

import pytest


def _set_up_test_process() -> None:
    """The set-up of a process that runs tests with the library in it: one whose collected test modules
    imported torch. Not in one whose tests only start subprocesses (the CUDA double's outer process,
    ``tests/upstream``'s, pytest-xdist's controller): about 7 s of CPU each, to import ManiSkill there."""
    if "torch" not in sys.modules:
        return
    import mani_skill.envs  # noqa: F401  (registers the tasks)
    import torch

    from maniskill_torchrl._internal.mp import preload_forkserver
    from maniskill_torchrl.engines.cpu_vector import WORKER_IMPORTS as CPU_ENGINE_IMPORTS
    from maniskill_torchrl.parallel import WORKER_IMPORTS as PARALLEL_IMPORTS

    # One intra-op thread in every test process: the suite runs in 2 pytest-xdist workers on 2 cores
    # beside the sim workers (one thread each, as the library's workers and the examples run), and
    # more threads only compete for the same cores. Every comparison runs its reference in the same
    # process.
    torch.set_num_threads(1)

    # Every worker process of the tests (the library's, TorchRL's ParallelEnv, collectors and
    # AsyncEnvPool, which start with the global method) forks from one forkserver that imported
    # torch, TorchRL and ManiSkill once: each spawned worker would import them again
    # (docs/guides/cpu_performance.md, "Worker start"). The start method itself is tested in
    # subprocesses (test_parallel.py, test_hang.py).
    multiprocessing.set_start_method("forkserver", force=True)
    preload_forkserver([*CPU_ENGINE_IMPORTS, *PARALLEL_IMPORTS])


warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")
warnings.filterwarnings("ignore", module="mani_skill")


_TESTS = Path(__file__).resolve().parent


# The files that take longest (seconds in one of `make test`'s or `make test-examples`'s 2 processes;
# RESULTS.md, "Tested versions"), run first: pytest-xdist hands out whole files in collection order
# (`--dist loadfile --no-loadscope-reorder`), so the short ones fill in at the end and both processes
# end together.
SLOW_FIRST = (
    "examples/test_examples.py",  # 75
    "examples/test_trainers.py",  # 70
    "examples/test_evaluate.py",  # 55
    "wrappers/test_wrappers.py",  # 71
    "envs/test_env.py",  # 63
    "engines/test_cpu_vector.py",  # 51
    "engines/test_async_edges.py",  # 20
    "engines/test_async_model.py",  # 35
    "data/test_demonstrations.py",  # 31
    "envs/test_unbatched_env.py",  # 31
    "testing/test_testing.py",  # 27
    "envs/test_async_collector.py",  # 22
    "transforms/test_env_states.py",  # 20
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Each test gets the marker of its area, the folder it is in (registered in pyproject.toml);
    the files of ``SLOW_FIRST`` come first, in its order (the others keep theirs)."""
    ranks = []
    for item in items:
        path = Path(item.fspath).resolve()
        parts = path.relative_to(_TESTS).parts if path.is_relative_to(_TESTS) else ()
        if len(parts) > 1 and parts[0] != "support":
            item.add_marker(parts[0])
        name = "/".join(parts)
        ranks.append(SLOW_FIRST.index(name) if name in SLOW_FIRST else len(SLOW_FIRST))
    # sorted() is stable: each file's tests, and the other files, keep their order
    items[:] = [item for _, item in sorted(zip(ranks, items), key=lambda pair: pair[0])]


def pytest_collection_finish(session: pytest.Session) -> None:
    """The process's set-up (:func:`_set_up_test_process`); then each test module with a selected
    test that defines ``start_early()`` gets it called once, right after collection (not with
    ``--collect-only``): ``test_hang.py`` starts its script of several processes there, which then
    runs beside the tests before it instead of after them. Under pytest-xdist every worker calls
    it, and ``test_hang.start_early`` starts its script in the first worker only (once per test run)."""
    if session.config.option.collectonly:
        return
    _set_up_test_process()
    started = set()
    for item in session.items:
        module = getattr(item, "module", None)
        if module is not None and module not in started and hasattr(module, "start_early"):
            started.add(module)
            module.start_early()


_RENDERER: list = []  # the render system held for the session, once a test has made one


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """Keeps SAPIEN's render engine alive in this process once a test has created one.

    SAPIEN frees its engine when the last ManiSkill env that renders is freed (module fixtures
    close theirs at teardown), and the next env's first picture builds it again: about 6 s (11
    CPU-s) of Mesa's lavapipe computing SAPIEN's BRDF lookup table, in every test that renders
    after one whose envs were freed. Held right after the body of the first test that loaded the
    Vulkan driver, before its fixtures free its envs, so that the engine it built, table and all,
    stays (never earlier: the fork guards and ``test_vulkan_loaded_after_a_maniskill_env`` see
    this process as the tests made it); on the CPU render device only (the one ManiSkill falls
    back to without CUDA; SAPIEN renders on one device per process). The pictures are the same:
    only the engine's start-up is skipped.
    """
    yield
    if _RENDERER:
        return
    from maniskill_torchrl._internal.mp import vulkan_loaded

    if not vulkan_loaded():
        return
    import sapien

    # Asked of SAPIEN itself, as ManiSkill's default render backend asks: a machine whose SAPIEN
    # renders on CUDA (even where torch sees no CUDA) must not hold a CPU renderer. Not the library's
    # `_no_cuda_render_device`, which the CUDA double replaces while its envs render on the CPU.
    try:
        sapien.Device("cuda")
        return
    except RuntimeError:
        pass
    try:
        _RENDERER.append(sapien.render.RenderSystem(sapien.Device("cpu")))
    except Exception:  # noqa: BLE001 - a speed-up only: without it the tests run as before
        _RENDERER.append(None)
