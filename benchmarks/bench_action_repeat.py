"""ActionRepeat: overhead against ManiSkill's ActionRepeatWrapper, and physics steps saved by partial steps.

One process, contenders timed round-robin by :mod:`common` (medians over rounds, ratios of medians).

Scenario "overhead" (PickCube-v1, state obs, CPU sim, repeat 3, no episode end within a round):
one ManiSkill env shared by the contenders (same physics work: seeded reset before every round,
the same pre-generated torch actions):

- ``ActionRepeatWrapper``: ``mani_skill.utils.wrappers.action_repeat.ActionRepeatWrapper(env, 3).step(a)``;
- ``ActionRepeat``: ``TransformedEnv(ManiSkillWrapper(env), ActionRepeat(3))``, ``td.set("action", a);
  env.step(td); td.pop("next")`` reusing one td: a collector writes its policy's action into a td
  that carries no ``"next"`` (its shuttle is the output of ``step_mdp``);
- ``ActionRepeat, td keeps "next"``: the same without the pop: TorchRL's ``EnvBase.step`` and
  ``TransformedEnv._step`` then merge the stale ``"next"`` into each new one (their cost, paid
  once per outer step);
- ``FrameSkipTransform`` (for reference): TorchRL's frame skip, as ``ActionRepeat``.

Scored on this process's CPU time by default (``--clock wall`` for wall time); both are
reported: on a machine shared with other jobs wall time also counts waiting for a core.

Scenario "partial steps" (``ParallelEnv(4)`` of MS-CartpoleBalance-v1 + ``CPUUnbatch``, repeat 8,
``step_and_maybe_reset`` as collectors call it; random actions make episodes fail after a few
to a few tens of steps, so envs end at different inner steps):

- physics steps counted inside each worker (a transform counting its env's steps) and checked
  against ``elapsed_steps``: env ``i`` took ``k_i`` inner steps in an outer step; with partial
  steps the workers do ``sum_i k_i`` physics steps, stepping every env as long as one runs costs
  ``n_envs * max_i k_i``;
- both timed: ``ActionRepeat`` (finished envs skipped through ``"_step"``) against the same
  transform with skipping turned off (finished envs stepped, results discarded).

Run: ``python -m benchmarks.bench_action_repeat [--rounds 9] [--steps 100] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import sys
import warnings

import torch

from benchmarks.common import Contender, interleave, make_actions, ratio, report
from benchmarks.machine import machine_line, save_json

warnings.filterwarnings("ignore")

TARGET = 1.10
SEED = 0


# ----------------------------------------------------------------------------- overhead
def scenario_overhead(steps: int, repeat: int, rounds: int, warmup: int, verbose: bool, clock: str):
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
    actions = make_actions(gym_env.unwrapped.single_action_space, steps, batch=(1,))
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

    def runner(env, keep_next=False):
        def fn():
            td, step = state["td"], env.step
            for a in actions:
                td.set("action", a)
                step(td)
                if not keep_next:
                    td.pop("next")
            return len(actions)

        return fn

    results = interleave(
        [
            Contender("ActionRepeatWrapper", run_oracle, setup_oracle),
            Contender("ActionRepeat", runner(ours), setup(ours)),
            Contender('ActionRepeat, td keeps "next"', runner(ours, keep_next=True), setup(ours)),
            Contender("FrameSkipTransform", runner(frameskip), setup(frameskip)),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock=clock,
    )
    gym_env.close()
    return results


# ----------------------------------------------------------------------------- partial steps
def _counting_transform():
    from torchrl.data import Unbounded
    from torchrl.envs import Transform

    class CountPhysicsSteps(Transform):
        """``"physics_steps"``: the steps this env really took so far (never reset)."""

        def __init__(self):
            super().__init__()
            self.n = 0

        def _step(self, tensordict, next_tensordict):
            self.n += 1
            return next_tensordict.set("physics_steps", torch.tensor(self.n))

        def _reset(self, tensordict, tensordict_reset):
            return tensordict_reset.set("physics_steps", torch.tensor(self.n))

        def transform_observation_spec(self, observation_spec):
            observation_spec["physics_steps"] = Unbounded(
                observation_spec.shape, dtype=torch.int64, device=observation_spec.device
            )
            return observation_spec

    return CountPhysicsSteps()


def _make_cartpole():
    from torchrl.envs import Compose, TransformedEnv

    from maniskill_torchrl import ManiSkillEnv
    from maniskill_torchrl.transforms import CPUUnbatch

    return TransformedEnv(
        ManiSkillEnv("MS-CartpoleBalance-v1", obs_mode="state"),
        Compose(CPUUnbatch(), _counting_transform()),
    )


def scenario_partial(steps: int, repeat: int, n_envs: int, rounds: int, warmup: int, verbose: bool):
    import gymnasium as gym
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

    actions = make_actions(gym.spaces.Box(-1, 1, (1,)), steps, batch=(n_envs,), seed=1)
    state = {}
    taken, physics = {}, {}

    def setup(env):
        def fn():
            env.set_seed(SEED)
            state["td"] = env.reset()

        return fn

    def runner(env, name):
        def fn():
            td, smr = state["td"], env.step_and_maybe_reset
            start = td.get("physics_steps").clone()
            k = []
            for a in actions:
                before = td.get("elapsed_steps")
                td.set("action", a)
                out, td = smr(td)
                k.append(out.get(("next", "elapsed_steps")) - before)
            # Inner steps each env really took per outer step, from elapsed_steps: [outer steps, n_envs].
            taken[name] = torch.stack(k).long()
            # Steps the workers really did, counted inside each worker.
            physics[name] = int((td.get("physics_steps") - start).sum())
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
    assert torch.equal(taken["skip"], taken["all"]), "the two runs should see the same episodes"
    k = taken["skip"]
    counts = {
        "outer_steps": k.shape[0],
        "n_envs": n_envs,
        "repeat": repeat,
        "inner_steps_taken": int(k.sum()),  # from elapsed_steps
        "counted_with_partial_steps": physics["skip"],  # counted in the workers
        "counted_stepping_all": physics["all"],
        "stepping_all_expected": int(k.max(-1).values.sum() * n_envs),
        "without_early_stop": k.shape[0] * n_envs * repeat,
    }
    return results, counts


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=9)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--steps", type=int, default=100, help="outer steps per contender per round")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--partial-steps", type=int, default=40, help="outer steps per round, ParallelEnv scenario")
    p.add_argument("--partial-repeat", type=int, default=8)
    p.add_argument("--envs", type=int, default=4)
    p.add_argument(
        "--clock",
        choices=("cpu", "wall"),
        default="cpu",
        help="the clock that scores the overhead scenario (both are reported)",
    )
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
    res = scenario_overhead(args.steps, args.repeat, args.rounds, args.warmup, args.verbose, args.clock)
    print(report(res, baseline="ActionRepeatWrapper"))
    r = ratio(res, "ActionRepeat", "ActionRepeatWrapper")
    r_other = res["ActionRepeat"].other_median / res["ActionRepeatWrapper"].other_median
    r_next = ratio(res, 'ActionRepeat, td keeps "next"', "ActionRepeatWrapper")
    payload["overhead"] = {k: v.as_dict() for k, v in res.items()}
    other = res["ActionRepeat"].other_clock
    print(
        f"\nActionRepeat / ActionRepeatWrapper = {r:.3f}x {args.clock}, {r_other:.3f}x {other} "
        f"(target <= {TARGET:.2f}x: {'within' if r <= TARGET else 'OVER'}); "
        f'td keeping "next": {r_next:.3f}x {args.clock}'
    )

    if not args.skip_partial:
        ph = physics
        print(
            f"\nscenario: partial steps, ParallelEnv({ph['n_envs']}) of MS-CartpoleBalance-v1, "
            f"repeat {ph['repeat']}, {ph['outer_steps']} outer steps (step_and_maybe_reset), "
            f"x {args.rounds} rounds (us per outer step, wall time)"
        )
        print(report(res_p, baseline="stepping all"))
        saved = 1 - ph["counted_with_partial_steps"] / ph["counted_stepping_all"]
        print("\n| physics steps in one round | count |")
        print("|---|---:|")
        print(f"| inner steps the envs really took (from elapsed_steps) | {ph['inner_steps_taken']} |")
        print(f"| ActionRepeat, partial steps (counted in the workers) | {ph['counted_with_partial_steps']} |")
        print(f"| stepping every env while any runs (counted) | {ph['counted_stepping_all']} |")
        print(f"| stepping every env while any runs (n_envs x max_i k_i) | {ph['stepping_all_expected']} |")
        print(f"| no early stop (n_envs x repeat x outer steps) | {ph['without_early_stop']} |")
        print(f"\nphysics steps saved by partial steps: {saved:.1%}")
        payload["physics_steps"]["saved_fraction"] = saved
    if args.json:
        save_json(args.json, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
