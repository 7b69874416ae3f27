"""What copying ManiSkill's observations costs, where ManiSkillWrapper copies them.

On the GPU sim (and the CPU sim rendering with ``sapien_cuda``) ManiSkill hands out buffers that
its next step or render overwrites, so the wrapper copies every observation entry it returns
(``maniskill_layout._LEAVES``, the ``_clone`` leaf). This times that copy on the CPU, with the
wrapper's own code, on PickCube-v1's real ``obs_mode="rgb"`` observation at 128 x 128 (agent and
extra state, camera parameters, ``sensor_data/base_camera/rgb`` uint8), tiled to the batch:

- ``as is``: the TensorDict built from ManiSkill's tensors without a copy (the CPU sim);
- ``copied``: the same with every entry cloned first (the GPU sim's path).

Beside them, one CPU-sim ``env.step`` of that task at batch 1 (128 px rgb, rendered with
lavapipe) gives the scale. Contenders interleaved (``common.interleave``), this process's CPU time,
medians over rounds.

Run: ``python benchmarks/bench_obs_copy.py [--batches 2 64] [--rounds 31]``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import Contender, interleave, make_actions, report  # noqa: E402
from machine import machine_line  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[2, 64])
    parser.add_argument("--size", type=int, default=128, help="camera width and height")
    parser.add_argument("--rounds", type=int, default=31)
    parser.add_argument("--calls", type=int, default=20, help="copies per round")
    args = parser.parse_args(argv)

    warnings.filterwarnings("ignore")
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    import torch

    from maniskill_torchrl._private import new_tensordict
    from maniskill_torchrl.maniskill_layout import _clone, _mapped

    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    torch.set_num_threads(1)
    print(machine_line())
    cam = dict(width=args.size, height=args.size)
    env = gym.make("PickCube-v1", num_envs=1, obs_mode="rgb", sensor_configs=cam)
    obs, _ = env.reset(seed=0)
    actions = make_actions(env.unwrapped.single_action_space, args.calls, batch=(1,))

    def tiled(x, b):
        if isinstance(x, torch.Tensor):
            return x.expand(b, *x.shape[1:]).contiguous()
        return {k: tiled(v, b) for k, v in x.items()}

    def step() -> int:
        for a in actions:
            env.step(a)
        return len(actions)

    for b in args.batches:
        batch_obs = tiled(obs, b)
        size = batch_obs["sensor_data"]["base_camera"]["rgb"]
        print(f"\nbatch {b}: rgb {tuple(size.shape)} uint8, {size.numel() / 2**20:.2f} MiB of pixels per step")

        def as_is(o=batch_obs, b=b) -> int:
            for _ in range(args.calls):
                new_tensordict(dict(o), batch_size=[b])
            return args.calls

        def copied(o=batch_obs, b=b) -> int:
            for _ in range(args.calls):
                new_tensordict(_mapped(o, _clone), batch_size=[b])
            return args.calls

        contenders = [Contender("as is", as_is), Contender("copied", copied)]
        if b == args.batches[0]:
            contenders.append(Contender("CPU-sim env.step, batch 1", step, setup=lambda: env.reset(seed=0)))
        results = interleave(contenders, rounds=args.rounds, warmup=2, clock="cpu")
        print(report(results, baseline="as is", unit="call", difference=True))
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
