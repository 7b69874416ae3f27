"""CPU cost of one ManiSkill CPU-sim step under torch's grad modes, paired in one process.

Why ``CPUVectorEnv`` workers step ManiSkill under :func:`torch.inference_mode`: a ManiSkill
step on the CPU sim is mostly Python and small torch ops (poses, controllers, ``evaluate``),
each of which pays autograd's bookkeeping unless inference mode is on. One raw env per
mode (``gym.make(id, num_envs=1, obs_mode="state")``, the same seeded random actions), always
used in its own mode, reset included (``grad``: torch's default, as in ManiSkill's own
``CPUGymWrapper`` workers; ``no_grad``; ``inference``), is stepped in blocks of ``--block``
steps, the modes taking turns block by block, so a busy machine slows every mode alike.
Reported: the thread's CPU time per step, median over blocks, and its ratio to ``grad``. One
env per mode because an env used under inference mode holds inference tensors, which a
later call outside inference mode may not update (PickCube-v1's ``reset`` raises).

Run: ``python -m benchmarks.bench_inference_mode [--env-id PickCube-v1] [--blocks 40] [--block 25]``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import statistics
import sys
import time
import warnings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="PickCube-v1")
    parser.add_argument("--blocks", type=int, default=40, help="blocks per mode (the first 4 are warm-up)")
    parser.add_argument("--block", type=int, default=25, help="steps per block")
    args = parser.parse_args(argv)

    warnings.filterwarnings("ignore")
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    import torch

    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    contexts = {"grad": contextlib.nullcontext, "no_grad": torch.no_grad, "inference": torch.inference_mode}
    envs = {m: gym.make(args.env_id, num_envs=1, obs_mode="state", max_episode_steps=50) for m in contexts}
    for mode, env in envs.items():
        with contexts[mode]():
            env.reset(seed=0)
    space = envs["grad"].action_space
    low, high = torch.as_tensor(space.low), torch.as_tensor(space.high)
    gen = torch.Generator().manual_seed(0)
    per_step: dict[str, list[float]] = {m: [] for m in contexts}
    for _ in range(args.blocks):
        actions = [low + (high - low) * torch.rand(low.shape, generator=gen) for _ in range(args.block)]
        for mode, ctx in contexts.items():
            env = envs[mode]
            t0 = time.thread_time()
            with ctx():
                for action in actions:
                    _, _, terminated, truncated, _ = env.step(action)
                    if (terminated | truncated).any():
                        env.reset()
            per_step[mode].append((time.thread_time() - t0) / args.block * 1e3)
    base = statistics.median(per_step["grad"][4:])
    print(f"{args.env_id}, {args.blocks - 4} blocks x {args.block} steps per mode, thread CPU per step:")
    for mode, values in per_step.items():
        med = statistics.median(values[4:])
        print(f"  {mode:10s} {med:.3f} ms  ({med / base:.3f}x of grad)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
