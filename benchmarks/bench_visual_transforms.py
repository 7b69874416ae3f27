"""The transforms of ManiSkill's other wrappers against the wrappers' own work, on the same data.

Each pair does one wrapper's job on one step's outputs, the env's step left out (the same for both):

- ``flatten_rgbd``: ``FlattenRGBDObservationWrapper.observation`` (on a fresh top-level copy of the raw
  observation dict, which it pops from) against ``FlattenRGBD._call`` on the env's TensorDict of that step
  (PushCube-v1, ``obs_mode="rgbd"``, one camera at ``--size`` pixels, one CPU env);
- ``flatten_action``: ``FlattenActionSpaceWrapper.action`` against ``FlattenActionSpace._inv_call`` (a new
  TensorDict holding the flat action each call, as a step's input is), TwoRobotPickCube-v1;
- ``frame_stack``: ``FrameStack.step``'s stacking (append, then ``observation``) against the recipe,
  ``UnsqueezeTransform`` + ``CatFrames`` (``Compose._call``), PickCube-v1 state, 3 frames.

Interleaved (``common.interleave``), this process's CPU time per call, medians over rounds, ratios of
medians and paired ratios. Run: ``python -m benchmarks.bench_visual_transforms [--rounds 15] [--calls 2000]``.
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDict

from benchmarks.common import Contender, interleave, paired_ratio, report
from benchmarks.machine import machine_line


def _flatten_rgbd(size: int, calls: int) -> list[Contender]:
    import gymnasium as gym
    from mani_skill.utils.wrappers import FlattenRGBDObservationWrapper

    from maniskill_torchrl import ManiSkillEnv
    from maniskill_torchrl.transforms import FlattenRGBD

    sensors = {"width": size, "height": size}
    kwargs = dict(obs_mode="rgbd", sim_backend="cpu", render_backend="cpu", sensor_configs=sensors)
    wrapper = FlattenRGBDObservationWrapper(gym.make("PushCube-v1", num_envs=1, **kwargs))
    raw, _ = wrapper.env.reset(seed=0)
    env = ManiSkillEnv("PushCube-v1", **{k: v for k, v in kwargs.items() if k != "render_backend"})
    transform = FlattenRGBD()
    transform.transform_observation_spec(env.observation_spec.clone())  # the layout, once, as in an env
    env.set_seed(0)
    td = env.reset()

    def theirs() -> int:
        for _ in range(calls):
            wrapper.observation(dict(raw))
        return calls

    def ours() -> int:
        for _ in range(calls):
            transform._call(td)
        return calls

    return [Contender("flatten_rgbd: ManiSkill", theirs), Contender("flatten_rgbd: FlattenRGBD", ours)]


def _flatten_action(calls: int) -> list[Contender]:
    import gymnasium as gym
    from mani_skill.utils.wrappers import FlattenActionSpaceWrapper
    from torchrl.envs import TransformedEnv

    from maniskill_torchrl import ManiSkillEnv
    from maniskill_torchrl.transforms import FlattenActionSpace

    wrapper = FlattenActionSpaceWrapper(
        gym.make("TwoRobotPickCube-v1", num_envs=1, obs_mode="state", sim_backend="cpu", render_backend="cpu")
    )
    env = TransformedEnv(ManiSkillEnv("TwoRobotPickCube-v1", obs_mode="state", sim_backend="cpu"), FlattenActionSpace())
    _ = env.action_spec  # the layout, once
    transform = env.transform
    flat = torch.zeros(1, 16)

    def theirs() -> int:
        for _ in range(calls):
            wrapper.action(flat)
        return calls

    def ours() -> int:
        for _ in range(calls):
            transform._inv_call(TensorDict({"action": flat}, [1]))
        return calls

    return [Contender("flatten_action: ManiSkill", theirs), Contender("flatten_action: FlattenActionSpace", ours)]


def _frame_stack(calls: int) -> list[Contender]:
    import gymnasium as gym
    from mani_skill.utils.wrappers import FrameStack
    from torchrl.envs import CatFrames, Compose, TransformedEnv, UnsqueezeTransform

    from maniskill_torchrl import ManiSkillEnv

    made = gym.make("PickCube-v1", num_envs=1, obs_mode="state", sim_backend="cpu", render_backend="cpu")
    stack = FrameStack(made, 3)
    obs, _ = stack.reset(seed=0)
    frame = stack.frames[-1]
    env = TransformedEnv(
        ManiSkillEnv("PickCube-v1", obs_mode="state", sim_backend="cpu"),
        Compose(UnsqueezeTransform(-2, in_keys=["observation"]), CatFrames(3, dim=-2, in_keys=["observation"])),
    )
    env.set_seed(0)
    td = env.reset()
    transform = env.transform
    raw = TensorDict({"observation": frame}, [1])

    def theirs() -> int:
        for _ in range(calls):
            stack.frames.append(frame)
            stack.observation(None)
        return calls

    def ours() -> int:
        for _ in range(calls):
            transform._call(raw.clone(False))
        return calls

    del td
    return [Contender("frame_stack: ManiSkill", theirs), Contender("frame_stack: CatFrames recipe", ours)]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=15, help="timed rounds (default 15)")
    p.add_argument("--calls", type=int, default=2000, help="calls per round (default 2000)")
    p.add_argument("--size", type=int, default=128, help="camera pixels for flatten_rgbd (default 128)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    print(machine_line())
    for name, contenders in (
        ("flatten_rgbd", _flatten_rgbd(args.size, args.calls)),
        ("flatten_action", _flatten_action(args.calls)),
        ("frame_stack", _frame_stack(args.calls)),
    ):
        results = interleave(contenders, rounds=args.rounds, clock="cpu")
        print(f"\n{name}\n" + report(results, unit="call"))
        print(f"paired ratio (cpu): {paired_ratio(results, contenders[1].name, contenders[0].name):.3f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
