"""Where a batched CPU env's step goes: the engine's per-step trace (issue 37, item 1).

Runs ``CPUVectorEnv(env_id, N, trace_steps=T)`` (the library's batched CPU env, what
``ManiSkillEnv(env_id, num_envs=N, sim_backend="cpu")`` builds) with random actions, a reset at
each episode's end, and prints the medians of the trace's summary per N: the whole step, each
sub-env's wake latency (send to wake) and sim time, the way back (last sim end to collect end),
how often each sub-env was the straggler, and the share of a step a sub-env spends not stepping.

    python -m benchmarks.bench_trace --n 1 2 --steps 500 --out outputs/trace.json
"""

from __future__ import annotations

import argparse
import json
import os

import torch

from benchmarks.machine import machine_info


def trace_one(env_id: str, n: int, steps: int, in_process: bool) -> dict:
    from maniskill_torchrl import CPUVectorEnv

    env = CPUVectorEnv(env_id, n, obs_mode="state", trace_steps=steps, in_process=in_process)
    try:
        env.reset(seed=0)
        low = torch.as_tensor(env.single_action_space.low)
        high = torch.as_tensor(env.single_action_space.high)
        gen = torch.Generator().manual_seed(0)
        for _ in range(steps + 20):  # the first 20 steps warm up and leave the ring
            action = low + (high - low) * torch.rand((n, *low.shape), generator=gen)
            _, _, terminated, truncated, _ = env.step(action)
            done = terminated | truncated
            if done.any():
                env.reset(options={"env_idx": done.nonzero().squeeze(-1)})
        return env.trace()["summary"]
    finally:
        env.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env-id", default="PickCube-v1")
    p.add_argument("--n", type=int, nargs="+", default=[1, 2])
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--workers-only", action="store_true", help="in_process=False: every sub-env in a worker")
    p.add_argument("--out", default=None)
    args = p.parse_args()
    torch.set_num_threads(1)  # the README's pipeline
    results = {}
    for n in args.n:
        s = trace_one(args.env_id, n, args.steps, not args.workers_only)
        results[n] = s
        print(f"N={n}: step {s['step_us']} us; wake {s['wake_us']} us; sim {s['sim_us']} us; "
              f"back {s['collect_after_last_us']} us; straggler {s['straggler_share']}; "
              f"not stepping {s['lockstep_wait_share']}")  # fmt: skip
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump({"machine": machine_info(), "args": vars(args), "summary": results}, f, indent=1)


if __name__ == "__main__":
    main()
