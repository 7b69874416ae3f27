"""GPU sim steps/s: a raw ManiSkill loop, ManiSkillEnv, +ActionRepeat(2)+EpisodeMetrics and
ManiSkill's ManiSkillVectorEnv (PushCube-v1, state obs; 256, 1024 and 4096 envs).

Per number of envs, one ManiSkill GPU-sim env is shared by the four contenders (the same
physics: a seeded reset before every round, the same pre-generated actions on the GPU), timed
round-robin by :mod:`common` (rotating order, medians over rounds, wall clock; every timed run
ends with ``torch.cuda.synchronize()``). Each round is ``--steps`` physics steps of every env
(40: the 50-step time limit never ends an episode within a round):

- ``raw``: ``obs, rew, term, trunc, info = env.step(a)``; envs that terminated are reset with
  ``env.reset(options={"env_idx": ...})`` (the least a training loop does);
- ``ManiSkillEnv``: ``td.set("action", a); _, td = env.step_and_maybe_reset(td)``, what TorchRL's
  collectors call (auto-reset through ``"_reset"``);
- ``+ActionRepeat(2)+EpisodeMetrics``: ``TransformedEnv(ManiSkillEnv, Compose(ActionRepeat(2),
  EpisodeMetrics()))``, ``step_and_maybe_reset``, ``--steps / 2`` outer steps (the same
  physics steps);
- ``ManiSkillVectorEnv``: ``mani_skill.vector.wrappers.gymnasium.ManiSkillVectorEnv(env).step(a)``
  (auto-reset, its defaults).

The unit is one env's physics step: steps/s = envs x physics steps / second. Targets (issue 10):
ManiSkillEnv within 1.05x of the raw loop's time, and at least as fast as ManiSkillVectorEnv.

Without CUDA it prints why and exits 0 (``make bench`` runs every bench_*.py). On an accelerator
machine: ``python3 scripts/gpu_check.py`` (benchmarks/README.md, "GPU kit").

Run: ``python -m benchmarks.bench_gpu [--envs 256 1024 4096] [--steps 40] [--rounds 7] [--out bench_gpu.json]``.
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
import warnings

import torch

from benchmarks.common import Contender, interleave, make_actions, ratio, report
from benchmarks.machine import machine_line, save_json

warnings.filterwarnings("ignore")

SEED = 0
TARGET_VS_RAW = 1.05
CONTENDERS = ("raw", "ManiSkillEnv", "+ActionRepeat(2)+EpisodeMetrics", "ManiSkillVectorEnv")


def bench_size(env_id: str, n: int, steps: int, rounds: int, warmup: int, verbose: bool, backend: str = "gpu") -> dict:
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv
    from torchrl.envs import Compose, TransformedEnv

    from maniskill_torchrl import ActionRepeat, EpisodeMetrics, ManiSkillEnv

    t0 = time.perf_counter()
    # inference_mode=False, the GPU sim's default, in the CPU dry run too: the raw loop and
    # ManiSkillVectorEnv step the same gym env in grad mode, which inference tensors would break.
    env = ManiSkillEnv(env_id, num_envs=n, sim_backend=backend, obs_mode="state", inference_mode=False)
    build_s = time.perf_counter() - t0
    raw = env._env  # the gym env ManiSkillEnv made: same instance, same physics for all
    stacked = TransformedEnv(env, Compose(ActionRepeat(2), EpisodeMetrics()))
    vec = ManiSkillVectorEnv(raw)
    device = env.device
    acts = [a.to(device) for a in make_actions(raw.unwrapped.single_action_space, steps, batch=(n,), seed=n)]
    sync = torch.cuda.synchronize if backend == "gpu" else (lambda: None)
    state = {}

    def setup_raw():
        raw.reset(seed=SEED)
        sync()

    def run_raw():
        step, reset = raw.step, raw.reset
        for a in acts:
            _, _, terminated, truncated, _ = step(a)
            done = terminated | truncated
            if done.any():
                reset(options={"env_idx": done.nonzero().squeeze(-1)})
        sync()
        return n * len(acts)

    def setup_env():
        state["td"] = env.reset(seed=SEED)
        sync()

    def run_env():
        td, smr = state["td"], env.step_and_maybe_reset
        for a in acts:
            td.set("action", a)
            _, td = smr(td)
        sync()
        return n * len(acts)

    def setup_stacked():
        state["td_stacked"] = stacked.reset(seed=SEED)
        sync()

    def run_stacked():
        td, smr = state["td_stacked"], stacked.step_and_maybe_reset
        for a in acts[::2]:
            td.set("action", a)
            _, td = smr(td)
        sync()
        return n * 2 * len(acts[::2])

    def setup_vec():
        vec.reset(seed=SEED)
        sync()

    def run_vec():
        step = vec.step
        for a in acts:
            step(a)
        sync()
        return n * len(acts)

    results = interleave(
        [
            Contender(CONTENDERS[0], run_raw, setup_raw),
            Contender(CONTENDERS[1], run_env, setup_env),
            Contender(CONTENDERS[2], run_stacked, setup_stacked),
            Contender(CONTENDERS[3], run_vec, setup_vec),
        ],
        rounds=rounds,
        warmup=warmup,
        verbose=verbose,
        clock="wall",
    )
    vec.closed = True  # env.close() below closes the shared gym env once
    env.close()
    return {"results": results, "build_s": build_s}  # the caller frees the GPU memory (free_gpu)


def free_gpu(backend: str) -> None:
    """After ``bench_size`` returned (its envs and actions are unreferenced): give the memory back."""
    gc.collect()
    if backend == "gpu":
        torch.cuda.empty_cache()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env-id", default="PushCube-v1")
    p.add_argument("--envs", type=int, nargs="+", default=[256, 1024, 4096], help="numbers of envs")
    p.add_argument("--steps", type=int, default=40, help="physics steps per env per contender per round (even)")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--out", "--json", dest="out", default=None, help="write the results as JSON here")
    p.add_argument("-v", "--verbose", action="store_true")
    p.add_argument(
        "--cpu-dry-run",
        action="store_true",
        help="check this script's code on the CPU sim with one env (no GPU figure: nothing to compare)",
    )
    args, unknown = p.parse_known_args(argv)  # run_all.py may forward the CPU benchmarks' flags
    if args.steps < 2 or args.steps % 2:
        p.error("--steps must be even and >= 2 (ActionRepeat(2) takes --steps / 2 outer steps)")

    backend = "gpu"
    if args.cpu_dry_run:
        backend, args.envs, args.rounds, args.warmup = "physx_cpu", [1], 1, 0
    elif not torch.cuda.is_available():
        msg = (
            "bench_gpu: no CUDA device (torch.cuda.is_available() is False): nothing measured. "
            "Run it on a GPU machine: python3 scripts/gpu_check.py (benchmarks/README.md, 'GPU kit')."
        )
        print(msg)
        if args.out:
            save_json(args.out, {"skipped": msg, "args": vars(args)})
        return 0

    gpu = (
        torch.cuda.get_device_name(0) if backend == "gpu" else "none: --cpu-dry-run (CPU sim, one env; no GPU figures)"
    )
    print(
        f"bench_gpu: {args.env_id} state obs, GPU sim on {gpu}; {args.steps} physics steps x envs per "
        f"contender per round, {args.rounds} rounds (+{args.warmup} warm-up), medians of wall time"
    )
    print(machine_line())
    if unknown:
        print(f"(ignored arguments: {' '.join(unknown)})")
    payload = {
        "args": vars(args),
        "gpu": gpu,
        "cuda": torch.version.cuda,
        "sizes": {},
        "summary": {},
        "date": time.strftime("%Y-%m-%d"),
    }
    verdicts = []
    for n in args.envs:
        t0 = time.perf_counter()
        out = bench_size(args.env_id, n, args.steps, args.rounds, args.warmup, args.verbose, backend)
        free_gpu(backend)
        res = out["results"]
        print(f"\n{n} envs (env built in {out['build_s']:.1f} s, measured in {time.perf_counter() - t0:.1f} s)")
        print(report(res, baseline="raw", unit="env-step"))
        line = {
            name: {"steps_per_s": 1.0 / r.median, "ratio_to_raw": ratio(res, name, "raw")} for name, r in res.items()
        }
        for name, v in line.items():
            print(f"  {name:<34} {v['steps_per_s'] / 1e3:10.1f} k env-steps/s   {v['ratio_to_raw']:.3f}x raw's time")
        vs_raw = line["ManiSkillEnv"]["ratio_to_raw"]
        vs_vec = ratio(res, "ManiSkillEnv", "ManiSkillVectorEnv")
        ok = vs_raw <= TARGET_VS_RAW and vs_vec <= 1.0
        verdicts.append(ok)
        print(
            f"  ManiSkillEnv / raw = {vs_raw:.3f}x (target <= {TARGET_VS_RAW:.2f}x), "
            f"ManiSkillEnv / ManiSkillVectorEnv = {vs_vec:.3f}x (target <= 1.00x): {'met' if ok else 'NOT met'}"
        )
        payload["sizes"][str(n)] = {"build_s": out["build_s"], **{k: v.as_dict() for k, v in res.items()}}
        payload["summary"][str(n)] = {**line, "ManiSkillEnv_vs_ManiSkillVectorEnv": vs_vec, "targets_met": ok}
        if args.out:  # after every size: a run stopped by a time limit keeps what it measured
            save_json(args.out, {**payload, "complete": False})
    payload["targets"] = {
        "ManiSkillEnv_vs_raw_max": TARGET_VS_RAW,
        "ManiSkillEnv_vs_ManiSkillVectorEnv_max": 1.0,
        "met_at_all_sizes": all(verdicts),
    }
    payload["complete"] = True
    if args.out:
        save_json(args.out, payload)
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
