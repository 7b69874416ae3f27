"""The asynchronous path's cost in the main process, before and after a change, alternating processes.

Each run is one child process: ``ManiSkillAsyncEnvPool`` + ``AsyncPoolCollector`` (random
actions, ``min_get=1``, repeat 2) collecting for ``--seconds`` after one untimed batch, on the
replay task (``benchmarks/replay_task.py``: sleeping workers, so that many envs fit on 2 cores) or
a real task. It reports frames per second and the main process's own CPU time per frame and per
cycle (``time.process_time``: the workers' CPU is not in it; cycles from ``cycle_stats()`` where
the collector has it). The contenders are code trees: this checkout, and ``--before REF`` checked
out with ``git worktree`` under ``outputs/`` (the replay task and this script are copied in), run
in turn, rounds rotated (``benchmarks/alternate.py``). Ratios of one run are what to compare: the
machine's speed moves from hour to hour.

    python -m benchmarks.bench_async_cycle --before 2ba4b3d --num-envs 15 64 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# What a tree checked out for --before needs from this one to run the same child.
CARRIED = ("benchmarks/replay_task.py", "benchmarks/replay", "benchmarks/bench_async_cycle.py")


def child(task: str, n: int, seconds: float) -> None:
    import warnings

    warnings.filterwarnings("ignore")
    import torch

    torch.set_num_threads(1)
    from benchmarks.alternate import child_ready, child_result
    from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool

    if task == "replay":
        from benchmarks.replay_task import REPLAY_ID

        task = REPLAY_ID
    pool = ManiSkillAsyncEnvPool(task, n, repeat=2, obs_mode="state", max_episode_steps=50)
    frames = 100 * n
    collector = AsyncPoolCollector(pool, frames_per_batch=frames)
    it = iter(collector)
    next(it)  # the first resets and one batch, untimed
    child_ready()
    stats = getattr(collector, "cycle_stats", None)
    if stats is not None:
        stats(reset=True)
    got, cpu0, t0 = 0, time.process_time(), time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        got += next(it).shape[0]
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    cycles = stats()["cycles"] if stats is not None else None
    child_result(
        got,
        wall,
        cpu,
        fps=got / wall,
        main_us_per_frame=1e6 * cpu / got,
        main_us_per_cycle=None if not cycles else 1e6 * cpu / cycles,
        frames_per_cycle=None if not cycles else got / cycles,
    )
    os._exit(0)  # the workers' teardown is not measured


def _tree(ref: str) -> Path:
    """``ref`` checked out under outputs/, with what :data:`CARRIED` names copied in."""
    path = ROOT / "outputs" / f"tree-{ref}"
    if not path.exists():
        subprocess.run(["git", "worktree", "add", "--detach", str(path), ref], cwd=ROOT, check=True)
    for name in CARRIED:
        src, dst = ROOT / name, path / name
        if src.is_dir():
            shutil.copytree(src, dst, dirs_exist_ok=True)
        else:
            shutil.copy2(src, dst)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--child", nargs=3, metavar=("TASK", "N", "SECONDS"), help=argparse.SUPPRESS)
    p.add_argument("--before", default=None, help="a git ref to compare with (checked out under outputs/)")
    p.add_argument("--task", default="replay", help="'replay' (the sleeping replay task) or a ManiSkill task id")
    p.add_argument("--num-envs", type=int, nargs="+", default=[15])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json", default=None, help="write the results here")
    from benchmarks.alternate import ProcessContender, add_alternation_args, run_alternating

    add_alternation_args(p)
    args = p.parse_args(argv)
    if args.child:
        child(args.child[0], int(args.child[1]), float(args.child[2]))
        return 0
    trees = {"now": ROOT} | ({f"before-{args.before}": _tree(args.before)} if args.before else {})
    once = argparse.Namespace(**{**vars(args), "rounds": 1})
    results: dict[str, list[dict]] = {}
    for n in args.num_envs:
        runs = [
            (
                tree,
                ProcessContender(
                    f"{name} N={n}",
                    [
                        sys.executable,
                        "-m",
                        "benchmarks.bench_async_cycle",
                        "--child",
                        args.task,
                        str(n),
                        str(args.seconds),
                    ],
                ),
            )
            for name, tree in trees.items()
        ]
        for r in range(args.rounds):  # rotated; each child runs in its tree (python -m puts it first on the path)
            for tree, c in runs[r % len(runs) :] + runs[: r % len(runs)]:
                out = run_alternating([c], once, cwd=str(tree))[c.name]
                results.setdefault(c.name, []).extend(out.extra)
    rows = []
    for name, extra in results.items():
        runs = [e for e in extra if e.get("main_us_per_frame") is not None]
        if not runs:
            continue

        def med(key: str, runs=runs) -> float | None:
            values = [r[key] for r in runs if r.get(key) is not None]
            return statistics.median(values) if values else None

        fps = med("fps")
        rows.append(
            dict(
                name=name,
                runs=len(runs),
                fps=fps,
                main_us_per_frame=med("main_us_per_frame"),
                main_us_per_cycle=med("main_us_per_cycle"),
                frames_per_cycle=med("frames_per_cycle"),
            )
        )
    print(f"{'contender':<28}{'runs':>5}{'frames/s':>10}{'main us/frame':>15}{'main us/cycle':>15}{'frames/cycle':>14}")
    for r in rows:
        per_cycle = "" if r["main_us_per_cycle"] is None else f"{r['main_us_per_cycle']:.0f}"
        fpc = "" if r["frames_per_cycle"] is None else f"{r['frames_per_cycle']:.2f}"
        print(f"{r['name']:<28}{r['runs']:>5}{r['fps']:>10.0f}{r['main_us_per_frame']:>15.0f}{per_cycle:>15}{fpc:>14}")
    if args.json:
        Path(args.json).write_text(json.dumps({"argv": sys.argv, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
