"""ManiSkillEnv step overhead against a raw ManiSkill loop (PickCube-v1, state obs, CPU sim).

One process, one ManiSkill env per scenario shared by the contenders (so the
physics work is the same: same seed, same pre-generated torch actions [1, 8]),
timed round-robin by :mod:`common` (rotating order, medians over rounds). The
default clock is this process's CPU time (both clocks are printed): on a machine
shared with other busy processes it is the steadier measure.

Scenario "step" (the target; episode limit above the steps per round: no resets):

- ``raw``: ``obs, rew, term, trunc, info = env.step(action)`` on the gym env;
- ``ManiSkillEnv.step``: ``td.set("action", a); env.step(td)`` reusing one td
  (which then carries the previous ``"next"``: EnvBase.step merges it);
- ``step_and_maybe_reset``: ``td.set("action", a); _, td = env.step_and_maybe_reset(td)``,
  what TorchRL's collectors and ``rollout`` call.

Scenario "paired" (cross-check): the same three, alternating at every single
step on one env (step ``i`` of round ``r`` goes to contender ``(i + r) % 3``),
each step timed alone: the three see the same machine state to the microsecond.

Scenario "episodes" (PickCube-v1's 50-step limit: a reset every 50 steps):

- ``raw+reset``: ``env.step(action)``, then ``env.reset(seed=next seed)`` when
  terminated or truncated (seeds drawn as ManiSkillEnv draws them);
- ``step_and_maybe_reset``: as above, its resets seeded by ``env.set_seed``.

Scenario "worker" (no physics, stubs as in "overhead"): what each worker of a ``ParallelEnv`` of
singles runs per step, ``step_and_maybe_reset``, on the batch-``[1]`` env, on
``TransformedEnv(env, CPUUnbatch())`` and on ``ManiSkillEnv(..., batch_size=[])``.

Scenario "overhead" (no physics): the gym env under ManiSkillEnv is replaced by
a stub that returns one recorded ``step`` output, so what is timed is the
wrapper and TorchRL alone, in microseconds per step. Caches stay hot here: in a
real loop the same code costs more (ManiSkill's step evicts it).

``ManiSkillEnv`` runs ManiSkill under ``torch.inference_mode()`` on the CPU sim by default; the
raw loop then runs under it too (the same torch work on both sides: the ratios are the
wrapper's cost). ``--grad-mode`` (``inference_mode=False``) times both in grad mode.

Run: ``python -m benchmarks.bench_env [--rounds 31] [--steps 50] [--grad-mode] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import sys
import warnings

import torch

from benchmarks import env_scenarios
from benchmarks.common import ratio, report
from benchmarks.env_scenarios import (
    scenario_episodes,
    scenario_overhead,
    scenario_paired,
    scenario_step,
    scenario_worker,
)
from benchmarks.machine import machine_line, save_json

warnings.filterwarnings("ignore")

TARGET = 1.10


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=31)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--steps", type=int, default=50, help="env steps per contender per round")
    p.add_argument("--episode-steps", type=int, default=150, help="steps per round, episodes scenario")
    p.add_argument("--skip-episodes", action="store_true")
    p.add_argument("--skip-paired", action="store_true")
    p.add_argument("--json", default=None, help="write the per-round times here")
    p.add_argument(
        "--clock",
        choices=("cpu", "wall"),
        default="cpu",
        help="the clock that scores (both are reported): cpu = this process's CPU time, steadier "
        "on a machine shared with other busy processes; everything here runs in this process",
    )
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    p.add_argument(
        "--grad-mode",
        action="store_true",
        help="ManiSkillEnv(inference_mode=False): the wrapper alone, ManiSkill in grad mode as in the raw loop",
    )
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)
    if args.grad_mode:
        env_scenarios.ENV_KWARGS["inference_mode"] = False

    torch.set_num_threads(args.threads)
    print(
        f"bench_env: PickCube-v1 state, CPU sim, scored on {args.clock} time, torch threads {torch.get_num_threads()}, "
        f"ManiSkillEnv in {'grad' if args.grad_mode else 'inference'} mode"
    )
    print(machine_line())
    payload = {"args": vars(args)}

    res = scenario_step(args.steps, args.rounds, args.warmup, args.verbose, args.clock)
    print(f"\nscenario: step (no resets; {args.steps} steps x {args.rounds} rounds)")
    print(report(res, baseline="raw"))
    r_step = ratio(res, "ManiSkillEnv.step", "raw")
    r_smr = ratio(res, "step_and_maybe_reset", "raw")
    payload["step"] = {k: v.as_dict() for k, v in res.items()}

    if not args.skip_paired:
        n_paired = 3 * 50
        paired = scenario_paired(n_paired, max(args.rounds // 2, 3), args.warmup)
        base = paired["raw"]
        print(f"\nscenario: paired (alternating every step; {n_paired} steps x {max(args.rounds // 2, 3)} rounds, cpu)")
        print("| contender | median us/step | mean us/step | ratio (medians) | ratio (means) |")
        print("|---|---:|---:|---:|---:|")
        for name, v in paired.items():
            print(
                f"| {name} | {1e6 * v['median_s']:.1f} | {1e6 * v['mean_s']:.1f} | "
                f"{v['median_s'] / base['median_s']:.3f}x | {v['mean_s'] / base['mean_s']:.3f}x |"
            )
        payload["paired"] = paired

    if not args.skip_episodes:
        n_ep_rounds = max(args.rounds // 3, 3)
        res_ep = scenario_episodes(args.episode_steps, n_ep_rounds, args.warmup, args.verbose, args.clock)
        print(f"\nscenario: episodes (50-step limit, seeded resets; {args.episode_steps} steps x {n_ep_rounds} rounds)")
        print(report(res_ep, baseline="raw+reset"))
        payload["episodes"] = {k: v.as_dict() for k, v in res_ep.items()}

    n_ov_rounds = max(args.rounds // 3, 3)
    res_ov = scenario_overhead(500, n_ov_rounds, args.warmup, args.verbose, args.clock)
    print(f"\nscenario: overhead (stub env, no physics, hot caches; 500 steps x {n_ov_rounds} rounds)")
    print(report(res_ov, baseline="stub", difference=True))
    payload["overhead"] = {k: v.as_dict() for k, v in res_ov.items()}

    res_w = scenario_worker(500, n_ov_rounds, args.warmup, args.verbose, args.clock)
    print(f"\nscenario: worker (a ParallelEnv worker's step_and_maybe_reset, stub; 500 steps x {n_ov_rounds} rounds)")
    print(report(res_w, baseline="batch [1]", difference=True))
    payload["worker"] = {k: v.as_dict() for k, v in res_w.items()}

    verdict = "within" if r_step <= TARGET else "OVER"
    print(
        f"\nManiSkillEnv.step / raw = {r_step:.3f}x, step_and_maybe_reset / raw = {r_smr:.3f}x "
        f"(target <= {TARGET:.2f}x: {verdict})"
    )
    if args.json:
        save_json(args.json, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
