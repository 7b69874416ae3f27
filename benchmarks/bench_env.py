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

Scenario "overhead" (no physics): the gym env under ManiSkillEnv is replaced by
a stub that returns one recorded ``step`` output, so what is timed is the
wrapper and TorchRL alone, in microseconds per step. Caches stay hot here: in a
real loop the same code costs more (ManiSkill's step evicts it).

Run: ``python benchmarks/bench_env.py [--rounds 31] [--steps 50] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import Contender, interleave, make_actions, ratio, report  # noqa: E402
from machine import machine_line, save_json  # noqa: E402

warnings.filterwarnings("ignore")

TARGET = 1.10
SEED = 0


def env_actions(env, n: int, seed: int = 0) -> list[torch.Tensor]:
    """``n`` uniform actions, each ``[1, *action_shape]`` float32, from the env's action bounds."""
    return make_actions(env.unwrapped.single_action_space, n, batch=(1,), seed=seed)


def step_contenders(env, actions, state) -> list[Contender]:
    """``ManiSkillEnv.step`` (td reused, ``td["action"]`` set each step) and ``step_and_maybe_reset``."""

    def setup_td():
        state["td"] = env.reset(seed=SEED)

    def run_step():
        td, step = state["td"], env.step
        for a in actions:
            td.set("action", a)
            step(td)
        return len(actions)

    def run_smr():
        td, smr = state["td"], env.step_and_maybe_reset
        for a in actions:
            td.set("action", a)
            _, td = smr(td)
        return len(actions)

    return [
        Contender("ManiSkillEnv.step", run_step, setup_td),
        Contender("step_and_maybe_reset", run_smr, setup_td),
    ]


def scenario_step(steps: int, rounds: int, warmup: int, verbose: bool, clock: str = "cpu"):
    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=10 * steps + 100)
    raw = env._env  # the gym env ManiSkillEnv made: same instance, same physics work
    actions = env_actions(raw, steps)
    state = {}

    def setup_raw():
        raw.reset(seed=SEED)

    def run_raw():
        step = raw.step
        for a in actions:
            step(a)
        return len(actions)

    results = interleave(
        [
            Contender("raw", run_raw, setup_raw),
            *step_contenders(env, actions, state),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock=clock,
    )
    env.close()
    return results


def scenario_episodes(steps: int, rounds: int, warmup: int, verbose: bool, clock: str = "cpu"):
    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv("PickCube-v1", obs_mode="state")  # 50-step episodes
    raw = env._env
    actions = env_actions(raw, steps, seed=1)
    state = {}

    def setup_raw():
        state["rng"] = np.random.RandomState(SEED)
        state["rng"].randint(2**31)  # ManiSkillEnv uses the seed itself first, then draws
        raw.reset(seed=SEED)

    def run_raw():
        step, reset, rng = raw.step, raw.reset, state["rng"]
        for a in actions:
            _, _, term, trunc, _ = step(a)
            if (term | trunc).any():
                reset(seed=int(rng.randint(2**31)))
        return len(actions)

    def setup_td():
        env.set_seed(SEED)
        state["td"] = env.reset()

    def run_smr():
        td, smr = state["td"], env.step_and_maybe_reset
        for a in actions:
            td.set("action", a)
            _, td = smr(td)
        return len(actions)

    results = interleave(
        [
            Contender("raw+reset", run_raw, setup_raw),
            Contender("step_and_maybe_reset", run_smr, setup_td),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock=clock,
    )
    env.close()
    return results


class _ReplayStub:
    """Stands in for the gym env: returns one recorded step output, does no work."""

    def __init__(self, env, out):
        self.unwrapped = env.unwrapped
        self._out = out

    def step(self, action):
        return self._out

    def reset(self, *, seed=None, options=None):
        return self._out[0], self._out[4]

    def render(self):
        raise NotImplementedError

    def close(self):
        pass


def scenario_overhead(steps: int, rounds: int, warmup: int, verbose: bool, clock: str = "cpu"):
    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=10 * steps + 100)
    real = env._env
    actions = env_actions(real, steps)
    real.reset(seed=SEED)
    stub = _ReplayStub(real, real.step(actions[0]))
    env._env = stub
    state = {}

    def run_raw():
        step = stub.step
        for a in actions:
            step(a)
        return len(actions)

    results = interleave(
        [
            Contender("stub", run_raw),
            *step_contenders(env, actions, state),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock=clock,
    )
    env._env = real
    env.close()
    return results


def scenario_paired(steps: int, rounds: int, warmup: int):
    """Per-step alternation of raw / step / step_and_maybe_reset on one env, CPU time per step."""
    import statistics
    import time

    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=10 * steps + 100)
    raw = env._env
    actions = env_actions(raw, steps, seed=2)
    names = ["raw", "ManiSkillEnv.step", "step_and_maybe_reset"]
    times = {n: [] for n in names}
    clock = time.process_time
    for r in range(warmup + rounds):
        td_step = env.reset(seed=SEED)
        td_smr = td_step.clone()
        for i, a in enumerate(actions):
            k = (i + r) % 3
            if k == 0:
                t0 = clock()
                raw.step(a)
                dt = clock() - t0
            elif k == 1:
                td_step.set("action", a)
                t0 = clock()
                env.step(td_step)
                dt = clock() - t0
            else:
                td_smr.set("action", a)
                t0 = clock()
                _, td_smr = env.step_and_maybe_reset(td_smr)
                dt = clock() - t0
            if r >= warmup:
                times[names[k]].append(dt)
    env.close()
    return {
        n: {"median_s": statistics.median(v), "mean_s": statistics.fmean(v), "steps": len(v)} for n, v in times.items()
    }


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
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)

    torch.set_num_threads(args.threads)
    print(
        f"bench_env: PickCube-v1 state, CPU sim, scored on {args.clock} time, torch threads {torch.get_num_threads()}"
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
