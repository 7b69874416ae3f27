"""Where a batched CPU env's step goes: the engine's per-step trace (issue 37, item 1; issue 43).

Runs ``CPUVectorEnv(env_id, N, trace_steps=T, in_process=...)`` (the library's batched CPU env,
what ``ManiSkillEnv(env_id, num_envs=N, sim_backend="cpu")`` builds) with random actions, a reset
at each episode's end, one torch thread in this process (the README's pipeline; the workers run
one each), and prints the medians of the trace's summary per N and per place of sub-env 0
(``--in-process``: ``both``, the default, traces sub-env 0 in this process and then every
sub-env in a worker; ``true``, ``false``, or ``auto``, the machine's default,
:func:`~maniskill_torchrl.engines.cpu_vector.in_process_default`): the whole step; each
sub-env's wake latency (send to wake) and sim time, as the median and the largest over the
sub-envs; the way back (last sim end to collect end); the straggler, the sub-env that ended
last most often (sub-env 0 is the main process when it runs there), with its share of the steps
and the main process's sub-env's share; the main process's wait per step (from the end of its
own sub-env's step, or from the send when it steps none, to the last result); and the share of
a step a sub-env spends not stepping.

    python -m benchmarks.bench_trace --n 15 --steps 500 --out outputs/trace.json
    python -m benchmarks.bench_trace --n 1 2 --in-process true
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
import torch

from benchmarks.machine import machine_info

SEND, HERE_END, COLLECT_END = 0, 1, 2  # the trace's parent columns (maniskill_torchrl/engines/_trace.py)


def trace_one(env_id: str, n: int, steps: int, in_process: bool | None) -> dict:
    """The trace's summary of ``steps`` steps, with the straggler and the main process's wait."""
    from maniskill_torchrl import CPUVectorEnv

    env = CPUVectorEnv(env_id, n, obs_mode="state", trace_steps=steps, in_process=in_process)
    here = env.in_process
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
        trace = env.trace()
    finally:
        env.close()
    summary = dict(trace["summary"], in_process=here)
    summary.update(main_process_wait(trace["rows"], here))
    share = summary.get("straggler_share") or []
    if share:
        k = int(np.argmax(share))
        summary["straggler"] = k
        summary["straggler_where"] = "main process" if k == 0 and here else "worker"
        summary["main_straggler_share"] = share[0] if here else 0.0
    return summary


def main_process_wait(rows: np.ndarray, in_process: bool) -> dict:
    """Medians (us) of the main process's wait per step: from the end of its own sub-env's step
    (sub-env 0 in this process) or from the send (none here) to its last result; and its own
    sub-env's part of the step (send to its end; 0 without one)."""
    rows = rows[~np.isnan(rows[:, [SEND, COLLECT_END]]).any(axis=1)]
    if in_process:
        rows = rows[~np.isnan(rows[:, HERE_END])]
    if not len(rows):
        return {}
    start = rows[:, HERE_END] if in_process else rows[:, SEND]
    own = rows[:, HERE_END] - rows[:, SEND] if in_process else np.zeros(len(rows))
    return {
        "main_wait_us": round(float(np.median(rows[:, COLLECT_END] - start)) * 1e6, 1),
        "main_own_step_us": round(float(np.median(own)) * 1e6, 1),
    }


def _spread(values) -> str:
    v = np.atleast_1d(np.asarray(values, dtype=float))
    return f"{np.median(v):.0f}" if len(v) == 1 else f"{np.median(v):.0f} (max {v.max():.0f})"


def line(n: int, s: dict) -> str:
    if not s.get("steps"):
        return f"N={n} in_process={s.get('in_process')}: no complete step traced"
    where = "sub-env 0 in the main process" if s["in_process"] else "every sub-env in a worker"
    straggler = f"sub-env {s['straggler']} ({s['straggler_where']}) {s['straggler_share'][s['straggler']]:.0%}"
    main_share = f"; main process's sub-env {s['main_straggler_share']:.0%}" if s["in_process"] else ""
    return (
        f"N={n}, {where}: step {s['step_us']:.0f} us; wake {_spread(s['wake_us'])} us; sim {_spread(s['sim_us'])} us; "
        f"back {s['collect_after_last_us']:.0f} us; straggler {straggler}{main_share}; main process waits "
        f"{s['main_wait_us']:.0f} us per step (its own sub-env {s['main_own_step_us']:.0f} us); not stepping "
        f"{s['lockstep_wait_share']:.0%}"
    )


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env-id", default="PickCube-v1")
    p.add_argument("--n", type=int, nargs="+", default=[1, 2])
    p.add_argument("--steps", type=int, default=500)
    p.add_argument(
        "--in-process",
        choices=("both", "true", "false", "auto"),
        default="both",
        help="sub-env 0 in this process (true), in a worker (false), both in turn (default), or the machine's default",
    )
    p.add_argument("--workers-only", action="store_true", help="the same as --in-process false")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    if args.workers_only:
        args.in_process = "false"
    settings = {"both": [True, False], "true": [True], "false": [False], "auto": [None]}[args.in_process]
    torch.set_num_threads(1)  # the README's pipeline
    results: dict[str, dict] = {}
    for n in args.n:
        for in_process in settings:
            s = trace_one(args.env_id, n, args.steps, in_process)
            results[f"N={n} in_process={s['in_process']}"] = s
            print(line(n, s), flush=True)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump({"machine": machine_info(), "args": vars(args), "summary": results}, f, indent=1)


if __name__ == "__main__":
    main()
