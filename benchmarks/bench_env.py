"""ManiSkillEnv step overhead against a raw ManiSkill loop (PickCube-v1, state obs, CPU sim).

One process, one ManiSkill env per scenario shared by the contenders (so the
physics work is the same: same seed, same pre-generated torch actions), timed
round-robin by :mod:`common`:

Scenario "step" (episode limit above the steps per round: no resets):

- ``raw``: ``obs, rew, term, trunc, info = env.step(action)`` on the gym env;
- ``ManiSkillEnv.step``: ``td.set("action", a); env.step(td)`` reusing one td,
  as a collector writes its policy's action;
- ``step_and_maybe_reset``: ``td.set("action", a); _, td = env.step_and_maybe_reset(td)``,
  what TorchRL's collectors and ``rollout`` call.

Scenario "episodes" (PickCube-v1's 50-step limit: a reset every 50 steps):

- ``raw+reset``: ``env.step(action)``, then ``env.reset(seed=next seed)`` when
  terminated or truncated (seeds drawn as ManiSkillEnv draws them);
- ``step_and_maybe_reset``: as above, its resets seeded by ``env.set_seed``.

Scenario "overhead" (no physics): the gym env under ManiSkillEnv is replaced by
a stub that returns one recorded ``step`` output, so what is timed is the
wrapper and TorchRL alone, in microseconds per step (``raw`` is the stub call).

Run: ``python benchmarks/bench_env.py [--rounds 15] [--steps 200] [--json out.json]``.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import Contender, interleave, machine_line, ratio, report, save_json  # noqa: E402

warnings.filterwarnings("ignore")

TARGET = 1.10
SEED = 0


def make_actions(env, n: int, seed: int = 0) -> list[torch.Tensor]:
    """``n`` uniform actions, each ``[1, *action_shape]`` float32, from the env's action bounds."""
    space = env.unwrapped.single_action_space
    g = torch.Generator().manual_seed(seed)
    low = torch.as_tensor(space.low, dtype=torch.float32)
    high = torch.as_tensor(space.high, dtype=torch.float32)
    return [(low + (high - low) * torch.rand(space.shape, generator=g)).unsqueeze(0) for _ in range(n)]


def scenario_step(steps: int, rounds: int, warmup: int, verbose: bool):
    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=10 * steps + 100)
    raw = env._env  # the gym env ManiSkillEnv made: same instance, same physics work
    actions = make_actions(raw, steps)
    state = {}

    def setup_raw():
        raw.reset(seed=SEED)

    def run_raw():
        step = raw.step
        for a in actions:
            step(a)
        return len(actions)

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

    results = interleave(
        [
            Contender("raw", run_raw, setup_raw),
            Contender("ManiSkillEnv.step", run_step, setup_td),
            Contender("step_and_maybe_reset", run_smr, setup_td),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
    )
    env.close()
    return results


def scenario_episodes(steps: int, rounds: int, warmup: int, verbose: bool):
    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv("PickCube-v1", obs_mode="state")  # 50-step episodes
    raw = env._env
    actions = make_actions(raw, steps, seed=1)
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


def scenario_overhead(steps: int, rounds: int, warmup: int, verbose: bool):
    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=10 * steps + 100)
    real = env._env
    actions = make_actions(real, steps)
    real.reset(seed=SEED)
    stub = _ReplayStub(real, real.step(actions[0]))
    env._env = stub
    state = {}

    def run_raw():
        step = stub.step
        for a in actions:
            step(a)
        return len(actions)

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

    results = interleave(
        [
            Contender("stub", run_raw),
            Contender("ManiSkillEnv.step", run_step, setup_td),
            Contender("step_and_maybe_reset", run_smr, setup_td),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
    )
    env._env = real
    env.close()
    return results


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=11)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--steps", type=int, default=200, help="env steps per contender per round")
    p.add_argument("--skip-episodes", action="store_true", help="only the no-reset scenario")
    p.add_argument("--json", default=None, help="write the per-round times here")
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)

    print(f"bench_env: PickCube-v1 state, CPU sim, {args.steps} steps x {args.rounds} rounds")
    print(machine_line())
    payload = {}

    res = scenario_step(args.steps, args.rounds, args.warmup, args.verbose)
    print("\nscenario: step (no resets)")
    print(report(res, baseline="raw"))
    r_step = ratio(res, "ManiSkillEnv.step", "raw")
    r_smr = ratio(res, "step_and_maybe_reset", "raw")
    payload["step"] = {k: v.as_dict() for k, v in res.items()}

    if not args.skip_episodes:
        res_ep = scenario_episodes(args.steps, args.rounds, args.warmup, args.verbose)
        print("\nscenario: episodes (50-step limit, seeded resets)")
        print(report(res_ep, baseline="raw+reset"))
        payload["episodes"] = {k: v.as_dict() for k, v in res_ep.items()}

    res_ov = scenario_overhead(1000, args.rounds, args.warmup, args.verbose)
    print("\nscenario: overhead (stub env, no physics; 1000 steps per round)")
    print(report(res_ov, baseline="stub", difference=True))
    payload["overhead"] = {k: v.as_dict() for k, v in res_ov.items()}
    ov_step = 1e6 * (res_ov["ManiSkillEnv.step"].median - res_ov["stub"].median)
    ov_smr = 1e6 * (res_ov["step_and_maybe_reset"].median - res_ov["stub"].median)
    raw_us = 1e6 * res["raw"].median
    print(
        f"wrapper overhead: step {ov_step:.1f} us, step_and_maybe_reset {ov_smr:.1f} us per step; "
        f"against the raw step ({raw_us:.0f} us) that predicts {1 + ov_step / raw_us:.3f}x and "
        f"{1 + ov_smr / raw_us:.3f}x"
    )

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
