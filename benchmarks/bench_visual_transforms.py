"""The transforms of ManiSkill's other wrappers against the wrappers' own work, on the same data.

Each pair does one wrapper's job on one step's outputs, the env's step left out (the same for both):

- ``flatten_rgbd``: ``FlattenRGBDObservationWrapper.observation`` (on a fresh top-level copy of the raw
  observation dict, which it pops from) against ``FlattenRGBD._call`` on the env's TensorDict of that step
  (PushCube-v1, ``obs_mode="rgbd"``, one camera at ``--size`` pixels, one CPU env);
- ``flatten_action``: ``FlattenActionSpaceWrapper.action`` against ``FlattenActionSpace._inv_call`` (a new
  TensorDict holding the flat action each call, as a step's input is), TwoRobotPickCube-v1;
- ``frame_stack``: ``FrameStack.step``'s stacking (append, then ``observation``) against the recipe,
  ``UnsqueezeTransform`` + ``CatFrames`` (``Compose._call``), PickCube-v1 state, 3 frames.

``--stack``: whole stacks instead, env step included (the target: each transform at most 1.05x ManiSkill's
wrapper on the same stack): ``TransformedEnv(ManiSkillEnv(...), transform).step`` against
``wrapper(gym.make(...)).step`` on the same task, options and actions, each env reset (seeded, untimed) before
its round; and ``--what cached_reset`` (``--task``, ``--obs``, ``--size``): a reset's cost per env, plain
(``env.reset()`` of ``ManiSkillEnv`` / ManiSkill's ``reset()``) against cached (``CachedReset(num_resets=16)`` /
``CachedResetWrapper``), on one CPU env each.

Interleaved (``common.interleave``), this process's CPU time per call, medians over rounds, ratios of
medians and paired ratios. Run: ``python -m benchmarks.bench_visual_transforms [--rounds 15] [--calls 2000]
[--stack [--calls 40]] [--what flatten_rgbd flatten_action frame_stack cached_reset]``.
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


def _gym(task: str, **kwargs):
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401

    return gym.make(task, num_envs=1, sim_backend="cpu", render_backend="cpu", **kwargs)


def _library(task: str, transform, **kwargs):
    from torchrl.envs import TransformedEnv

    from maniskill_torchrl import ManiSkillEnv

    env = ManiSkillEnv(task, sim_backend="cpu", **kwargs)
    return env if transform is None else TransformedEnv(env, transform)


def _step_pair(name: str, wrapper, env, action: torch.Tensor, calls: int, gym_action=None) -> list[Contender]:
    """``calls`` steps of ManiSkill's wrapper and of the library's transformed env per round, each reset
    (seeded, untimed) before its round."""
    now = {}
    gym_action = action if gym_action is None else gym_action

    def theirs() -> int:
        for _ in range(calls):
            wrapper.step(gym_action)
        return calls

    def ours() -> int:
        td = now["td"]
        for _ in range(calls):
            td = env.step(td.set("action", action))["next"]
        return calls

    def reset_ours() -> None:
        now["td"] = env.reset(seed=0)

    return [
        Contender(f"{name}: ManiSkill", theirs, setup=lambda: wrapper.reset(seed=0)),
        Contender(f"{name}: library", ours, setup=reset_ours),
    ]


def _stack_flatten_rgbd(size: int, calls: int) -> list[Contender]:
    from mani_skill.utils.wrappers import FlattenRGBDObservationWrapper

    from maniskill_torchrl.transforms import FlattenRGBD

    kwargs = dict(obs_mode="rgbd", sensor_configs={"width": size, "height": size}, max_episode_steps=10_000)
    wrapper = FlattenRGBDObservationWrapper(_gym("PushCube-v1", **kwargs))
    env = _library("PushCube-v1", FlattenRGBD(), **kwargs)
    return _step_pair("flatten_rgbd stack", wrapper, env, torch.zeros(env.action_spec.shape), calls)


def _stack_flatten_action(calls: int) -> list[Contender]:
    from mani_skill.utils.wrappers import FlattenActionSpaceWrapper

    from maniskill_torchrl.transforms import FlattenActionSpace

    kwargs = dict(obs_mode="state", max_episode_steps=10_000)
    wrapper = FlattenActionSpaceWrapper(_gym("TwoRobotPickCube-v1", **kwargs))
    env = _library("TwoRobotPickCube-v1", FlattenActionSpace(), **kwargs)
    return _step_pair("flatten_action stack", wrapper, env, torch.zeros(1, 16), calls)


def _stack_frame_stack(calls: int) -> list[Contender]:
    from mani_skill.utils.wrappers import FrameStack
    from torchrl.envs import CatFrames, Compose, UnsqueezeTransform

    kwargs = dict(obs_mode="state", max_episode_steps=10_000)
    wrapper = FrameStack(_gym("PickCube-v1", **kwargs), 3)
    recipe = Compose(UnsqueezeTransform(-2, in_keys=["observation"]), CatFrames(3, dim=-2, in_keys=["observation"]))
    env = _library("PickCube-v1", recipe, **kwargs)
    return _step_pair("frame_stack stack", wrapper, env, torch.zeros(env.action_spec.shape), calls)


def _cached_reset(task: str, obs: str, size: int, calls: int, num_resets: int = 16) -> list[Contender]:
    """A reset's cost per env: plain and cached, ManiSkill's and the library's, one CPU env each (the caches
    filled before timing)."""
    from mani_skill.utils.wrappers import CachedResetWrapper

    from maniskill_torchrl.transforms import CachedReset

    kwargs = dict(obs_mode=obs)
    if obs != "state":
        kwargs["sensor_configs"] = {"width": size, "height": size}
    plain_gym, plain = _gym(task, **kwargs), _library(task, None, **kwargs)
    cached_gym = CachedResetWrapper(_gym(task, **kwargs), config=dict(num_resets=num_resets, seed=0))
    cached = _library(task, CachedReset(num_resets=num_resets, seed=0), **kwargs)
    plain_gym.reset(seed=0)
    plain.set_seed(0)
    cached.reset()  # fills the cache

    def resets(reset):
        def run() -> int:
            for _ in range(calls):
                reset()
            return calls

        return run

    return [
        Contender("reset: ManiSkill", resets(plain_gym.reset)),
        Contender("reset: CachedResetWrapper", resets(cached_gym.reset)),
        Contender("reset: ManiSkillEnv", resets(plain.reset)),
        Contender("reset: CachedReset", resets(cached.reset)),
    ]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=15, help="timed rounds (default 15)")
    p.add_argument("--calls", type=int, default=2000, help="calls per round (default 2000; steps or resets)")
    p.add_argument("--size", type=int, default=128, help="camera pixels for flatten_rgbd (default 128)")
    p.add_argument("--stack", action="store_true", help="whole stacks, env step included")
    what = ("flatten_rgbd", "flatten_action", "frame_stack", "cached_reset")
    p.add_argument("--what", nargs="+", choices=what, default=list(what[:3]), help="the pairs (default the first 3)")
    p.add_argument("--task", default="PickCube-v1", help="cached_reset's task (default PickCube-v1)")
    p.add_argument("--obs", default="state", help="cached_reset's obs_mode (default state)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    print(machine_line())
    makers = {
        "flatten_rgbd": (lambda: _stack_flatten_rgbd(args.size, args.calls))
        if args.stack
        else (lambda: _flatten_rgbd(args.size, args.calls)),
        "flatten_action": (lambda: _stack_flatten_action(args.calls))
        if args.stack
        else (lambda: _flatten_action(args.calls)),
        "frame_stack": (lambda: _stack_frame_stack(args.calls)) if args.stack else (lambda: _frame_stack(args.calls)),
        "cached_reset": lambda: _cached_reset(args.task, args.obs, args.size, args.calls),
    }
    for name in args.what:
        contenders = makers[name]()
        results = interleave(contenders, rounds=args.rounds, clock="cpu")
        print(f"\n{name}{' (stack)' if args.stack and name != 'cached_reset' else ''}\n" + report(results, unit="call"))
        pairs = [(contenders[1].name, contenders[0].name)]
        if name == "cached_reset":
            pairs = (
                [(c[3].name, c[2].name), (c[1].name, c[0].name), (c[3].name, c[1].name)] if (c := contenders) else []
            )
        for a, b in pairs:
            print(f"paired ratio (cpu) {a} / {b}: {paired_ratio(results, a, b):.3f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
