"""Process-alternation harness: contenders that must each start from a fresh interpreter.

For multi-process pipelines (their worker processes, start-up state and imported modules must
not leak from one contender into the next), :func:`alternate_processes` runs every round as one
child process per contender, in the rotating order of :func:`common.interleave`, and reads back
what each child measured (:func:`child_result` writes it). :func:`add_alternation_args` and
:func:`run_alternating` are the scripts' shared flags and call.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from benchmarks.common import Result
from benchmarks.machine import wait_for_quiet

__all__ = [
    "ProcessContender",
    "ProcessResult",
    "alternate_processes",
    "child_result",
    "child_ready",
    "RESULT_MARKER",
    "add_alternation_args",
    "run_alternating",
]

RESULT_MARKER = "@@bench-result "
READY_MARKER = "@@bench-ready"  # a child's start-up is over (imports, pipeline built, warmed up)
LAUNCH_ENV = "BENCH_LAUNCH_T"  # the parent's time.time() when it launched the child


def child_ready() -> float | None:
    """Tells the parent that this child's start-up is over; returns its start-up in seconds (from the
    parent's launch), or None when not launched by :func:`alternate_processes`."""
    sys.stdout.write(READY_MARKER + "\n")
    sys.stdout.flush()
    launch = os.environ.get(LAUNCH_ENV)
    return round(time.time() - float(launch), 2) if launch else None


def child_result(
    units: int | None = None,
    wall_s: float | None = None,
    cpu_s: float | None = None,
    *,
    skipped: str | None = None,
    **extra,
) -> None:
    """Reports a child's measurement to :func:`alternate_processes` (one marked JSON line on stdout).

    ``units`` done in ``wall_s`` seconds of wall time and ``cpu_s`` seconds of the child's own CPU
    time; or ``skipped=reason`` when the contender cannot run here (the parent then drops it from
    later rounds). ``extra`` entries (JSON-serialisable) are kept per round in ``ProcessResult.extra``.
    """
    payload = {"units": units, "wall_s": wall_s, "cpu_s": cpu_s, "skipped": skipped, **extra}
    sys.stdout.write(RESULT_MARKER + json.dumps(payload, default=str) + "\n")
    sys.stdout.flush()


@dataclass
class ProcessContender:
    """One contender run as a child process: ``argv`` (``[sys.executable, "-m", "benchmarks.<name>", ...]``,
    from the repository root) must end by calling :func:`child_result` once."""

    name: str
    argv: list[str]
    env: dict[str, str] | None = None


@dataclass
class ProcessResult(Result):
    """A :class:`Result` from child processes, plus per-round extras and a note when skipped or failed."""

    extra: list[dict] = field(default_factory=list)
    note: str | None = None
    failures: int = 0

    @property
    def ok(self) -> bool:
        return bool(self.per_unit)

    def as_dict(self) -> dict:
        d = super().as_dict() if self.per_unit else {"name": self.name, "clock": self.clock}
        d.update({"extra": self.extra, "note": self.note, "failures": self.failures})
        return d


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _end_group(pgid: int, grace: float = 10.0) -> None:
    """Ends every process of a child's session: SIGTERM, then SIGKILL what is left after ``grace`` s.

    multiprocessing's resource tracker ignores SIGTERM; it exits by itself (unlinking the
    semaphores the workers registered) once every process that used it is gone, so it is given
    the grace period before SIGKILL."""
    if not _group_alive(pgid):
        return
    os.killpg(pgid, signal.SIGTERM)
    deadline = time.monotonic() + grace
    while _group_alive(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    if _group_alive(pgid):
        try:
            os.killpg(pgid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _run_child(
    c: ProcessContender, timeout: float, cwd: str | None, startup_limit: float | None = None
) -> tuple[dict | None, str]:
    """Runs one child in its own session and returns its result as soon as it is printed.

    A child that has not called :func:`child_ready` within ``startup_limit`` seconds is ended as
    one that timed out.
    The child may exit right after :func:`child_result` without closing its workers (their
    teardown is not measured and can take seconds); whatever is left of its session is then
    ended here, as is the whole session of a child that hangs past ``timeout``."""
    import threading

    env = dict(os.environ, PYTHONUNBUFFERED="1", **(c.env or {}), **{LAUNCH_ENV: repr(time.time())})
    proc = subprocess.Popen(
        c.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=cwd, start_new_session=True
    )
    lines: list[str] = []
    got, ready = threading.Event(), threading.Event()

    def read() -> None:
        for line in proc.stdout:  # until every process of the session has closed the pipe
            lines.append(line)
            if line.startswith(READY_MARKER):
                ready.set()
            if line.startswith(RESULT_MARKER):
                got.set()
        got.set()
        ready.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    t0 = time.monotonic()
    late = startup_limit is not None and not ready.wait(min(startup_limit, timeout))
    timed_out = late or not got.wait(max(0.0, timeout - (time.monotonic() - t0)))
    try:
        if not timed_out:
            try:
                proc.wait(timeout=30)  # the child itself exits right after its result
            except subprocess.TimeoutExpired:
                pass
    finally:
        _end_group(proc.pid)
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pass
        reader.join(timeout=5)
    out = "".join(lines)
    if late:
        return None, f"start-up over its {startup_limit:.0f} s limit\n{out[-2000:]}"
    if timed_out:
        return None, f"timed out after {timeout:.0f} s\n{out[-2000:]}"
    payload = None
    for line in lines:
        if line.startswith(RESULT_MARKER):
            payload = json.loads(line[len(RESULT_MARKER) :])
    if payload is None:
        return None, f"exit {proc.returncode}, no result\n{out[-2000:]}"
    return payload, out


def alternate_processes(
    contenders: Sequence[ProcessContender],
    *,
    rounds: int = 3,
    clock: str = "wall",
    timeout: float = 300.0,
    cwd: str | None = None,
    verbose: bool = False,
    quiet: tuple[float, float] | None = None,
    accept: Callable[[dict], bool] | None = None,
    retries: int = 0,
    on_result: Callable[[str, int, dict], None] | None = None,
    startup_limit: float | None = None,
    busy: int = 0,
) -> dict[str, ProcessResult]:
    """Runs each contender ``rounds`` times, each run a fresh child process, rounds alternating.

    Round ``r`` runs every contender once, starting with contender ``r % n`` (the order of
    :func:`interleave`); children run one at a time. Each child measures itself (warm-up untimed)
    and reports with :func:`child_result`; scores are its time per unit on ``clock``. A child that
    reports ``skipped`` is not run again (its reason goes to ``note``); one that fails or times out
    (its whole process group is killed) counts in ``failures`` and is retried next round.
    ``quiet=(max_busy, max_wait)`` waits for :func:`wait_for_quiet` before each child and keeps
    the reading in the round's extras as ``busy_before``. A result that ``accept(payload)``
    rejects (say, other jobs took cores during the timed window) is run again, up to ``retries``
    more times; the last try is kept either way, with the number of rejected tries in ``rejected``.
    ``startup_limit``: seconds a child may take to call :func:`child_ready` (see :func:`_run_child`).
    ``busy``: that many busy-loop processes (a pure-Python ``while True``, a learner's stand-in) run
    beside each child, started after the quiet wait and ended with the child; ``accept`` then sees
    the ``others_cores`` they took less ``busy``.
    """
    if clock not in ("wall", "cpu"):
        raise ValueError(f"clock must be 'wall' or 'cpu', got {clock!r}.")
    names = [c.name for c in contenders]
    if len(set(names)) != len(names):
        raise ValueError(f"Contender names must be unique, got {names}.")
    results = {c.name: ProcessResult(c.name, clock=clock) for c in contenders}
    n = len(contenders)
    for r in range(rounds):
        for c in (contenders[(r + i) % n] for i in range(n)):
            res = results[c.name]
            if res.note is not None and res.note.startswith("skipped"):
                continue
            rejected = 0
            while True:
                before = wait_for_quiet(*quiet, verbose=verbose) if quiet is not None else None
                loops = [_busy_loop() for _ in range(busy)]
                t0 = time.perf_counter()
                try:
                    payload, log = _run_child(c, timeout, cwd, startup_limit)
                finally:
                    for loop in loops:
                        loop.kill()
                        loop.wait()
                took = time.perf_counter() - t0
                if (
                    payload is None
                    or payload.get("skipped")
                    or accept is None
                    or accept({**payload, "others_cores": max(0.0, payload.get("others_cores", 0.0) - busy)})
                    or rejected >= retries
                ):
                    break
                rejected += 1
                if verbose:
                    print(
                        f"  round {r}: {c.name:<34} rejected ({payload.get('units', 0) / payload.get('wall_s', 1):.1f} "
                        f"units/s; {payload}), running it again",
                        flush=True,
                    )
            if on_result is not None:  # a failed run: {"failed": why}
                on_result(c.name, r, payload if payload is not None else {"failed": log.strip()[:300]})
            if payload is None:
                res.failures += 1
                res.note = f"failed: {log.strip().splitlines()[0] if log.strip() else 'no output'}"
                if verbose:
                    print(f"  round {r}: {c.name:<34} FAILED ({took:.0f} s)\n{log[-1500:]}", flush=True)
                continue
            if payload.get("skipped"):
                res.note = f"skipped: {payload['skipped']}"
                if verbose:
                    print(f"  round {r}: {c.name:<34} skipped: {payload['skipped']}", flush=True)
                continue
            units, wall, cpu = payload["units"], payload["wall_s"], payload["cpu_s"]
            res.per_unit.append((wall if clock == "wall" else cpu) / units)
            res.per_unit_wall.append(wall / units)
            res.per_unit_cpu.append(cpu / units)
            res.units.append(units)
            extra = {k: v for k, v in payload.items() if k not in ("units", "wall_s", "cpu_s", "skipped")}
            if before is not None:
                extra["busy_before"] = round(before, 3)
            if busy:
                extra["busy_loops"] = busy
            if accept is not None:
                extra["rejected"] = rejected
            res.extra.append(extra)
            if verbose:
                print(
                    f"  round {r}: {c.name:<34} {units / wall:8.1f} units/s ({units} in {wall:.2f} s; "
                    f"child ran {took:.1f} s)",
                    flush=True,
                )
    return results


def _busy_loop() -> subprocess.Popen:
    """A process that keeps a core busy until killed: a learner beside the sims, as on a user's machine."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"], start_new_session=True)


def add_alternation_args(p: argparse.ArgumentParser, retries: int = 2) -> None:
    """The flags of :func:`run_alternating`: rounds' process limits and the quiet-machine checks."""
    p.add_argument("--timeout", type=float, default=240.0, help="per child process (killed after)")
    p.add_argument(
        "--startup-limit",
        type=float,
        default=None,
        help="seconds a child may take to start (imports, build, warm-up) before it is ended (default: --timeout)",
    )
    p.add_argument(
        "--max-busy",
        type=float,
        default=0.3,
        help="before each run, wait until other processes use fewer cores than this (default 0.3)",
    )
    p.add_argument(
        "--max-wait",
        type=float,
        default=60.0,
        help="longest wait for that, in seconds; 0 turns the wait off (default 60)",
    )
    p.add_argument(
        "--max-others",
        type=float,
        default=0.25,
        help="a run during which other processes kept more cores busy than this is run again (default 0.25)",
    )
    p.add_argument("--retries", type=int, default=retries, help=f"re-runs of a disturbed run (default {retries})")
    p.add_argument(
        "--busy",
        type=int,
        default=0,
        help="busy-loop processes beside each run (a learner's stand-in; --max-others counts past them)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no per-run lines")


def run_alternating(contenders: list, args: argparse.Namespace, cwd: str, on_result=None) -> dict:
    """:func:`alternate_processes` with the flags of :func:`add_alternation_args` (and ``--rounds``)."""
    return alternate_processes(
        contenders,
        rounds=args.rounds,
        timeout=args.timeout,
        cwd=cwd,
        verbose=not args.quiet,
        quiet=(args.max_busy, args.max_wait) if args.max_wait > 0 else None,
        accept=lambda r: r.get("others_cores", 0.0) <= args.max_others,
        retries=args.retries,
        on_result=on_result,
        startup_limit=args.startup_limit,
        busy=getattr(args, "busy", 0),
    )
