"""What a process's first env costs, and every later one: its workers' start and its first picture.

Each run is a fresh process that, after its own imports, makes an env, uses it and closes it,
twice: ``first`` (what the process pays once) and ``second`` (what every later env pays). Wall
seconds, and the machine's busy CPU seconds over the same span (``/proc/stat``: run it on a quiet
machine). Contenders alternate in rotated order over ``--rounds``; medians. Two groups (``--what``):

``workers``: a pool of ``--n`` CPU-sim workers started, reset and closed. A worker's imports (torch,
TorchRL, ManiSkill's tasks) are most of its start; the library's workers are forked from a forkserver
that imported them once (``_internal.mp.preload_forkserver``), which the ``first`` env starts too:

- ``vector``: ``CPUVectorEnv("PickCube-v1", num_envs=--n, in_process=False)`` (every sub-env in a
  worker), as the library starts it; ``vector:plain``: the same with a forkserver that was started
  with no preload (the library's preload then changes nothing);
- ``parallel``: ``ManiSkillParallelEnv(--n, ManiSkillEnv)`` with its default, a preloaded forkserver;
  ``parallel:spawn``: the same with ``mp_start_method="spawn"`` (TorchRL's default).

``picture``: ``ManiSkillEnv("PickCube-v1", obs_mode="rgb")`` made, reset, stepped twice, closed and
freed (``del``, ``gc.collect()``). SAPIEN's render engine computes its BRDF lookup table at its first
picture (a compute shader, which Mesa's lavapipe runs on the CPU), and frees the engine with the
last env of the process that renders: the next env's first picture computes the table again.

- ``freed``: nothing else holds the engine (what a loop that makes one env after another gets);
- ``held``: the process holds a ``sapien.render.RenderSystem`` on the envs' render device from the
  first env's end (what ``tests/conftest.py`` does, and the docs' CPU guide shows users).

    python -m benchmarks.bench_startup --what workers --n 2 --rounds 3 --out outputs/startup.json
    python -m benchmarks.bench_startup --what picture --rounds 3
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import subprocess
import sys
import time

from benchmarks.machine import machine_info

CONTENDERS = {"workers": ["vector", "vector:plain", "parallel", "parallel:spawn"], "picture": ["freed", "held"]}


def _busy_s() -> float:
    """CPU seconds the whole machine has been busy (all cores, every process)."""
    with open("/proc/stat") as f:
        v = [int(x) for x in f.readline().split()[1:]]
    return (sum(v[:8]) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


def _make_single():
    from maniskill_torchrl import ManiSkillEnv

    return ManiSkillEnv("PickCube-v1", obs_mode="state", batch_size=[])


def child_workers(contender: str, n: int) -> dict:
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


def child_picture(contender: str) -> dict:
    """One run in this process: two envs, one after the other, each made, stepped, closed and freed."""
    import sapien

    from maniskill_torchrl import ManiSkillEnv

    held = []
    out = {}
    for which in ("first", "second"):
        t0, c0 = time.perf_counter(), _busy_s()
        env = ManiSkillEnv("PickCube-v1", obs_mode="rgb", batch_size=[])
        env.rollout(2)
        if contender == "held" and not held:
            held.append(sapien.render.RenderSystem(env.unwrapped.scene.sub_scenes[0].render_system.device))
        env.close()
        del env
        gc.collect()
        out[which] = time.perf_counter() - t0
        out[f"{which}_cpu"] = _busy_s() - c0
    return out


def alternate_first_second(contenders: list[str], rounds: int, child_args: list[str]) -> tuple[dict, dict]:
    """Runs ``python -m benchmarks.bench_startup --child <contender> *child_args`` once per contender
    per round, in rotated order, each printing its ``first`` / ``second`` figures (and their ``_cpu``)
    as a JSON line; returns the runs and their medians."""
    runs: dict[str, list[dict]] = {c: [] for c in contenders}
    for r in range(rounds):
        for contender in contenders[r % len(contenders) :] + contenders[: r % len(contenders)]:
            cmd = [sys.executable, "-m", "benchmarks.bench_startup", "--child", contender, *child_args]
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
            if proc.returncode != 0:
                raise RuntimeError(f"{contender} failed:\n{proc.stderr[-3000:]}")
            runs[contender].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(contender, runs[contender][-1], flush=True)

    keys = ("first", "second", "first_cpu", "second_cpu")
    return runs, {c: {k: statistics.median(run[k] for run in rs) for k in keys} for c, rs in runs.items()}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--what", nargs="+", default=list(CONTENDERS), choices=list(CONTENDERS))
    p.add_argument("--n", type=int, default=2, help="workers per env (--what workers)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--child", choices=[c for cs in CONTENDERS.values() for c in cs], help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help="write the runs and medians as JSON here")
    args = p.parse_args(argv)
    if args.child:
        out = child_picture(args.child) if args.child in CONTENDERS["picture"] else child_workers(args.child, args.n)
        print(json.dumps(out))
        return 0

    results = {}
    for what in args.what:
        runs, medians = alternate_first_second(CONTENDERS[what], args.rounds, ["--n", str(args.n)])
        unit = f"N = {args.n} workers, " if what == "workers" else ""
        print(f"\n{what}: {unit}{args.rounds} rounds, medians (s): wall first / second, machine CPU first / second")
        for c, m in medians.items():
            print(f"{c:16s} {m['first']:6.2f} {m['second']:6.2f}   {m['first_cpu']:6.2f} {m['second_cpu']:6.2f}")
        results[what] = {"runs": runs, "medians": medians}
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump({"machine": machine_info(), "n": args.n, **results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
