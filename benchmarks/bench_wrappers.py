"""Gym shim against ManiSkill's own wrappers (PickCube-v1, state obs, CPU sim).

One process, one ManiSkill env per scenario: ManiSkill's wrapper and ours wrap
the same gym env (wrappers are thin, so the physics work is identical), run the
same pre-generated actions and reset with the same seeds when an episode ends
(PickCube-v1's 50-step limit), as a user loop does. Each round starts from the
same seeded reset (untimed) and runs every contender once, in rotating order
(``common.interleave``);
a ``raw`` loop on the gym env itself is timed alongside for the absolute overhead.

On a shared machine wall time swings by tens of percent from round to round, so
each round records both wall time and this process's CPU time
(``time.process_time``, all threads; not inflated by other processes taking
the cores), and the ratio reported is the median over rounds of the per-round
ratio ours / ManiSkill (adjacent runs see the same machine state), next to the
ratio of the median times.

Scenarios:

- ``CPUGymWrapper()``: defaults; numpy actions in, numpy / python out;
- ``CPUGymWrapper(ignore_terminations=True, record_metrics=True)``: the
  evaluation setting (episode metrics every step);
- ``ActionRepeatWrapper(repeat=2)`` and ``(repeat=3)``: batched torch actions,
  a step is one outer step.

``--replay`` times the wrappers' own work: the env's outputs (its first 50 steps from the seeded
reset, recorded once) are replayed, so a step or reset of the env costs a list lookup and the
physics' CPU time and its noise on a shared machine (milliseconds against the wrappers' tens of
microseconds) drop out; the ``raw`` row is then the loop alone.

Run: ``python -m benchmarks.bench_wrappers [--rounds 30] [--steps 100] [--replay] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import warnings

import torch

from benchmarks.common import Contender, Result, interleave, make_actions, paired_ratio
from benchmarks.machine import machine_line, save_json

warnings.filterwarnings("ignore")

TARGET = 1.05
SEED = 0


def _loop_unbatched(env, actions, seeds):
    """A gymnasium user loop: step, reset (seeded) when terminated or truncated."""

    def run():
        step, reset, it = env.step, env.reset, iter(seeds)
        for a in actions:
            _, _, terminated, truncated, _ = step(a)
            if terminated or truncated:
                reset(seed=next(it))
        return len(actions)

    return run


def _loop_batched(env, actions, seeds):
    """A batched-torch user loop: step, reset (seeded) when any env is done."""

    def run():
        step, reset, it = env.step, env.reset, iter(seeds)
        for a in actions:
            _, _, terminated, truncated, _ = step(a)
            if (terminated | truncated).any():
                reset(seed=next(it))
        return len(actions)

    return run


class _Replay:
    """Makes a gym wrapper that replays ``env``'s outputs from a seeded reset (see ``--replay``)."""

    @staticmethod
    def wrap(env, actions, n: int = 50):
        import gymnasium as gym

        first = env.reset(seed=SEED)
        steps = [env.step(torch.as_tensor(a[None])) for a in actions[:n]]

        class Replay(gym.Wrapper):  # a gym.Wrapper: the shims still find the ManiSkill env under it
            i = 0

            def step(self, action):
                out = steps[self.i % n]
                self.i += 1
                return out

            def reset(self, **kwargs):
                self.i = 0
                return first

        return Replay(env)


def table(times: dict[str, Result], base: str = "ManiSkill") -> str:
    rows = [
        "| contender | median CPU us/step | median wall us/step | ratio to ManiSkill (paired CPU) "
        "| ratio (paired wall) | ratio of median CPU |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, t in times.items():
        med_cpu = statistics.median(t.per_unit_cpu)
        rows.append(
            f"| {name} | {1e6 * med_cpu:.1f} | {1e6 * statistics.median(t.per_unit_wall):.1f} | "
            f"{paired_ratio(times, name, base):.3f}x | {paired_ratio(times, name, base, 'wall'):.3f}x | "
            f"{med_cpu / statistics.median(times[base].per_unit_cpu):.3f}x |"
        )
    return "\n".join(rows)


def scenario(kind: str, steps: int, rounds: int, warmup: int, replay: bool = False, **kwargs) -> dict[str, Result]:
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    from mani_skill.utils import wrappers as ms_wrappers

    from maniskill_torchrl import wrappers as our_wrappers

    env = gym.make("PickCube-v1", num_envs=1, obs_mode="state")  # 50-step episodes
    seeds = list(range(SEED + 1, SEED + 1 + steps))
    if replay:
        env = _Replay.wrap(env, make_actions(env.unwrapped.single_action_space, 50, seed=1))
    if kind == "cpu":
        ms = ms_wrappers.CPUGymWrapper(env, **kwargs)
        ours = our_wrappers.CPUGymWrapper(env, **kwargs)
        actions = [a.numpy() for a in make_actions(ms.action_space, steps, seed=1)]
        loop = _loop_unbatched
        raw_actions = [a[None] for a in actions]
    else:
        ms = ms_wrappers.ActionRepeatWrapper(env, **kwargs)
        ours = our_wrappers.ActionRepeatWrapper(env, **kwargs)
        actions = [a[None] for a in make_actions(env.unwrapped.single_action_space, steps, seed=1)]
        loop = _loop_batched
        raw_actions = actions

    def setup():
        env.reset(seed=SEED)

    contenders = [
        Contender("ManiSkill", loop(ms, actions, seeds), setup),
        Contender("maniskill_torchrl", loop(ours, actions, seeds), setup),
    ]
    if kind == "cpu":  # the same physics without any wrapper (ActionRepeat's raw work is 2-3 steps)
        contenders.append(Contender("raw env (no wrapper)", _loop_batched(env, raw_actions, seeds), setup))
    res = interleave(contenders, rounds=rounds, warmup=warmup, clock="cpu")
    env.close()
    return res


SCENARIOS = [
    ("CPUGymWrapper()", "cpu", {}),
    (
        "CPUGymWrapper(ignore_terminations=True, record_metrics=True)",
        "cpu",
        {"ignore_terminations": True, "record_metrics": True},
    ),
    ("ActionRepeatWrapper(repeat=2)", "repeat", {"repeat": 2}),
    ("ActionRepeatWrapper(repeat=3)", "repeat", {"repeat": 3}),
]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=30)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--steps", type=int, default=100, help="wrapper steps per contender per round")
    p.add_argument("--only", default=None, help="run the scenarios whose name contains this")
    p.add_argument("--replay", action="store_true", help="replay the env's outputs: the wrappers' own work")
    p.add_argument("--json", default=None, help="write the per-round times here")
    args = p.parse_args(argv)

    torch.set_num_threads(1)
    replayed = ", env outputs replayed" if args.replay else ""
    print(f"bench_wrappers: PickCube-v1 state, CPU sim{replayed}, {args.steps} steps x {args.rounds} rounds")
    print(machine_line())
    payload, summary = {}, []
    for name, kind, kwargs in SCENARIOS:
        if args.only and args.only not in name:
            continue
        res = scenario(kind, args.steps, args.rounds, args.warmup, args.replay, **kwargs)
        print(f"\n### {name}\n")
        print(table(res))
        r = paired_ratio(res, "maniskill_torchrl", "ManiSkill")
        diff = res["maniskill_torchrl"].median - res["ManiSkill"].median  # the CPU clock scores
        summary.append((name, r, 1e6 * diff))
        payload[name] = {k: {"wall_s": v.per_unit_wall, "cpu_s": v.per_unit_cpu} for k, v in res.items()}

    print(
        "\n| shim class vs ManiSkill's | ratio (median of paired CPU-time ratios) | CPU us/step difference | target |"
    )
    print("|---|---:|---:|---|")
    for name, r, diff in summary:
        print(f"| {name} | {r:.3f}x | {diff:+.1f} | {'ok' if r <= TARGET else 'OVER'} (<= {TARGET:.2f}x) |")
    if args.json:
        save_json(args.json, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
