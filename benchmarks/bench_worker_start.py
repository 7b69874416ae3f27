"""How long a pool of CPU-sim workers takes to start, with and without a preloaded forkserver.

A worker's imports (torch, TorchRL, ManiSkill's tasks) are most of its start. The library's
workers are forked from a forkserver that imported them once (``_internal.mp.preload_forkserver``):

- ``vector``: ``CPUVectorEnv("PickCube-v1", num_envs=--n, in_process=False)`` (every sub-env in a
  worker), as the library starts it; ``vector:plain``: the same with a forkserver that was started
  with no preload (the library's preload then changes nothing);
- ``parallel``: ``ManiSkillParallelEnv(--n, ManiSkillEnv)`` with its default, a preloaded forkserver;
  ``parallel:spawn``: the same with ``mp_start_method="spawn"`` (TorchRL's default).

Each run is a fresh process that, after its own imports, builds the env, resets it and closes it,
twice: ``first`` (the forkserver starts too) and ``second`` (what every later pool of the process
costs). Wall seconds, and the machine's busy CPU seconds over the same span (``/proc/stat``: run it
on a quiet machine). Contenders alternate in rotated order over ``--rounds``; medians.

    python -m benchmarks.bench_worker_start --n 2 --rounds 3 --out outputs/worker_start.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

from benchmarks.machine import machine_info

CONTENDERS = ["vector", "vector:plain", "parallel", "parallel:spawn"]


def _busy_s() -> float:
    """CPU seconds the whole machine has been busy (all cores, every process)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return (sum(v[:8]) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


def _make_single():
    from maniskill_torchrl import ManiSkillEnv

    return ManiSkillEnv("PickCube-v1", obs_mode="state", batch_size=[])


def child(contender: str, n: int) -> dict:
    """One run in this process: the contender's env started, reset and closed twice."""
    import multiprocessing as mp

    from maniskill_torchrl import CPUVectorEnv
    from maniskill_torchrl.parallel import ManiSkillParallelEnv

    if contender == "vector:plain":
        mp.set_forkserver_preload(["__main__"])
        from multiprocessing import forkserver

        forkserver.ensure_running()  # started bare: the library's preload then changes nothing

    def build():
        if contender.startswith("vector"):
            return CPUVectorEnv("PickCube-v1", num_envs=n, in_process=False)
        method = "spawn" if contender == "parallel:spawn" else None
        return ManiSkillParallelEnv(n, _make_single, mp_start_method=method)

    out = {}
    for which in ("first", "second"):
        t0, c0 = time.perf_counter(), _busy_s()
        env = build()
        env.reset(seed=0)
        env.close()
        out[which] = time.perf_counter() - t0
        out[f"{which}_cpu"] = _busy_s() - c0
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--n", type=int, default=2, help="workers per env")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--contenders", nargs="+", default=CONTENDERS, choices=CONTENDERS)
    p.add_argument("--child", choices=CONTENDERS, help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help="write the runs and medians as JSON here")
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.n)))
        return 0

    alternate_first_second(
        "benchmarks.bench_worker_start",
        args.contenders,
        args.rounds,
        ["--n", str(args.n)],
        f"N = {args.n} workers, {args.rounds} rounds, medians (s): wall first / second, machine CPU first / second",
        args.out,
        n=args.n,
    )
    return 0


def alternate_first_second(
    module: str, contenders: list[str], rounds: int, child_args: list[str], title: str, out: str | None, **extra
) -> dict:
    """Runs ``python -m module --child <contender> *child_args`` once per contender per round, in
    rotated order, each printing its ``first`` / ``second`` figures (and their ``_cpu``) as a JSON
    line; prints and returns the medians (written with the runs to ``out`` as JSON, with ``extra``)."""
    runs: dict[str, list[dict]] = {c: [] for c in contenders}
    for r in range(rounds):
        for contender in contenders[r % len(contenders) :] + contenders[: r % len(contenders)]:
            cmd = [sys.executable, "-m", module, "--child", contender, *child_args]
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
            if proc.returncode != 0:
                raise RuntimeError(f"{contender} failed:\n{proc.stderr[-3000:]}")
            runs[contender].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(contender, runs[contender][-1], flush=True)

    keys = ("first", "second", "first_cpu", "second_cpu")
    medians = {c: {k: statistics.median(run[k] for run in rs) for k in keys} for c, rs in runs.items()}
    print(f"\n{title}")
    for c, m in medians.items():
        print(f"{c:16s} {m['first']:6.2f} {m['second']:6.2f}   {m['first_cpu']:6.2f} {m['second_cpu']:6.2f}")
    if out:
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        with open(out, "w") as f:
            json.dump({"machine": machine_info(), **extra, "runs": runs, "medians": medians}, f, indent=1)
    return medians


if __name__ == "__main__":
    sys.exit(main())
