"""What the first picture of a process costs on the CPU (Mesa's lavapipe), and again after every env is freed.

SAPIEN's render engine computes its BRDF lookup table at its first picture (a compute shader, which
lavapipe runs on the CPU), and frees the engine with the last env of the process that renders: the
next env's first picture computes the table again. Two contenders, each a fresh process that makes
``ManiSkillEnv("PickCube-v1", obs_mode="rgb")``, resets it and takes 2 steps, closes and frees it
(``del``, ``gc.collect()``), then does the same with a second env:

- ``freed``: nothing else holds the engine (what a loop that makes one env after another gets);
- ``held``: the process holds a ``sapien.render.RenderSystem`` on the envs' render device from the
  first env's end (what ``tests/conftest.py`` does, and the docs' CPU guide shows users).

Wall seconds, and the machine's busy CPU seconds over the same span (``/proc/stat``: run it on a quiet
machine). Contenders alternate in rotated order over ``--rounds``; medians.

    python -m benchmarks.bench_first_picture --rounds 3 --out outputs/first_picture.json
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

from benchmarks.bench_worker_start import _busy_s
from benchmarks.machine import machine_info

CONTENDERS = ["freed", "held"]


def child(contender: str) -> dict:
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
            held.append(sapien.render.RenderSystem(env.base_env.scene.sub_scenes[0].render_system.device))
        env.close()
        del env
        gc.collect()
        out[which] = time.perf_counter() - t0
        out[f"{which}_cpu"] = _busy_s() - c0
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--child", choices=CONTENDERS, help=argparse.SUPPRESS)
    p.add_argument("--out", default=None, help="write the runs and medians as JSON here")
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child)))
        return 0

    runs: dict[str, list[dict]] = {c: [] for c in CONTENDERS}
    for r in range(args.rounds):
        for contender in CONTENDERS[r % 2 :] + CONTENDERS[: r % 2]:
            cmd = [sys.executable, "-m", "benchmarks.bench_first_picture", "--child", contender]
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
            if proc.returncode != 0:
                raise RuntimeError(f"{contender} failed:\n{proc.stderr[-3000:]}")
            runs[contender].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(contender, runs[contender][-1], flush=True)

    keys = ("first", "second", "first_cpu", "second_cpu")
    medians = {c: {k: statistics.median(run[k] for run in rs) for k in keys} for c, rs in runs.items()}
    print(f"\n{args.rounds} rounds, medians (s): wall first / second env, machine CPU first / second env")
    for c, m in medians.items():
        print(f"{c:8s} {m['first']:6.2f} {m['second']:6.2f}   {m['first_cpu']:6.2f} {m['second_cpu']:6.2f}")
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump({"machine": machine_info(), "runs": runs, "medians": medians}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
