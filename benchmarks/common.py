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

Beside it: ``machine.py`` (the machine's description and load, results saved as JSON) and
``alternate.py`` (contenders that must each start from a fresh interpreter: every round runs
one child process per contender, in the same rotating order).

Example::

    from benchmarks.common import Contender, interleave, report

    results = interleave(
        [Contender("raw", run_raw, setup=reset_raw), Contender("wrapped", run_wrapped, setup=reset_wrapped)],
        rounds=7,
        warmup=1,
    )
    print(report(results, baseline="raw"))
"""

from __future__ import annotations

import gc
import statistics
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
    "make_actions",
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


def make_actions(space, n: int, batch: tuple = (), seed: int = 0) -> list:
    """``n`` reproducible uniform float32 actions of shape ``[*batch, *space.shape]`` within a Box's bounds."""
    import torch

    g = torch.Generator().manual_seed(seed)
    low = torch.as_tensor(space.low, dtype=torch.float32)
    high = torch.as_tensor(space.high, dtype=torch.float32)
    return [low + (high - low) * torch.rand(tuple(batch) + tuple(space.shape), generator=g) for _ in range(n)]
