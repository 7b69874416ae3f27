"""Collection frames/s: ManiSkill's gym path against TorchRL collectors, side by side (CPU sim).

Task PickCube-v1, ``obs_mode="state"``, random actions, ``max_episode_steps=50``, at
``N`` = 1, 2, 4 sub-envs, with and without an action repeat of 2. Contenders:

- ``gym``: ManiSkill's own CPU path, ``gymnasium.vector.AsyncVectorEnv([thunk] * N,
  context="forkserver")`` with ``thunk = lambda: CPUGymWrapper(gym.make(id, num_envs=1,
  obs_mode="state", max_episode_steps=50))`` (ManiSkill's ``CPUGymWrapper``; for repeat 2,
  ``CPUGymWrapper(ActionRepeatWrapper(gym.make(...), 2))``: ManiSkill's ``ActionRepeatWrapper``
  works on the batched torch env, so it goes under ``CPUGymWrapper``), stepped with
  ``envs.step(envs.action_space.sample())``, torch's default threads (one per core) in the main
  process and in each worker, the sims in autograd's grad mode (gymnasium's worker loop);
- ``gym:<options>``: ``t1`` (``torch.set_num_threads(1)`` in the main process and in each
  worker before it makes its env: the library's thread policy; the sims' mode unchanged),
  ``inf`` (each worker's ``step`` and ``reset`` under :func:`torch.inference_mode`, as the
  library's workers run theirs: the sims' per-step autograd bookkeeping gone, threads
  unchanged; ``gym:t1,inf`` both: the library workers' settings, so what remains between it
  and ``batched`` is mostly the engine), ``noshm`` (``AsyncVectorEnv(..., shared_memory=False)``);
- ``batched``: ``Collector(ManiSkillEnv(id, num_envs=N, obs_mode="state",
  max_episode_steps=50), policy=None)`` (``TransformedEnv(..., ActionRepeat(2))`` for
  repeat 2): the batched CPU env, its sims under inference mode, its workers at one torch
  thread, the main process at torch's default (``t1``: one). Skipped with a note when its
  construction raises;
- ``batched:<options>``: the same with settings changed (comma-separated options): ``rp``
  (``policy=RandomPolicy(env.action_spec)``), ``dev`` (``device=env.device``), ``notraj``
  (``track_traj_ids=False``), ``noinf`` (``inference_mode=False``), ``t1`` (one torch thread),
  ``workers`` (``in_process=False``: every sub-env in a worker process, none in this one), ``inproc``
  (``in_process=True``: sub-env 0 in this process; without either, the machine decides),
  ``em`` (``EpisodeMetrics()`` after the repeat), ``sched=batch|other`` (every worker thread put under
  Linux's ``SCHED_BATCH`` / ``SCHED_OTHER`` once built, whatever the library set; the policies found are
  reported as ``workers_sched``), ``cr`` / ``cr=K`` (``CachedReset(num_resets=K)`` last, ``K > 1``;
  default ``num_envs``). The README's pipeline is ``batched:t1,rp,dev,em`` with ``--repeat 2``;
- ``rgb=S`` (``gym`` and ``batched``): the task's cameras' rgb at S x S pixels (``obs_mode="rgb"``), flattened
  as ManiSkill's PPO-from-rgb baseline does: ``FlattenRGBDObservationWrapper(rgb=True, depth=False,
  state=True)`` under ``CPUGymWrapper`` for ``gym``, ``FlattenRGBD`` first for ``batched`` (the rgb pipeline
  of ``examples/ppo_torchrl.py --obs rgb``);
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
  policy process directly, TorchRL's set-up for process workers); ``async:lib``:
  ``AsyncPoolCollector(ManiSkillAsyncEnvPool(id, N, repeat=r))``, the library's path past lockstep
  (lean workers, the repeat inside them, random actions; ``min=K``: ``min_get``, ``mlp``: the
  ``Linear -> Tanh`` policy, ``sched=batch|other`` as for ``batched``).

**Frames are agent steps for every contender**: a sim step taken on an agent's action; a reset
is never a frame. TorchRL's collectors count their frames, agent steps (``step_and_maybe_reset``
resets an ended episode in the same call, uncounted); ``AsyncBatchedCollector`` counts its
transitions, one per agent step. Gymnasium's ``AsyncVectorEnv`` (default next-step autoreset)
spends one ``step`` call of a sub-env on its reset after each episode, its action ignored: a
call counts ``N`` less the sub-envs whose previous step ended their episode
(``terminated | truncated``). It used to count ``N`` per call, one frame per agent episode
more: +1/50 (2%) at repeat 1, +1/25 (4%) at repeat 2 (25-step agent episodes); the JSON keeps
that count per gym run as ``credited_frames``, beside ``autoreset_steps``.

**What each contender runs** is reported by its child and shown in the table: ``threads`` is
the main process's torch threads / its workers' (``-``: no worker; gym's workers answer
``AsyncVectorEnv.call``, TorchRL's write what they run as they build their env; the batched
env's workers run one thread, the engine's setting, and its sub-env 0 runs in the main
process when ``sub-env 0`` says so), ``sims`` the mode the sims step in (``inference``:
:func:`torch.inference_mode`; ``grad``: autograd's default; ``not inference``:
``inference_mode=False``, the caller's mode).

Each run is a fresh Python process (this script with ``--child``) that builds the pipeline,
warms up untimed (first reset and one batch / 50 steps), then collects for ``--seconds`` of
wall time, counting whole batches. Rounds alternate (round ``r`` runs every pipeline once, in
a rotating order, :func:`alternate.alternate_processes`); medians over rounds are reported,
with ratios to ``gym`` and to the faster of ``gym`` and ``gym:t1`` (``best gym``, which the
targets use) at the same N and repeat. The child also records its own CPU time
and its workers' (``main cpu``: cores the main process keeps busy; ``workers cpu``: cores
its worker processes keep busy, summed) and the cores other processes of the machine kept
busy meanwhile (``others``). On a shared machine each run waits for the cores to be quiet
first (``--max-busy``, ``--max-wait``), and a run disturbed by other jobs (``others`` above
``--max-others``) is run again (``--retries``). ``--busy K`` runs K busy-loop processes beside
every run (a learner's stand-in; ``others`` then counts them, ``--max-others`` past them).

``--order n`` runs all rounds of one N (all repeats) before the next N, in the order ``--n``
gives, so a sweep cut short has whole rounds of the N values it reached; ``--budget S``
starts no run that would end past ``S`` seconds (its estimate: the longest run so far at its
N), and reports the runs so far (``"complete": false`` in the JSON).

Run: ``python -m benchmarks.bench_collection [--n 1 2 4] [--repeat 1 2] [--rounds 2]
[--seconds 2.5] [--pipelines gym gym:t1 batched parallel parallel:lib] [--order rounds|n]
[--budget S] [--out results.json]``. The default run (5 pipelines x 6 cells x 2 rounds, ~17 s
per run, mostly start-up: every process imports torch, TorchRL and ManiSkill) takes about
17 minutes on 2 idle cores; ``--n 2`` about 6. Quick check of the code (no quiet-machine wait,
no re-runs): ``--n 1 2 --repeat 2 --rounds 1 --seconds 0.5 --max-wait 0 --retries 0``.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import sys
import time
import warnings

from benchmarks.alternate import ProcessContender, ProcessResult, add_alternation_args, run_alternating
from benchmarks.collection_pipelines import ENV_ID, EPISODE, run_child
from benchmarks.machine import machine_line, save_json

HERE = os.path.dirname(os.path.abspath(__file__))

warnings.filterwarnings("ignore")

DEFAULT_PIPELINES = ["gym", "gym:t1", "batched", "parallel", "parallel:lib"]
# ratios to the faster of gym and gym:t1 at the same cell ("best gym"; gym alone when it ran alone)
TARGETS = {"batched": 1.0, "parallel:lib": 0.9}
GYMS = ("gym", "gym:t1")


def cell_name(spec: str, n: int, repeat: int) -> str:
    return f"{spec} N={n} r={repeat}"


def fmt_table(results: dict, specs: list[str], ns: list[int], repeats: list[int], baseline: str = "gym") -> str:
    rows = [
        "| pipeline | N | repeat | frames/s (median) | min-max | to gym | to best gym | threads (main/workers) "
        "| sims | sub-env 0 | main cpu | workers cpu | others | rounds |",
        "|---|---:|---:|---:|---:|---:|---:|---|---|---|---:|---:|---:|---:|",
    ]
    notes = []
    for repeat in repeats:
        for n in ns:
            base = results.get(cell_name(baseline, n, repeat))
            base_fps = 1.0 / base.median if base is not None and base.ok else None
            best_fps, _ = best_gym(results, n, repeat)
            for spec in specs:
                res = results[cell_name(spec, n, repeat)]
                if not res.ok:
                    rows.append(f"| {spec} | {n} | {repeat} | - | - | - | - | - | - | - | - | - | - | 0 |")
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
                best = f"{fps / best_fps:.2f}x" if best_fps else "-"
                threads, sims, sub0 = ran_cell(res.extra)
                rows.append(
                    f"| {spec} | {n} | {repeat} | {fps:.0f} | {lo:.0f}-{hi:.0f} | {ratio} | {best} | {threads} | "
                    f"{sims} | {sub0} | {main:.2f} | {workers:.2f} | {others_s} | {len(res.per_unit)} |"
                )
                credited = [e["credited_frames"] / u for e, u in zip(res.extra, res.units) if "credited_frames" in e]
                if credited:
                    notes.append(
                        f"- {spec} N={n} repeat={repeat}: counting N per step() call, as before, would credit "
                        f"{statistics.median(credited) - 1:+.1%} frames (the autoreset calls)"
                    )
    legend = (
        "frames = agent steps, for every contender; a reset is never a frame (TorchRL's collectors: their "
        "frames / transitions; gym: N per step() call less the sub-envs that call autoreset). to best gym: "
        "to the faster of gym and gym:t1. threads: torch threads of the main process / of each worker (- : "
        "none). sims: the mode the sims step in."
    )
    return "\n".join(rows + ["", legend] + ([""] + notes if notes else []))


def best_gym(results: dict, n: int, repeat: int) -> tuple[float | None, str | None]:
    """The frames/s of the faster of the gym contenders (:data:`GYMS`) that ran at this cell, and its name."""
    found = [(1.0 / r.median, g) for g in GYMS if (r := results.get(cell_name(g, n, repeat))) is not None and r.ok]
    return max(found) if found else (None, None)


def ran_cell(extra: list[dict]) -> tuple[str, str, str]:
    """What a cell's rounds ran (``RAN_KEYS`` of each child): threads main/workers, sims, sub-env 0."""

    def one(key: str) -> str:
        values = []
        for e in extra:
            v = e.get(key)
            v = "-" if v is None else "/".join(map(str, v)) if isinstance(v, list) else str(v)
            values.append(v)
        return ", ".join(dict.fromkeys(values)) or "?"

    return f"{one('main_threads')}/{one('worker_threads')}", one("sims"), one("sub_env0")


class _OutOfBudget(Exception):
    pass


def results_from_runs(names: list[str], runs: list[dict]) -> dict[str, ProcessResult]:
    """ProcessResults from the children's reports as ``on_result`` kept them (a sweep cut by its budget)."""
    results = {name: ProcessResult(name) for name in names}
    for run in runs:
        res, payload = results[run["name"]], run["result"]
        if "failed" in payload:
            res.failures += 1
            res.note = f"failed: {(payload['failed'].splitlines() or ['no output'])[0]}"
        elif payload.get("skipped"):
            res.note = f"skipped: {payload['skipped']}"
        else:
            units, wall, cpu = payload["units"], payload["wall_s"], payload["cpu_s"]
            res.per_unit.append(wall / units)
            res.per_unit_wall.append(wall / units)
            res.per_unit_cpu.append(cpu / units)
            res.units.append(units)
            res.extra.append({k: v for k, v in payload.items() if k not in ("units", "wall_s", "cpu_s", "skipped")})
    return results


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[1, 2, 4], help="sub-envs (default 1 2 4)")
    p.add_argument("--repeat", type=int, nargs="+", default=[1, 2], help="action repeats (default 1 2)")
    p.add_argument("--rounds", type=int, default=2, help="alternating rounds (default 2)")
    p.add_argument("--seconds", type=float, default=2.5, help="timed collection per run (default 2.5)")
    p.add_argument(
        "--pipelines", nargs="+", default=DEFAULT_PIPELINES, help=f"contenders (default {' '.join(DEFAULT_PIPELINES)})"
    )
    p.add_argument(
        "--order",
        choices=("rounds", "n"),
        default="rounds",
        help="rounds: each round runs every cell (default); n: all rounds of one N before the next, in --n's order",
    )
    p.add_argument(
        "--budget", type=float, default=None, help="seconds: start no run that would end past them (default: none)"
    )
    p.add_argument(
        "--baseline",
        default="gym",
        help="the pipeline the 'to gym' column divides by, always run (default gym; e.g. gym:rgb=64 for rgb)",
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
    if args.baseline not in specs:
        specs.insert(0, args.baseline)
    print(machine_line())
    t0 = time.perf_counter()
    cells = [(spec, n, repeat) for repeat in args.repeat for n in args.n for spec in specs]
    contenders = {
        cell_name(*cell): ProcessContender(
            cell_name(*cell),
            [sys.executable, "-m", "benchmarks.bench_collection", "--child", cell[0], "--n", str(cell[1])]
            + ["--repeat", str(cell[2]), "--seconds", str(args.seconds)],
        )
        for cell in cells
    }
    if args.order == "n":  # one N at a time, its repeats and pipelines alternating
        groups = [[cell_name(*c) for c in cells if c[1] == n] for n in args.n]
    else:
        groups = [list(contenders)]
    settings = {
        "env_id": ENV_ID,
        "episode": EPISODE,
        "n": args.n,
        "repeat": args.repeat,
        "rounds": args.rounds,
        "seconds": args.seconds,
        "pipelines": specs,
        "order": args.order,
        "budget_s": args.budget,
        "frames": "agent steps for every contender; resets are not frames (gym: N per step() call less the "
        "sub-envs that call autoreset; credited_frames: N per call)",
    }
    runs: list[dict] = []  # every child's report, written as it comes (a sweep cut short keeps its runs)
    clock = {"last": t0, "longest": {}}  # the longest run so far per N (the budget's estimate)

    def over_budget(n: int) -> bool:
        longest = clock["longest"].get(n) or max(clock["longest"].values(), default=0.0)
        return args.budget is not None and time.perf_counter() - t0 + longest > args.budget

    def on_result(name: str, r: int, payload: dict) -> None:
        now, n = time.perf_counter(), int(name.split(" N=")[1].split()[0])
        clock["longest"][n] = max(clock["longest"].get(n, 0.0), now - clock["last"])
        clock["last"] = now
        runs.append({"name": name, "round": r, "result": payload})
        if args.out:
            save_json(
                args.out, {"benchmark": "bench_collection", "settings": settings, "complete": False, "runs": runs}
            )
        if over_budget(n):
            raise _OutOfBudget(f"stopped after {now - t0:.0f} s: the next run would end past --budget {args.budget:g}")

    results: dict[str, ProcessResult] = {}
    stopped = None
    for group in groups:
        n = int(group[0].split(" N=")[1].split()[0])
        if clock["longest"] and over_budget(n):
            stopped = f"stopped after {time.perf_counter() - t0:.0f} s: the next run would end past --budget"
            break
        clock["last"] = time.perf_counter()
        try:
            results.update(
                run_alternating([contenders[c] for c in group], args, cwd=os.path.dirname(HERE), on_result=on_result)
            )
        except _OutOfBudget as err:
            stopped = str(err)
            results.update(results_from_runs(group, [x for x in runs if x["name"] in group]))
            break
    for name in contenders:
        results.setdefault(name, ProcessResult(name, note="not run: --budget"))
    done = {name: sum(x["name"] == name for x in runs) for name in contenders}
    complete = all(done[k] >= args.rounds or (results[k].note or "").startswith("skipped") for k in contenders)
    stopped = None if complete else stopped
    took = time.perf_counter() - t0
    table = fmt_table(results, specs, args.n, args.repeat, args.baseline)
    print(
        f"\nPickCube-v1 state, random actions, episodes of {EPISODE} steps; frames = agent steps (resets are "
        f"not frames); median of {args.rounds} rounds x {args.seconds:g} s, one process per run ({took:.0f} s "
        f"in all{'; ' + stopped if stopped else ''})\n"
    )
    print(table)
    missed = []
    for spec, target in TARGETS.items():
        if spec not in specs:
            continue
        for repeat in args.repeat:
            for n in args.n:
                res = results[cell_name(spec, n, repeat)]
                best_fps, best = best_gym(results, n, repeat)
                if res.ok and best_fps and 1.0 / res.median / best_fps < target:
                    missed.append(
                        f"{spec} N={n} repeat={repeat}: {1.0 / res.median / best_fps:.2f}x {best} < {target}x"
                    )
    if missed:
        print("\nbelow target: " + "; ".join(missed))
    if args.out:
        save_json(
            args.out,
            {
                "benchmark": "bench_collection",
                "settings": settings,
                "complete": complete,
                **({"stopped": stopped} if stopped else {}),
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
