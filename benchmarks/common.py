"""Interleaved timing harness shared by the ``benchmarks/bench_*.py`` scripts.

All contenders run in one process and take turns: each round runs every
contender once, in a rotating order (round ``r`` starts with contender
``r % n``), so slow drifts of the machine (thermal state, other processes,
allocator warm-up) hit every contender alike. Each contender's score is the
median over rounds of its time per unit (per env step, usually); ratios are
taken between medians.

Two clocks are read around every timed call: wall time (``time.perf_counter``)
and this process's CPU time (``time.process_time``, all its threads). The
``clock`` argument of :func:`interleave` picks which one scores (``"wall"`` by
default). On a machine shared with other busy processes, wall time also counts
the time the benchmark waits for a core; CPU time does not, and is the steadier
measure of what the code costs, as long as all the work happens in this process
(use ``"wall"`` for contenders that use worker processes, e.g. ``ParallelEnv``).

A contender is a callable ``run() -> int`` that does one round of work and
returns the number of units it did (or ``None`` for the ``units`` given to
:func:`interleave`). Untimed per-round set-up (a seeded reset, say) goes into
an optional ``setup`` callable: it runs just before the contender's timed call.

For contenders that must each start from a fresh interpreter (multi-process
pipelines: their worker processes, start-up state and imported modules must not
leak from one contender into the next), :func:`alternate_processes` runs every
round as one child process per contender, in the same rotating order, and reads
back what each child measured (:func:`child_result` writes it).

Example::

    from common import Contender, interleave, report

    results = interleave(
        [Contender("raw", run_raw, setup=reset_raw), Contender("wrapped", run_wrapped, setup=reset_wrapped)],
        rounds=7,
        warmup=1,
    )
    print(report(results, baseline="raw"))
"""

from __future__ import annotations

import argparse
import datetime as _dt
import gc
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

__all__ = [
    "Contender",
    "Result",
    "interleave",
    "report",
    "ratio",
    "paired_ratio",
    "machine_info",
    "machine_line",
    "save_json",
    "make_actions",
    "ProcessContender",
    "alternate_processes",
    "child_result",
    "RESULT_MARKER",
    "busy_cores",
    "wait_for_quiet",
]


@dataclass
class Contender:
    """One thing to time: ``run()`` does one round and returns its unit count (or ``None``)."""

    name: str
    run: Callable[[], int | None]
    setup: Callable[[], None] | None = None


@dataclass
class Result:
    """Per-round times per unit (seconds) of one contender, on the scoring clock (``per_unit``)
    and on both clocks (``per_unit_wall``, ``per_unit_cpu``)."""

    name: str
    per_unit: list[float] = field(default_factory=list)
    units: list[int] = field(default_factory=list)
    clock: str = "wall"
    per_unit_wall: list[float] = field(default_factory=list)
    per_unit_cpu: list[float] = field(default_factory=list)

    @property
    def other_clock(self) -> str:
        return "cpu" if self.clock == "wall" else "wall"

    @property
    def other_median(self) -> float:
        """Median per unit on the clock that does not score."""
        return statistics.median(self.per_unit_cpu if self.clock == "wall" else self.per_unit_wall)

    @property
    def median(self) -> float:
        return statistics.median(self.per_unit)

    @property
    def minimum(self) -> float:
        return min(self.per_unit)

    @property
    def spread(self) -> float:
        """Relative spread of the rounds: (max - min) / median."""
        return (max(self.per_unit) - min(self.per_unit)) / self.median

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "median_s": self.median,
            "min_s": self.minimum,
            "spread": self.spread,
            "clock": self.clock,
            "per_unit_s": self.per_unit,
            "per_unit_wall_s": self.per_unit_wall,
            "per_unit_cpu_s": self.per_unit_cpu,
            "units": self.units,
        }


def interleave(
    contenders: Sequence[Contender],
    *,
    rounds: int = 7,
    warmup: int = 1,
    units: int | None = None,
    gc_collect: bool = True,
    clock: str = "wall",
    verbose: bool = False,
) -> dict[str, Result]:
    """Runs the contenders round-robin for ``warmup`` untimed then ``rounds`` timed rounds.

    ``clock`` (``"wall"`` or ``"cpu"``) picks the clock that scores; both are recorded.
    Returns ``{name: Result}`` in the order of ``contenders``.
    """
    if not contenders:
        raise ValueError("interleave() needs at least one contender.")
    if clock not in ("wall", "cpu"):
        raise ValueError(f"clock must be 'wall' or 'cpu', got {clock!r}.")
    names = [c.name for c in contenders]
    if len(set(names)) != len(names):
        raise ValueError(f"Contender names must be unique, got {names}.")
    results = {c.name: Result(c.name, clock=clock) for c in contenders}
    n = len(contenders)
    for r in range(warmup + rounds):
        timed = r >= warmup
        order = [contenders[(r + i) % n] for i in range(n)]
        for c in order:
            if c.setup is not None:
                c.setup()
            if gc_collect:
                gc.collect()
            c0 = time.process_time()
            t0 = time.perf_counter()
            done = c.run()
            dt_wall = time.perf_counter() - t0
            dt_cpu = time.process_time() - c0
            dt = dt_wall if clock == "wall" else dt_cpu
            count = done if done is not None else units
            if count is None or count <= 0:
                raise ValueError(
                    f"Contender {c.name!r} returned {done!r}: return the number of units done "
                    "or pass units= to interleave()."
                )
            if timed:
                res = results[c.name]
                res.per_unit.append(dt / count)
                res.per_unit_wall.append(dt_wall / count)
                res.per_unit_cpu.append(dt_cpu / count)
                res.units.append(count)
            if verbose:
                tag = "round" if timed else "warmup"
                print(
                    f"  {tag} {r - warmup if timed else r}: {c.name:<28} "
                    f"{1e6 * dt_wall / count:9.1f} us/unit wall {1e6 * dt_cpu / count:9.1f} cpu"
                )
    return results


def ratio(results: dict[str, Result], name: str, baseline: str) -> float:
    """Median time per unit of ``name`` over that of ``baseline``."""
    return results[name].median / results[baseline].median


def paired_ratio(results: dict[str, Result], name: str, baseline: str, clock: str = "cpu") -> float:
    """Median over rounds of the per-round ratio ``name / baseline`` on ``clock`` (``"cpu"`` or ``"wall"``):
    adjacent runs see the same machine state, so this ratio swings less than the ratio of medians."""
    attr = "per_unit_cpu" if clock == "cpu" else "per_unit_wall"
    return statistics.median(x / y for x, y in zip(getattr(results[name], attr), getattr(results[baseline], attr)))


def report(
    results: dict[str, Result],
    *,
    baseline: str | None = None,
    unit: str = "step",
    difference: bool = False,
) -> str:
    """A markdown table: median and min time per unit, spread over rounds, and the ratio to
    ``baseline`` (or, with ``difference=True``, the median time over the baseline's, in us:
    for a baseline that does next to nothing)."""
    if baseline is None:
        baseline = next(iter(results))
    first = results[baseline]
    clk, other = first.clock, first.other_clock
    last = f"us/{unit} over {baseline}" if difference else f"ratio to {baseline}"
    last_other = f"over {baseline} ({other})" if difference else f"ratio ({other})"
    rows = [
        f"| contender | median us/{unit} ({clk}) | min | spread | {last} | median ({other}) | {last_other} |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    base, base_other = first.median, first.other_median
    for name, res in results.items():
        if difference:
            cmp = f"{1e6 * (res.median - base):+.1f}"
            cmp_other = f"{1e6 * (res.other_median - base_other):+.1f} us"
        else:
            cmp = f"{ratio(results, name, baseline):.3f}x"
            cmp_other = f"{res.other_median / base_other:.3f}x"
        rows.append(
            f"| {name} | {1e6 * res.median:.1f} | {1e6 * res.minimum:.1f} | "
            f"{100 * res.spread:.1f}% | {cmp} | {1e6 * res.other_median:.1f} | {cmp_other} |"
        )
    return "\n".join(rows)


def _cpu_model() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """CPU model, usable cores, python and library versions."""
    info = {
        "cpu": _cpu_model(),
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "python": platform.python_version(),
        "date": _dt.date.today().isoformat(),
    }
    for mod in ("torch", "tensordict", "torchrl", "mani_skill", "sapien", "gymnasium", "numpy"):
        try:
            info[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001 - a missing library is just not reported
            pass
    try:
        import torch

        info["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    return info


def machine_line(info: dict | None = None) -> str:
    """One line describing the machine and versions, for RESULTS.md."""
    info = info or machine_info()
    libs = ", ".join(f"{k} {info[k]}" for k in ("torch", "tensordict", "torchrl", "mani_skill", "sapien") if k in info)
    return f"{info['cpu']}, {info['cores']} cores, Python {info['python']}; {libs}"


def save_json(path: str, payload: dict) -> None:
    """Writes ``payload`` (with machine info added) as JSON, creating the folder."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    payload = {"machine": machine_info(), **payload}
    with open(path, "w") as f:
        json.dump(payload, f, indent=2, default=str)


def make_actions(space, n: int, batch: tuple = (), seed: int = 0) -> list:
    """``n`` reproducible uniform float32 actions of shape ``[*batch, *space.shape]`` within a Box's bounds."""
    import torch

    g = torch.Generator().manual_seed(seed)
    low = torch.as_tensor(space.low, dtype=torch.float32)
    high = torch.as_tensor(space.high, dtype=torch.float32)
    return [low + (high - low) * torch.rand(tuple(batch) + tuple(space.shape), generator=g) for _ in range(n)]


# ----------------------------------------------------------------------------- one process per run
RESULT_MARKER = "@@bench-result "


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


def _cpu_jiffies() -> tuple[int, int] | None:
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return sum(fields[:8]), idle  # user..steal; guest time is already in user


def busy_cores(interval: float = 1.0) -> float | None:
    """Cores kept busy on this machine over ``interval`` seconds (all processes; Linux ``/proc/stat``).

    ``None`` where ``/proc/stat`` cannot be read."""
    a = _cpu_jiffies()
    time.sleep(interval)
    b = _cpu_jiffies()
    if a is None or b is None or b[0] == a[0]:
        return None
    cores = os.cpu_count() or 1
    return cores * (1.0 - (b[1] - a[1]) / (b[0] - a[0]))


def wait_for_quiet(
    max_busy: float = 0.3, max_wait: float = 120.0, interval: float = 0.5, verbose: bool = False
) -> float | None:
    """Waits until other processes keep fewer than ``max_busy`` cores busy (sampled every
    ``interval`` s), at most ``max_wait`` seconds; returns the last reading (``None`` if unknown).

    For timings on a machine shared with other jobs: call it before each timed run (not while
    this process's own workers are running) and record the reading next to the result."""
    t0 = time.perf_counter()
    warned = False
    while True:
        busy = busy_cores(interval)
        if busy is None or busy < max_busy or time.perf_counter() - t0 >= max_wait:
            return busy
        if verbose and not warned:
            print(f"  (machine busy: {busy:.2f} cores used by others; waiting up to {max_wait:.0f} s)", flush=True)
            warned = True


@dataclass
class ProcessContender:
    """One contender run as a child process: ``argv`` (``[sys.executable, script, ...]``) must end
    by calling :func:`child_result` once."""

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


def _run_child(c: ProcessContender, timeout: float, cwd: str | None) -> tuple[dict | None, str]:
    """Runs one child in its own session and returns its result as soon as it is printed.

    The child may exit right after :func:`child_result` without closing its workers (their
    teardown is not measured and can take seconds); whatever is left of its session is then
    ended here, as is the whole session of a child that hangs past ``timeout``."""
    import threading

    env = dict(os.environ, PYTHONUNBUFFERED="1", **(c.env or {}))
    proc = subprocess.Popen(
        c.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=cwd, start_new_session=True
    )
    lines: list[str] = []
    got = threading.Event()

    def read() -> None:
        for line in proc.stdout:  # until every process of the session has closed the pipe
            lines.append(line)
            if line.startswith(RESULT_MARKER):
                got.set()
        got.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    timed_out = not got.wait(timeout)
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
    on_result: Callable[[str, int, dict | None], None] | None = None,
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
                busy = wait_for_quiet(*quiet, verbose=verbose) if quiet is not None else None
                t0 = time.perf_counter()
                payload, log = _run_child(c, timeout, cwd)
                took = time.perf_counter() - t0
                if (
                    payload is None
                    or payload.get("skipped")
                    or accept is None
                    or accept(payload)
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
            if on_result is not None:
                on_result(c.name, r, payload)
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
            if busy is not None:
                extra["busy_before"] = round(busy, 3)
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


def add_alternation_args(p: argparse.ArgumentParser, retries: int = 2) -> None:
    """The flags of :func:`run_alternating`: rounds' process limits and the quiet-machine checks."""
    p.add_argument("--timeout", type=float, default=240.0, help="per child process (killed after)")
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
    p.add_argument("-q", "--quiet", action="store_true", help="no per-run lines")


def run_alternating(contenders: list, args: argparse.Namespace, cwd: str) -> dict:
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
    )
