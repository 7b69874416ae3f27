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
import sys
import time

from benchmarks.bench_worker_start import _busy_s, alternate_first_second

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

    alternate_first_second(
        "benchmarks.bench_first_picture",
        CONTENDERS,
        args.rounds,
        [],
        f"{args.rounds} rounds, medians (s): wall first / second env, machine CPU first / second env",
        args.out,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
