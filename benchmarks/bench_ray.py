"""Frames/s of TorchRL's Ray collectors against the same number of local worker processes.

Contenders, each with ``K`` collectors of one ``ManiSkillEnv -> CPUUnbatch`` env (PickCube-v1,
state observations, random actions, episodes of 50 steps; the env of
``bench_collection.py``'s ``multisync`` pipeline), ``frames_per_batch = 50 * K``, ``sync=True``:

- ``ray``: ``Collector(make_env, backend="ray", num_collectors=K)`` (TorchRL's ``RayCollector``)
  on a local Ray instance started in the child (``ray.init(num_cpus=2)``), one Ray actor per
  collector (``remote_configs={"num_cpus": 1}``);
- ``multisync``: ``Collector(make_env, backend="process", num_collectors=K)`` (TorchRL's
  ``MultiSyncCollector``), one local worker process per collector.

Every run is a fresh process and the runs alternate (``alternate.alternate_processes``, the
harness of ``bench_collection.py``, whose child helpers in ``collection_pipelines.py`` this
script reuses); medians over rounds. Start-up (Ray's head processes, actor start, first batch)
is not timed; it is reported as ``start-up``. ``workers cpu`` counts every process under the
child (for ``ray`` that includes Ray's own raylet / GCS / agents).

Run: ``python -m benchmarks.bench_ray [--k 1 2] [--rounds 2] [--seconds 5] [--out results.json]``
(about 4 minutes on 2 cores with the defaults).
"""

from __future__ import annotations

import argparse
import functools
import os
import signal
import statistics
import sys
import time

from benchmarks.alternate import ProcessContender, add_alternation_args, child_result, run_alternating
from benchmarks.collection_pipelines import ENV_ID, EPISODE, SEED, _CPUMeter, _quiet, _time_collector, _worker_env
from benchmarks.machine import machine_line, save_json

HERE = os.path.dirname(os.path.abspath(__file__))

PIPELINES = ["multisync", "ray"]


# ============================================================================ child side
def child(kind: str, k: int, seconds: float, num_cpus: int) -> dict:
    from torchrl.collectors import Collector

    t0 = time.perf_counter()
    meter = _CPUMeter()
    make_env = functools.partial(_worker_env, 1)
    common = dict(frames_per_batch=EPISODE * k, total_frames=10**9, num_collectors=k, sync=True)
    if kind == "ray":
        import ray

        ray.init(num_cpus=num_cpus, log_to_driver=False, include_dashboard=False)
        collector = Collector(
            make_env, None, backend="ray", backend_options={"remote_configs": {"num_cpus": 1}}, **common
        )
    elif kind == "multisync":
        collector = Collector(make_env, None, backend="process", **common)
    else:
        raise SystemExit(f"unknown pipeline {kind!r}; one of {PIPELINES}")
    collector.set_seed(SEED)
    # _time_collector: one untimed batch (first reset, warm-up), then `seconds` of batches.
    out = _time_collector(collector, seconds, meter)
    out["startup_s"] = round(time.perf_counter() - t0 - out["wall_s"], 2)
    out["_collector"] = collector
    return out


def run_child(kind: str, k: int, seconds: float, num_cpus: int) -> None:
    _quiet()
    out = child(kind, k, seconds, num_cpus)
    collector = out.pop("_collector")
    child_result(**out)
    sys.stdout.flush()
    # Teardown (not measured): Ray's head processes must not outlive the run.
    try:
        collector.shutdown()
    finally:
        if kind == "ray":
            import ray

            ray.shutdown()
    os._exit(0)


# ============================================================================ parent side
def cell(kind: str, k: int) -> str:
    return f"{kind} K={k}"


def fmt_table(results: dict, ks: list[int]) -> str:
    rows = [
        "| collectors | K | frames/s (median) | min-max | ray / local | start-up s "
        "| main cpu | workers cpu | others | rounds |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    notes = []
    for k in ks:
        base = results[cell("multisync", k)]
        base_fps = 1.0 / base.median if base.ok else None
        for kind in PIPELINES:
            res = results[cell(kind, k)]
            label = 'Ray (`backend="ray"`)' if kind == "ray" else "local processes (`MultiSyncCollector`)"
            if not res.ok:
                rows.append(f"| {label} | {k} | - | - | - | - | - | - | - | 0 |")
                if res.note:
                    notes.append(f"- {kind} K={k}: {res.note.splitlines()[0][:300]}")
                continue
            fps = 1.0 / res.median
            lo, hi = 1.0 / max(res.per_unit), 1.0 / min(res.per_unit)
            wall = [u * p for u, p in zip(res.units, res.per_unit_wall)]
            main = statistics.median(u * p / w for u, p, w in zip(res.units, res.per_unit_cpu, wall))
            workers = statistics.median(e.get("workers_cpu_s", 0.0) / w for e, w in zip(res.extra, wall))
            startup = statistics.median(e["startup_s"] for e in res.extra)
            others = [e["others_cores"] for e in res.extra if "others_cores" in e]
            others_s = f"{statistics.median(others):.2f}" if others else "-"
            ratio = f"{fps / base_fps:.2f}x" if base_fps and kind == "ray" else "-"
            rows.append(
                f"| {label} | {k} | {fps:.0f} | {lo:.0f}-{hi:.0f} | {ratio} | {startup:.1f} | "
                f"{main:.2f} | {workers:.2f} | {others_s} | {len(res.per_unit)} |"
            )
    return "\n".join(rows + ([""] + notes if notes else []))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--k", type=int, nargs="+", default=[1, 2], help="collectors (default 1 2)")
    p.add_argument("--rounds", type=int, default=2, help="alternating rounds (default 2)")
    p.add_argument("--seconds", type=float, default=5.0, help="timed collection per run (default 5)")
    p.add_argument("--num-cpus", type=int, default=2, help="CPUs of the local Ray instance (default 2)")
    p.add_argument("--out", "--json", dest="out", default=None, help="write all results as JSON here")
    add_alternation_args(p, retries=1)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.child is not None:
        run_child(args.child, args.k[0], args.seconds, args.num_cpus)
        return 0

    try:
        import ray  # noqa: F401
    except ImportError:
        print("ray is not installed (pip install -e '.[distributed]'): nothing to run")
        return 0
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    print(machine_line())
    t0 = time.perf_counter()
    contenders = [
        ProcessContender(
            cell(kind, k),
            [
                sys.executable,
                "-m",
                "benchmarks.bench_ray",
                "--child",
                kind,
                "--k",
                str(k),
                "--seconds",
                str(args.seconds),
                "--num-cpus",
                str(args.num_cpus),
            ],
        )
        for k in args.k
        for kind in PIPELINES
    ]
    results = run_alternating(contenders, args, cwd=os.path.dirname(HERE))
    took = time.perf_counter() - t0
    print(
        f"\n{ENV_ID} state, random actions, episodes of {EPISODE} steps, one ManiSkillEnv -> CPUUnbatch per "
        f"collector, frames_per_batch = {EPISODE} x K, sync; median of {args.rounds} rounds x {args.seconds:g} s, "
        f"one process per run ({took:.0f} s in all)\n"
    )
    print(fmt_table(results, args.k))
    if args.out:
        save_json(
            args.out,
            {
                "seconds": args.seconds,
                "rounds": args.rounds,
                "results": {name: r.as_dict() for name, r in results.items()},
            },
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
