"""Collector settings for the batched CPU env, paired in one process: frames/s and main-process CPU.

``bench_collection.py`` times each pipeline in a process of its own; this script keeps every
contender alive in one process and takes turns batch by batch, so a noisy machine slows all of
them alike, and it reports the main process's CPU time per step: the work that runs while the
sim workers wait. Contenders (PickCube-v1 state, random actions, ``max_episode_steps=50``,
``N`` sub-envs, ``ActionRepeat(2)`` on the TorchRL env and ManiSkill's ``ActionRepeatWrapper``
in the gym workers with ``--repeat 2``):

- ``gym``: ``AsyncVectorEnv([CPUGymWrapper(gym.make(...))] * N, context="forkserver")``,
  ``step(action_space.sample())`` 50 times per batch;
- ``batched``: ``Collector(ManiSkillEnv(id, num_envs=N), policy=None)``, TorchRL's defaults;
- ``batched:<options>``, options joined by ``+``: ``rp`` (``RandomPolicy(env.action_spec)``:
  the leaf spec), ``dev`` (``device=env.device``), ``notraj`` (``track_traj_ids=False``),
  ``workers`` (``ManiSkillEnv(..., in_process=False)``: every sub-env in a worker process,
  none stepped in this one), ``noinf`` (``ManiSkillEnv(..., inference_mode=False)``: at N=1 the sim runs in this
  process, in grad mode);
- ``parallel[:<options>]``: ``Collector(ParallelEnv(N, ManiSkillEnv + CPUUnbatch))`` with
  :class:`maniskill_torchrl.parallel.ManiSkillParallelEnv` (``torchrl``: TorchRL's own, started with
  ``"spawn"``), the options as above (``noinf`` in the workers' envs), ``unb`` (the workers'
  envs ``ManiSkillEnv(id, batch_size=[])``, no ``CPUUnbatch``), ``sleep`` / ``spin`` (the parent's
  wait, instead of ``"auto"``).

Run: ``python -m benchmarks.bench_collector_settings [--n 2] [--repeat 1] [--rounds 16]
[--pipelines gym batched batched:rp+dev batched:rp+dev+notraj]``.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import time
import warnings

from benchmarks.collection_pipelines import (
    ENV_ID,
    EPISODE,
    SEED,
    _worker_env,
    batched_collector,
    collector_options,
    env_options,
    gym_vector_env,
)
from benchmarks.machine import machine_line


def _gym(n: int, repeat: int):
    envs = gym_vector_env(n, repeat)

    def batch() -> None:
        for _ in range(EPISODE):
            envs.step(envs.action_space.sample())

    return batch


def _batched(n: int, repeat: int, options: list[str]):
    batches = iter(batched_collector(n, repeat, dict.fromkeys(options, "1")))
    return lambda: next(batches)


def _parallel(n: int, repeat: int, options: list[str]):
    import functools

    from torchrl.collectors import Collector

    opts = dict.fromkeys(options, "1")
    if "torchrl" in opts:
        from torchrl.envs import ParallelEnv

        kwargs = {"mp_start_method": "spawn"}  # fork would hang once this process holds SAPIEN
    else:
        from maniskill_torchrl.parallel import ManiSkillParallelEnv as ParallelEnv

        waits = [w for w in ("sleep", "spin") if w in opts]
        kwargs = {"wait": waits[0]} if waits else {}
    env = ParallelEnv(n, functools.partial(_worker_env, repeat, **env_options(opts)), **kwargs)
    env.set_seed(SEED)
    policy, kwargs = collector_options(env, opts)
    collector = Collector(env, policy=policy, frames_per_batch=EPISODE * n, total_frames=-1, **kwargs)
    batches = iter(collector)
    return lambda: next(batches)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=16)
    parser.add_argument("--pipelines", nargs="+", default=["gym", "batched", "batched:rp+dev", "batched:rp+dev+notraj"])
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore")
    logging.getLogger("mani_skill").setLevel(logging.ERROR)

    contenders = {}
    for spec in args.pipelines:
        kind, _, opts = spec.partition(":")
        if kind == "gym":
            contenders[spec] = _gym(args.n, args.repeat)
        elif kind == "batched":
            contenders[spec] = _batched(args.n, args.repeat, opts.split("+"))
        elif kind == "parallel":
            contenders[spec] = _parallel(args.n, args.repeat, opts.split("+"))
        else:
            raise SystemExit(f"unknown pipeline {spec!r}: gym, batched[:options] or parallel[:options]")
    for batch in contenders.values():
        batch()  # warm-up: first reset and one batch
    fps: dict[str, list[float]] = {s: [] for s in contenders}
    cpu: dict[str, list[float]] = {s: [] for s in contenders}
    for _ in range(args.rounds):
        for spec, batch in contenders.items():
            c0, t0 = time.thread_time(), time.perf_counter()
            batch()
            fps[spec].append(EPISODE * args.n / (time.perf_counter() - t0))
            cpu[spec].append((time.thread_time() - c0) / EPISODE * 1e3)
    print(machine_line())
    print(
        f"{ENV_ID}, N={args.n}, repeat={args.repeat}, {args.rounds} rounds of one {EPISODE}-step batch each, medians:"
    )
    base = statistics.median(fps[args.pipelines[0]])
    print(f"| pipeline | frames/s | ratio to {args.pipelines[0]} | main process CPU per step |")
    print("|---|---:|---:|---:|")
    for spec in contenders:
        med = statistics.median(fps[spec])
        print(f"| {spec} | {med:.0f} | {med / base:.2f}x | {statistics.median(cpu[spec]):.2f} ms |")
    sys.stdout.flush()
    # No teardown: closing SAPIEN in every worker takes seconds and is not measured. The workers
    # are killed first, so that they do not print their broken pipes.
    import psutil

    for child in psutil.Process().children(recursive=True):
        child.kill()
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
