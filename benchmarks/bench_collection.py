"""Collection frames/s: ManiSkill's gym path against TorchRL collectors, side by side (CPU sim).

Task PickCube-v1, ``obs_mode="state"``, random actions, ``max_episode_steps=50``, at
``N`` = 1, 2, 4 sub-envs, with and without an action repeat of 2. Contenders:

- ``gym``: ManiSkill's own CPU path, ``gymnasium.vector.AsyncVectorEnv([thunk] * N,
  context="forkserver")`` with ``thunk = lambda: CPUGymWrapper(gym.make(id, num_envs=1,
  obs_mode="state", max_episode_steps=50))`` (ManiSkill's ``CPUGymWrapper``; for repeat 2,
  ``CPUGymWrapper(ActionRepeatWrapper(gym.make(...), 2))``: ManiSkill's ``ActionRepeatWrapper``
  works on the batched torch env, so it goes under ``CPUGymWrapper``), stepped with
  ``envs.step(envs.action_space.sample())``; N frames per call (with gymnasium's default
  next-step autoreset, one call in 51 per sub-env is a reset, not a sim step: the gym path
  is credited ~2% more frames than sim steps it takes);
- ``batched``: ``Collector(ManiSkillEnv(id, num_envs=N, obs_mode="state",
  max_episode_steps=50), policy=None)`` (``TransformedEnv(..., ActionRepeat(2))`` for
  repeat 2): the batched CPU env. Skipped with a note when its construction raises;
- ``batched:<options>``: the same with settings changed (comma-separated options): ``rp``
  (``policy=RandomPolicy(env.action_spec)``), ``dev`` (``device=env.device``), ``notraj``
  (``track_traj_ids=False``), ``noinf`` (``inference_mode=False``), ``t1`` (one torch thread),
  ``workers`` (``in_process=False``: every sub-env in a worker process, none in this one),
  ``em`` (``EpisodeMetrics()`` after the repeat). The README's pipeline is ``batched:t1,rp,dev,em``
  with ``--repeat 2``;
- ``gym:<options>``: ``t1`` (one torch thread in the main process and in each worker, the
  library's thread policy), ``noshm`` (``AsyncVectorEnv(..., shared_memory=False)``);
- ``parallel``: ``Collector(ParallelEnv(N, lambda: TransformedEnv(ManiSkillEnv(id,
  obs_mode="state", max_episode_steps=50), CPUUnbatch())), policy=None)``, what TorchRL
  users write by habit (``Compose(CPUUnbatch(), ActionRepeat(2))`` inside the workers for
  repeat 2), with TorchRL's defaults;
- ``parallel:<options>``: the same with settings changed (comma-separated options):
  ``t1`` (``torch.set_num_threads(1)`` in the main process before building the env),
  ``nobuf`` (``use_buffers=False``), ``mp=<method>`` (``mp_start_method``),
  ``lib`` (:class:`maniskill_torchrl.parallel.ManiSkillParallelEnv`, the library's settings),
  ``wait=<spin|sleep>`` (that class with the given wait strategy), ``nobatch`` (that class
  without ``SCHED_BATCH`` workers), ``noinf`` (the workers' envs with ``inference_mode=False``),
  ``unb`` (the workers' envs ``ManiSkillEnv(id, batch_size=[])``, no ``CPUUnbatch``),
  ``rp`` and ``dev`` (as for ``batched``);
- ``multisync``: ``Collector(make_env, backend="process", num_collectors=N)`` (TorchRL's
  ``MultiSyncCollector``: one single env and one collector per process, data gathered per
  batch instead of per step), the same worker env as ``parallel``; ``multisync:unb``: the
  workers' envs ``ManiSkillEnv(id, batch_size=[])`` (no ``CPUUnbatch``), as for ``parallel``.

- ``async``: ``AsyncBatchedCollector([make_env] * N, policy, env_backend="multiprocessing")``,
  TorchRL's collector without a lockstep (each env stepped as soon as its action is ready), the
  workers' envs ``ManiSkillEnv(id, batch_size=[])`` (-> ``ActionRepeat``), a ``Linear -> Tanh``
  policy; ``async:auto``: ``policy_factory=...`` and ``transport="auto"`` (the workers reach a
  policy process directly, TorchRL's set-up for process workers).

Frames are agent steps (the collector's frames; gym: N per ``step``). Each run is a fresh
Python process (this script with ``--child``) that builds the pipeline, warms up untimed
(first reset and one batch / 50 steps), then collects for ``--seconds`` of wall time,
counting whole batches. Rounds alternate (round ``r`` runs every pipeline once, in a
rotating order, :func:`alternate.alternate_processes`); medians over rounds are reported, with
ratios to the gym path at the same N and repeat. The child also records its own CPU time
and its workers' (``main cpu``: cores the main process keeps busy; ``workers cpu``: cores
its worker processes keep busy, summed) and the cores other processes of the machine kept
busy meanwhile (``others``). On a shared machine each run waits for the cores to be quiet
first (``--max-busy``, ``--max-wait``), and a run disturbed by other jobs (``others`` above
``--max-others``) is run again (``--retries``).

Run: ``python -m benchmarks.bench_collection [--n 1 2 4] [--repeat 1 2] [--rounds 2]
[--seconds 2.5] [--pipelines gym batched parallel parallel:lib] [--out results.json]``.
The default run (4 pipelines x 6 cells x 2 rounds, ~17 s per run, mostly start-up: every
process imports torch, TorchRL and ManiSkill) takes about 14 minutes on 2 idle cores;
``--n 2`` about 5.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import sys
import time
import warnings

from benchmarks.alternate import ProcessContender, add_alternation_args, run_alternating
from benchmarks.collection_pipelines import ENV_ID, EPISODE, run_child
from benchmarks.machine import machine_line, save_json

HERE = os.path.dirname(os.path.abspath(__file__))

warnings.filterwarnings("ignore")

DEFAULT_PIPELINES = ["gym", "batched", "parallel", "parallel:lib"]
TARGETS = {"batched": 1.0, "parallel:lib": 0.9}


def cell_name(spec: str, n: int, repeat: int) -> str:
    return f"{spec} N={n} r={repeat}"


def fmt_table(results: dict, specs: list[str], ns: list[int], repeats: list[int]) -> str:
    rows = [
        "| pipeline | N | repeat | frames/s (median) | min-max | ratio to gym "
        "| main cpu | workers cpu | others | rounds |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    notes = []
    for repeat in repeats:
        for n in ns:
            base = results.get(cell_name("gym", n, repeat))
            base_fps = 1.0 / base.median if base is not None and base.ok else None
            for spec in specs:
                res = results[cell_name(spec, n, repeat)]
                if not res.ok:
                    rows.append(f"| {spec} | {n} | {repeat} | - | - | - | - | - | - | 0 |")
                    if res.note:
                        notes.append(f"- {spec} N={n} repeat={repeat}: {res.note.splitlines()[0][:300]}")
                    continue
                fps = 1.0 / res.median
                lo, hi = 1.0 / max(res.per_unit), 1.0 / min(res.per_unit)
                wall = [u * p for u, p in zip(res.units, res.per_unit_wall)]
                main = statistics.median(u * p / w for u, p, w in zip(res.units, res.per_unit_cpu, wall))
                workers = statistics.median(e.get("workers_cpu_s", 0.0) / w for e, w in zip(res.extra, wall))
                others = [e["others_cores"] for e in res.extra if "others_cores" in e]
                others_s = f"{statistics.median(others):.2f}" if others else "-"
                ratio = f"{fps / base_fps:.2f}x" if base_fps else "-"
                rows.append(
                    f"| {spec} | {n} | {repeat} | {fps:.0f} | {lo:.0f}-{hi:.0f} | {ratio} | "
                    f"{main:.2f} | {workers:.2f} | {others_s} | {len(res.per_unit)} |"
                )
    return "\n".join(rows + ([""] + notes if notes else []))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[1, 2, 4], help="sub-envs (default 1 2 4)")
    p.add_argument("--repeat", type=int, nargs="+", default=[1, 2], help="action repeats (default 1 2)")
    p.add_argument("--rounds", type=int, default=2, help="alternating rounds (default 2)")
    p.add_argument("--seconds", type=float, default=2.5, help="timed collection per run (default 2.5)")
    p.add_argument(
        "--pipelines", nargs="+", default=DEFAULT_PIPELINES, help=f"contenders (default {' '.join(DEFAULT_PIPELINES)})"
    )
    p.add_argument("--out", "--json", dest="out", default=None, help="write all results as JSON here")
    add_alternation_args(p, retries=2)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.child is not None:
        run_child(args.child, args.n[0], args.repeat[0], args.seconds)
        return 0

    # A TERM (timeout, kill) ends the run in progress with its workers (alternate._run_child's cleanup).
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    specs = list(dict.fromkeys(args.pipelines))
    if "gym" not in specs:
        specs.insert(0, "gym")
    print(machine_line())
    t0 = time.perf_counter()
    contenders = [
        ProcessContender(
            cell_name(spec, n, repeat),
            [
                sys.executable,
                "-m",
                "benchmarks.bench_collection",
                "--child",
                spec,
                "--n",
                str(n),
                "--repeat",
                str(repeat),
                "--seconds",
                str(args.seconds),
            ],
        )
        for repeat in args.repeat
        for n in args.n
        for spec in specs
    ]
    settings = {
        "env_id": ENV_ID,
        "episode": EPISODE,
        "n": args.n,
        "repeat": args.repeat,
        "rounds": args.rounds,
        "seconds": args.seconds,
        "pipelines": specs,
    }
    runs: list[dict] = []  # every child's report, written as it comes (a sweep cut short keeps its runs)

    def on_result(name: str, r: int, payload: dict) -> None:
        runs.append({"name": name, "round": r, "result": payload})
        if args.out:
            save_json(
                args.out, {"benchmark": "bench_collection", "settings": settings, "complete": False, "runs": runs}
            )

    results = run_alternating(contenders, args, cwd=os.path.dirname(HERE), on_result=on_result)
    took = time.perf_counter() - t0
    table = fmt_table(results, specs, args.n, args.repeat)
    print(
        f"\nPickCube-v1 state, random actions, episodes of {EPISODE} steps; frames = agent steps; "
        f"median of {args.rounds} rounds x {args.seconds:g} s, one process per run ({took:.0f} s in all)\n"
    )
    print(table)
    missed = []
    for spec, target in TARGETS.items():
        if spec not in specs:
            continue
        for repeat in args.repeat:
            for n in args.n:
                res, base = results[cell_name(spec, n, repeat)], results[cell_name("gym", n, repeat)]
                if res.ok and base.ok and base.median / res.median < target:
                    missed.append(f"{spec} N={n} repeat={repeat}: {base.median / res.median:.2f}x < {target}x")
    if missed:
        print("\nbelow target: " + "; ".join(missed))
    if args.out:
        save_json(
            args.out,
            {
                "benchmark": "bench_collection",
                "settings": settings,
                "complete": True,
                "runs": runs,
                "wall_s": took,
                "table": table,
                "results": {k: v.as_dict() for k, v in results.items()},
            },
        )
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
