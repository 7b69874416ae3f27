"""Helpers shared by the test files (imported as ``helpers``; pytest puts ``tests/`` on the path).

- making ManiSkill envs and reproducible actions: :func:`make_gym_env`, :func:`random_actions`;
  closing many at once: :func:`close_envs`; demonstration files: :func:`record_episodes`; seeded
  rollouts: :func:`seeded_rollout`;
- comparing bit for bit: :func:`assert_same`, :func:`bits`, :func:`clone_tree`, :func:`tensor_infos`;
- running what users run as subprocesses: :func:`run`, :func:`start` (to wait later),
  :data:`ROOT`, :data:`EXAMPLES`, :data:`TIMEOUT_S`;
- running one test alone in a new process where it would otherwise mix render devices in this
  one: :func:`alone_where_cuda`.
"""

from __future__ import annotations

import gc
import os
import signal
import struct
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from unittest import mock

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDictBase

from maniskill_torchrl.testing import assert_tensordict_equal

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
TIMEOUT_S = 300  # a hung worker fails the test instead of the session


# ----------------------------------------------------------------------------- envs
def make_gym_env(env_id: str = "PickCube-v1", **kwargs) -> gym.Env:
    """A single CPU ManiSkill env made as users make it."""
    import mani_skill.envs  # noqa: F401  (registers the tasks)

    kwargs.setdefault("num_envs", 1)
    return gym.make(env_id, **kwargs)


def seeded_rollout(env: Any, steps: int, seed: int) -> TensorDictBase:
    """``env.rollout(steps)`` through dones, with the env and torch seeded by ``seed`` (the random
    actions too); closes ``env``. Two envs that must agree give equal rollouts."""
    env.set_seed(seed)
    torch.manual_seed(seed)
    try:
        return env.rollout(steps, break_when_any_done=False)
    finally:
        env.close()


@pytest.fixture(name="envs")
def closed_after_test():
    """A list the test appends the envs it makes to, closed (:func:`close_envs`) after it; a test
    module takes it with ``from helpers import closed_after_test``."""
    made: list = []
    yield made
    close_envs(made)


def close_envs(envs: Iterable[Any]) -> None:
    """Closes ``envs`` (module teardown), then runs one garbage collection.

    ManiSkill's ``close()`` runs ``gc.collect()`` (about 0.5 s each with this many objects alive):
    one collection after closing them all does the same job. A failing close is ignored:
    teardown must not mask test results."""
    with mock.patch.object(gc, "collect", lambda *args, **kwargs: 0):
        for env in envs:
            try:
                env.close()
            except Exception:  # noqa: BLE001
                pass
    gc.collect()


def random_actions(space: gym.Space, n: int, seed: int = 0) -> list:
    """``n`` reproducible actions (torch tensors, or dicts of them) for an unbatched action space."""
    g = torch.Generator().manual_seed(seed)

    def one(sp):
        if isinstance(sp, gym.spaces.Dict):
            return {k: one(v) for k, v in sp.spaces.items()}
        low = torch.as_tensor(sp.low, dtype=torch.float32)
        high = torch.as_tensor(sp.high, dtype=torch.float32)
        return low + (high - low) * torch.rand(sp.shape, generator=g)

    return [one(space) for _ in range(n)]


def record_episodes(
    env: gym.Env,
    out: Path,
    seeds: Sequence[int],
    lengths: int | Sequence[int],
    *,
    action_seeds: Sequence[int] | None = None,
    name: str = "demo",
) -> Path:
    """Records seeded episodes of random actions with ManiSkill's ``RecordEpisode`` into ``out``
    and returns the ``.h5`` path (tests make their own demonstrations: nothing can be downloaded).

    Episode ``i`` resets ``env`` with ``seeds[i]`` and takes ``lengths[i]`` actions (``lengths`` if
    an int) from :func:`random_actions` with ``action_seeds[i]`` (default: the reset seed). Closes
    ``env``, which writes the file."""
    from mani_skill.utils.wrappers import RecordEpisode

    lengths = [lengths] * len(seeds) if isinstance(lengths, int) else list(lengths)
    action_seeds = list(seeds) if action_seeds is None else list(action_seeds)
    rec = RecordEpisode(env, output_dir=str(out), trajectory_name=name, save_video=False, record_reward=True)
    try:
        for seed, n, action_seed in zip(seeds, lengths, action_seeds, strict=True):
            rec.reset(seed=seed)
            for action in random_actions(env.unwrapped.single_action_space, n, seed=action_seed):
                rec.step(action.unsqueeze(0))
    finally:
        rec.close()
    return out / f"{name}.h5"


# ----------------------------------------------------------------------------- data
def bits(x: Any, dtype: Any = None) -> bytes:
    """The bytes of ``x`` as a numpy array (of ``dtype`` if given): equal bytes, equal bits."""
    return np.asarray(x, dtype=dtype).tobytes()


def clone_tree(x: Any) -> Any:
    """``x`` with every tensor cloned, through dicts, tuples and lists."""
    if isinstance(x, torch.Tensor):
        return x.clone()
    if isinstance(x, dict):
        return {k: clone_tree(v) for k, v in x.items()}
    if isinstance(x, (tuple, list)):
        return type(x)(clone_tree(v) for v in x)
    return x


def tensor_infos(info: dict) -> dict:
    return {k: v for k, v in info.items() if isinstance(v, torch.Tensor)}


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    if a.dtype.kind in "fc":
        itemsize = a.dtype.itemsize // (2 if a.dtype.kind == "c" else 1)
        view = {2: np.uint16, 4: np.uint32, 8: np.uint64, 16: np.uint64}[itemsize]
        return np.array_equal(np.ascontiguousarray(a).view(view), np.ascontiguousarray(b).view(view))
    return np.array_equal(a, b)


def _tensor_diff(got: torch.Tensor, want: torch.Tensor, what: str) -> str:
    """How many envs (first dim) differ, and the first of them."""
    diff = got != want
    if diff.ndim > 1:
        diff = diff.reshape(diff.shape[0], -1).any(-1)
    envs = diff.nonzero().reshape(-1).tolist()
    i = envs[0] if envs else 0
    return (
        f"{what}: values differ in {len(envs)} of {got.shape[0] if got.ndim else 1} envs, "
        f"first env {i}:\n got  {got[i] if got.ndim else got}\n want {want[i] if want.ndim else want}"
    )


def assert_same(a: Any, b: Any, what: str = "out") -> None:
    """``a`` and ``b`` are the same: python types at every level, dict key order, dtypes, shapes,
    devices and bits (tensors on any device; a difference names the envs, first dim, that differ);
    TensorDicts with the library's public ``assert_tensordict_equal``."""
    assert type(a) is type(b), f"{what}: {type(a).__name__} vs {type(b).__name__}"
    if isinstance(a, TensorDictBase):
        assert_tensordict_equal(a, b, msg=what)
    elif isinstance(a, dict):
        assert list(a) == list(b), f"{what}: keys {list(a)} vs {list(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{what}[{k!r}]")
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b), f"{what}: len {len(a)} vs {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{what}[{i}]")
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype, f"{what}: dtype {a.dtype} != {b.dtype}"
        assert a.shape == b.shape, f"{what}: shape {tuple(a.shape)} != {tuple(b.shape)}"
        assert a.device == b.device, f"{what}: device {a.device} != {b.device}"
        if not _same_bits(a.detach().cpu().numpy(), b.detach().cpu().numpy()):
            raise AssertionError(_tensor_diff(a, b, what))
    elif isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), f"{what}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"
        if a.dtype == object:
            for i, (x, y) in enumerate(zip(a.ravel(), b.ravel())):
                assert_same(x, y, f"{what}.flat[{i}]")
        else:
            assert _same_bits(a, b), f"{what}: {a} vs {b}"
    elif isinstance(a, np.generic):
        assert a.dtype == b.dtype and _same_bits(np.asarray(a), np.asarray(b)), f"{what}: {a!r} vs {b!r}"
    elif isinstance(a, float):
        assert struct.pack("<d", a) == struct.pack("<d", b), f"{what}: {a!r} vs {b!r}"
    else:
        assert a == b, f"{what}: {a!r} vs {b!r}"


# ----------------------------------------------------------------------------- subprocesses
def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """Runs ``cmd`` like a user would; a failure shows its output."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    _check(proc)
    return proc


def _check(proc: subprocess.CompletedProcess) -> None:
    assert proc.returncode == 0, (
        f"{' '.join(map(str, proc.args))} exited with {proc.returncode}\n"
        f"--- stdout ---\n{proc.stdout[-4000:]}\n--- stderr ---\n{proc.stderr[-4000:]}"
    )


class Started:
    """A command started by :func:`start`; :meth:`result` waits for it and checks it as :func:`run` does.

    Its output goes to temporary files, not pipes: nothing blocks while no one reads."""

    def __init__(self, cmd: list[str], cwd: Path) -> None:
        self.args = [str(c) for c in cmd]
        self._out = tempfile.TemporaryFile("w+")
        self._err = tempfile.TemporaryFile("w+")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self._proc = subprocess.Popen(self.args, cwd=cwd, env=env, stdout=self._out, stderr=self._err, text=True)

    def running(self) -> bool:
        return self._proc.poll() is None

    def result(self, check: bool = True) -> subprocess.CompletedProcess:
        """Waits for the command (:data:`TIMEOUT_S` at most); ``check``: a non-zero exit fails."""
        try:
            self._proc.wait(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.kill()
            raise
        out, err = self._out, self._err
        out.seek(0)
        err.seek(0)
        proc = subprocess.CompletedProcess(self.args, self._proc.returncode, out.read(), err.read())
        if check:
            _check(proc)
        return proc

    def kill(self) -> None:
        """Stops the command if it still runs (a test that did not wait for it)."""
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._out.close()
        self._err.close()


def start(cmd: list[str], cwd: Path) -> Started:
    """Starts ``cmd`` like a user would, without waiting: ``start(...).result()`` is ``run(...)``."""
    return Started(cmd, cwd)


OWN_PROCESS = "MANISKILL_TORCHRL_TEST_OWN_PROCESS"  # set in a test's own process (alone_where_cuda)


def alone_where_cuda(request: Any) -> bool:
    """For a test that renders with ``render_backend="cpu"``: on a machine where SAPIEN finds a CUDA
    device, the other tests' envs render there (ManiSkill's default, ``"gpu"``) and SAPIEN renders
    on one device per process, so this runs the test alone in a new pytest process and returns
    True: the caller then returns (the new process passed). False where SAPIEN finds no CUDA
    device (the CPU is every env's render device), or in that new process: the caller runs the
    test itself.

    Call it first, before any fixture or env of the test makes a ManiSkill env (it asks SAPIEN
    for a CUDA device, as the library does before its first env: that loads Vulkan)."""
    from maniskill_torchrl._internal.rendering import _no_cuda_render_device

    if os.environ.get(OWN_PROCESS) == "1" or _no_cuda_render_device():
        return False
    env = dict(os.environ, **{OWN_PROCESS: "1", "PYTHONUNBUFFERED": "1"})
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", request.node.nodeid]
    proc = subprocess.run(cmd, cwd=request.config.rootpath, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    _check(proc)
    assert "1 passed" in proc.stdout, proc.stdout[-3000:]
    return True


class ReadHung(Exception):
    """A read that did not return (not an OSError: the engine takes those for a dead worker)."""


# Where the engine's pipes are read and written, and its bookkeeping kept: the files :func:`ctrl_c_at_line` counts.
ENGINE_FILES = (
    "maniskill_torchrl/engines/cpu_vector.py",
    "maniskill_torchrl/engines/_pool.py",
    "maniskill_torchrl/engines/_interrupts.py",
    "multiprocessing/connection.py",
)


@contextmanager
def ctrl_c_at_line(line: int, files: Sequence[str] = ENGINE_FILES) -> Iterator[list[int]]:
    """SIGINT raised at the ``line``-th line run (1 the first) in a module whose file ends with one of ``files``
    (this thread's lines), as a terminal's Ctrl-C lands: between two bytecodes, the handler at once (Python's
    default one, set for the block: ``KeyboardInterrupt`` at that line, unless the engine holds it). Yields a
    one-item list, the lines counted so far. ``line=0``: none raised (to count a call's lines)."""
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers are the main thread's")
    counted = [0]
    ends = tuple(files)

    def local(frame: Any, event: str, arg: Any) -> Any:
        if event == "line":
            counted[0] += 1
            if counted[0] == line:
                signal.raise_signal(signal.SIGINT)  # runs the handler before it returns
        return local

    def calls(frame: Any, event: str, arg: Any) -> Any:
        return local if frame.f_code.co_filename.endswith(ends) else None

    old, tracer = signal.signal(signal.SIGINT, signal.default_int_handler), sys.gettrace()
    sys.settrace(calls)
    try:
        yield counted
    finally:
        sys.settrace(tracer)
        signal.signal(signal.SIGINT, old)


@contextmanager
def no_hang(seconds: float = 20.0, what: str = "a read after Ctrl-C hangs: a message was cut in two") -> Iterator[None]:
    """The block is cut by SIGALRM after ``seconds`` (:class:`ReadHung`): a hang fails the test, never blocks it."""

    def hung(signum: int, frame: Any) -> None:
        raise ReadHung(what)

    old = signal.signal(signal.SIGALRM, hung)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@contextmanager
def ctrl_c_after_a_length(pipe: Any, monkeypatch: pytest.MonkeyPatch) -> Iterator[list[int]]:
    """SIGINT raised inside ``pipe.recv_bytes()``, right after a message's 4-byte length and before its body
    (where a terminal's Ctrl-C can land), once; yields the sizes ``Connection._recv`` read. Python's default
    SIGINT handler is set for the block; a read that hangs is cut by SIGALRM after 20 s (:class:`ReadHung`)."""
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signal handlers are the main thread's")
    reads: list[int] = []
    real = pipe._recv

    def recv(size: int, read: Any = None) -> Any:
        out = real(size)
        reads.append(size)
        if len(reads) == 1:
            signal.raise_signal(signal.SIGINT)
        return out

    monkeypatch.setattr(pipe, "_recv", recv, raising=False)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with no_hang():
            yield reads
    finally:
        signal.signal(signal.SIGINT, old)
        monkeypatch.setattr(pipe, "_recv", real, raising=False)


def terminal_sigint() -> None:
    """``preexec_fn`` of a process a test will Ctrl-C: SIGINT at its default, as a terminal starts a process.
    A script's background job (``cmd &`` with no job control, as a CI runner or a shell script may start the
    suite) inherits SIGINT ignored, and Python then never raises ``KeyboardInterrupt``: the test's Ctrl-C
    would reach nothing, and the test would fail for a reason of the runner's."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
