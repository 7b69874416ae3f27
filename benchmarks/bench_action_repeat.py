"""ActionRepeat: overhead against ManiSkill's ActionRepeatWrapper, and physics steps saved by partial steps.

One process, contenders timed round-robin by :mod:`common` (medians over rounds, ratios of medians).

Scenario "overhead" (PickCube-v1, state obs, CPU sim, repeat 3, no episode end within a round):
one ManiSkill env shared by the contenders (same physics work: seeded reset before every round,
the same pre-generated torch actions):

- ``ActionRepeatWrapper``: ``mani_skill.utils.wrappers.action_repeat.ActionRepeatWrapper(env, 3).step(a)``;
- ``ActionRepeat``: ``TransformedEnv(ManiSkillWrapper(env), ActionRepeat(3))``, ``td.set("action", a);
  env.step(td)`` reusing one td, as a collector writes its policy's action;
- ``FrameSkipTransform`` (for reference): TorchRL's frame skip, same loop.

Scenario "partial steps" (``ParallelEnv(4)`` of MS-CartpoleBalance-v1 + ``CPUUnbatch``, repeat 8,
``step_and_maybe_reset`` as collectors call it; random actions make episodes fail after a few
to a few tens of steps, so envs end at different inner steps):

- physics steps counted from ``elapsed_steps``: env ``i`` took ``k_i`` inner steps in an outer step;
  with partial steps the workers do ``sum_i k_i`` physics steps, stepping every env as long as
  one runs costs ``n_envs * max_i k_i``;
- both timed: ``ActionRepeat`` (finished envs skipped through ``"_step"``) against the same
  transform with skipping turned off (finished envs stepped, results discarded).

Run: ``python benchmarks/bench_action_repeat.py [--rounds 9] [--steps 100] [--json out.json]``.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import Contender, interleave, machine_line, ratio, report, save_json  # noqa: E402

warnings.filterwarnings("ignore")

TARGET = 1.10
SEED = 0


def make_actions(space, n: int, batch: tuple = (1,), seed: int = 0) -> list[torch.Tensor]:
    """``n`` uniform float32 actions of shape ``[*batch, *space.shape]`` within the space's bounds."""
    g = torch.Generator().manual_seed(seed)
    low = torch.as_tensor(space.low, dtype=torch.float32)
    high = torch.as_tensor(space.high, dtype=torch.float32)
    return [low + (high - low) * torch.rand(batch + tuple(space.shape), generator=g) for _ in range(n)]


# ----------------------------------------------------------------------------- overhead
def scenario_overhead(steps: int, repeat: int, rounds: int, warmup: int, verbose: bool):
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper
    from torchrl.envs import FrameSkipTransform, TransformedEnv

    from maniskill_torchrl import ActionRepeat, ManiSkillWrapper

    gym_env = gym.make("PickCube-v1", num_envs=1, obs_mode="state", max_episode_steps=10 * steps * repeat)
    oracle = ActionRepeatWrapper(gym_env, repeat)
    base = ManiSkillWrapper(gym_env)
    ours = TransformedEnv(base, ActionRepeat(repeat))
    frameskip = TransformedEnv(base, FrameSkipTransform(repeat))
    actions = make_actions(gym_env.unwrapped.single_action_space, steps)
    state = {}

    def setup_oracle():
        oracle.reset(seed=SEED)

    def run_oracle():
        step = oracle.step
        for a in actions:
            step(a)
        return len(actions)

    def setup(env):
        def fn():
            state["td"] = env.reset(seed=SEED)

        return fn

    def runner(env):
        def fn():
            td, step = state["td"], env.step
            for a in actions:
                td.set("action", a)
                step(td)
            return len(actions)

        return fn

    results = interleave(
        [
            Contender("ActionRepeatWrapper", run_oracle, setup_oracle),
            Contender("ActionRepeat", runner(ours), setup(ours)),
            Contender("FrameSkipTransform", runner(frameskip), setup(frameskip)),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
    )
    gym_env.close()
    return results


# ----------------------------------------------------------------------------- partial steps
def _make_cartpole():
    from torchrl.envs import TransformedEnv

    from maniskill_torchrl import ManiSkillEnv
    from maniskill_torchrl.transforms import CPUUnbatch

    return TransformedEnv(ManiSkillEnv("MS-CartpoleBalance-v1", obs_mode="state"), CPUUnbatch())


def scenario_partial(steps: int, repeat: int, n_envs: int, rounds: int, warmup: int, verbose: bool):
    from torchrl.envs import ParallelEnv, TransformedEnv

    from maniskill_torchrl import ActionRepeat

    class StepAll(ActionRepeat):
        """ActionRepeat with skipping turned off: finished envs are stepped, their results discarded."""

        def _parent_info(self):
            info = super()._parent_info()
            info.partial = False
            return info

    penv = ParallelEnv(n_envs, _make_cartpole)
    skip = TransformedEnv(penv, ActionRepeat(repeat))
    step_all = TransformedEnv(penv, StepAll(repeat))
    import gymnasium as gym

    actions = make_actions(gym.spaces.Box(-1, 1, (1,)), steps, batch=(n_envs,), seed=1)
    state = {}
    counts = {}

    def setup(env):
        def fn():
            env.set_seed(SEED)
            state["td"] = env.reset()

        return fn

    def runner(env, name):
        def fn():
            td, smr = state["td"], env.step_and_maybe_reset
            taken = []
            for a in actions:
                before = td.get("elapsed_steps")
                td.set("action", a)
                out, td = smr(td)
                taken.append(out.get(("next", "elapsed_steps")) - before)
            counts[name] = torch.stack(taken).long()  # [outer steps, n_envs]: inner steps per env
            return len(actions)

        return fn

    results = interleave(
        [
            Contender("ActionRepeat (skips)", runner(skip, "skip"), setup(skip)),
            Contender("stepping all", runner(step_all, "all"), setup(step_all)),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
    )
    penv.close()
    # Same seeds, same actions: both contenders saw the same episodes.
    assert torch.equal(counts["skip"], counts["all"]), "the two runs should see the same episodes"
    k = counts["skip"]
    physics = {
        "outer_steps": k.shape[0],
        "n_envs": n_envs,
        "repeat": repeat,
        "with_partial_steps": int(k.sum()),
        "stepping_all": int(k.max(-1).values.sum() * n_envs),
        "without_early_stop": k.shape[0] * n_envs * repeat,
    }
    return results, physics


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=9)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--steps", type=int, default=100, help="outer steps per contender per round")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--partial-steps", type=int, default=40, help="outer steps per round, ParallelEnv scenario")
    p.add_argument("--partial-repeat", type=int, default=8)
    p.add_argument("--envs", type=int, default=4)
    p.add_argument("--skip-partial", action="store_true", help="only the overhead scenario")
    p.add_argument("--json", default=None, help="write the per-round times here")
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)

    torch.set_num_threads(1)
    print(machine_line())
    payload = {}

    if not args.skip_partial:  # ParallelEnv first: its workers start before SAPIEN loads here
        res_p, physics = scenario_partial(
            args.partial_steps, args.partial_repeat, args.envs, args.rounds, args.warmup, args.verbose
        )
        payload["partial"] = {k: v.as_dict() for k, v in res_p.items()}
        payload["physics_steps"] = physics

    print(
        f"\nscenario: overhead, PickCube-v1 state, repeat {args.repeat}, "
        f"{args.steps} outer steps x {args.rounds} rounds (us per outer step)"
    )
    res = scenario_overhead(args.steps, args.repeat, args.rounds, args.warmup, args.verbose)
    print(report(res, baseline="ActionRepeatWrapper"))
    r = ratio(res, "ActionRepeat", "ActionRepeatWrapper")
    payload["overhead"] = {k: v.as_dict() for k, v in res.items()}
    verdict = "within" if r <= TARGET else "OVER"
    print(f"\nActionRepeat / ActionRepeatWrapper = {r:.3f}x (target <= {TARGET:.2f}x: {verdict})")

    if not args.skip_partial:
        ph = physics
        print(
            f"\nscenario: partial steps, ParallelEnv({ph['n_envs']}) of MS-CartpoleBalance-v1, "
            f"repeat {ph['repeat']}, {ph['outer_steps']} outer steps (step_and_maybe_reset), "
            f"x {args.rounds} rounds (us per outer step)"
        )
        print(report(res_p, baseline="stepping all"))
        saved = 1 - ph["with_partial_steps"] / ph["stepping_all"]
        print("\n| physics steps per round | count |")
        print("|---|---:|")
        print(f"| with partial steps (ActionRepeat) | {ph['with_partial_steps']} |")
        print(f"| stepping every env while any runs | {ph['stepping_all']} |")
        print(f"| no early stop (n_envs x repeat x outer steps) | {ph['without_early_stop']} |")
        print(f"\nphysics steps saved by partial steps: {saved:.1%}")
        payload["physics_steps"]["saved_fraction"] = saved
    if args.json:
        save_json(args.json, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
