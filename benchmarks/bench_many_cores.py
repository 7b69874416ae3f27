"""Many cores, emulated on few: collection frames/s at N = 1 to 64 on the replay task (issue 51, item 1).

The task is ``benchmarks/replay_task.py``'s ``ReplayPickCube-v1``: PickCube-v1's recorded outputs,
each step *sleeping* its recorded time scaled to a target machine. A sleeping worker needs no core,
so ``N`` of them on 2 cores stand in for ``N`` sims on ``N`` cores; what really needs a core (the
main process, each worker's own overhead around its sim) competes for the 2 cores as it would for
one core per process. Contenders, at action repeat 2, from ``collection_pipelines.py`` (its frame
rule: frames are agent steps, a reset is never a frame):

- ``gym``: gymnasium's ``AsyncVectorEnv(context="forkserver")`` of ManiSkill's ``CPUGymWrapper(
  ActionRepeatWrapper(gym.make(id), 2))``, stepped with ``action_space.sample()`` (``gym``);
- ``readme``: the README pipeline, ``Collector(TransformedEnv(ManiSkillEnv(id, num_envs=N),
  Compose(ActionRepeat(2), EpisodeMetrics())), RandomPolicy)`` (``batched:t1,rp,dev,em``), every
  sub-env in a worker at N > 1 (``workers``: what the library picks on a machine with more cores
  than sub-envs, the one emulated);
- ``async``: ``AsyncPoolCollector(ManiSkillAsyncEnvPool(id, N, repeat=2))``, random actions
  (``async:lib``).

Each is scored against the **emulated ideal**: N envs that never wait, each agent episode costing 50
sim steps of the target's mean step time and one reset (``many_cores.ideal_fps``). Runs are fresh
processes, rounds rotated within each N (``alternate.py``); medians over rounds.

**The emulated machine** (``--step-ms``, ``--spread``): the recorded step times scaled to a mean of
``--step-ms`` (default ``h200-loaded``: 2.67 ms, what each of 15 independent PickCube-v1 envs took on
the lent H200 host, 5,623 steps/s for 15; ``h200``: 2.07 ms, one env alone, 484/s), and their spread
around that mean shrunk by ``--spread`` (``auto``: fitted so that 15 envs in lockstep reach what
they reached on the H200 against 15 independent ones, 3,774 / 5,623 = 0.67, from the recorded
times alone: ``many_cores.fit_spread``). The recording was made on a shared 2-core machine whose
step times scatter more than the H200's (per step, a coefficient of variation of about 0.5, most of
it noise: two passes over the same steps hardly correlate), so the recorded spread would overstate
the cost of lockstep.

**Calibration** (``--calibrate``): the same emulator against every figure of the H200 record
(DESIGN.md, RESULTS.md; 2026-11-27/28): one raw env (484 steps/s, at ``h200``), 15 independent (5,623;
at ``h200`` and at ``h200-loaded``), 15 in lockstep (3,774, a barrier after each step; the record's
used a spin barrier), and collection at N=15, repeat 2 (gym 1,728 f/s; the README pipeline 0.89x gym;
TorchRL's ``AsyncBatchedCollector`` over single envs, ``async:auto``, 0.97x gym), each beside the
record with the emulator's ratio to it.

**What it cannot model**, and which way that biases each contender:

- contention between real sims: memory bandwidth, shared caches, turbo falling as cores fill up
  (15 independent envs on the H200 ran at 0.77 of one alone). Sleeping workers do not slow each
  other down. ``h200-loaded`` folds the N=15 slow-down into the mean as a constant, so the emulator
  is optimistic past 15 busy cores and pessimistic below for every contender alike in its ideal; the
  lockstep contenders (gym, README) lose more to it than the asynchronous path, since the slowest
  env of each step sets their pace and contention widens the spread, which the fitted spread only
  matches at N=15;
- the cost of a worker's own work beside its sim (pipes, copies, the wrappers' Python): here it is
  real, but on 2 cores shared by N workers and the main process, where on the target each worker has
  a core. At large N this overstates the main process's wait for a core and biases against the
  contender whose workers do the most per step (gym's: ManiSkill's wrappers and gymnasium's worker
  loop; the library's workers are leaner);
- the main process's speed: it runs on this machine's core, not the target's (the H200 host's cores
  were faster: one PickCube-v1 step 2.07 ms there against about 2.2 ms here, alone); a contender
  whose main process saturates (gym's ``AsyncVectorEnv`` at large N) is shown a little slower than
  on the target;
- sleep itself: each sleep overshoots by some tens of microseconds (the replay sets Linux's timer
  slack to 1 ns), about 2% of a 2.67 ms step, alike for all; and waking N sleeping workers at once
  costs 2 cores more than N cores.

Run (from the repository root)::

    python -m benchmarks.bench_many_cores [--n 1 4 8 15 32 64] [--rounds 3] [--seconds 5]
        [--step-ms h200-loaded] [--spread auto] [--calibrate] [--csv PATH] [--out results.json]

About 20-30 minutes on 2 cores for the default sweep, and 8 more with ``--calibrate``.
Quick check of the code: ``--n 1 4 --rounds 1 --seconds 1 --max-wait 0 --retries 0``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import shlex
import signal
import statistics
import sys
import time

from benchmarks import many_cores
from benchmarks.alternate import ProcessContender, ProcessResult, add_alternation_args, run_alternating
from benchmarks.machine import machine_line, save_json

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
CSV = os.path.join(HERE, "collection", "many_cores_emulated.csv")


def child_env(step_ms: str, spread: float) -> dict[str, str]:
    from benchmarks.replay_task import REPLAY_ID, SPREAD_ENV, STEP_MS_ENV

    return {"BENCH_ENV_ID": REPLAY_ID, STEP_MS_ENV: str(step_ms), SPREAD_ENV: repr(spread)}


def contender(name: str, spec: str, n: int, repeat: int, seconds: float, env: dict) -> ProcessContender:
    argv = [sys.executable, "-m", "benchmarks.bench_many_cores", "--child", spec, "--n", str(n)]
    return ProcessContender(name, argv + ["--repeat", str(repeat), "--seconds", str(seconds)], env=env)


def fps(res: ProcessResult) -> float | None:
    return 1.0 / res.median if res.ok else None


def cell(name: str, n: int) -> str:
    return f"{name} N={n}"


def sweep_rows(results: dict, names: list[str], ns: list[int], ideal) -> list[dict]:
    """One row per contender and N: median frames/s, min-max, share of the ideal, ratio to gym."""
    rows = []
    for n in ns:
        gym = results.get(cell("gym", n))
        gym_fps = fps(gym) if gym is not None else None
        for name in names:
            res = results.get(cell(name, n))
            if res is None:
                continue
            row = {"contender": name, "n": n, "ideal": ideal(n), "rounds": len(res.per_unit), "note": res.note}
            if res.ok:
                f = fps(res)
                wall = [u * p for u, p in zip(res.units, res.per_unit_wall)]
                row.update(
                    frames_per_s=f,
                    min=1.0 / max(res.per_unit),
                    max=1.0 / min(res.per_unit),
                    share=f / ideal(n),
                    x_gym=f / gym_fps if gym_fps else None,
                    main_cores=statistics.median(
                        u * p / w for u, p, w in zip(res.units, res.per_unit_cpu, wall) if w > 0
                    ),
                )
            rows.append(row)
    return rows


def fmt_sweep(rows: list[dict]) -> str:
    out = [
        "| contender | N | frames/s (median) | min-max | emulated ideal | share of ideal | x gym | main process cores "
        "| rounds |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "frames_per_s" not in r:
            out.append(f"| {r['contender']} | {r['n']} | - | - | {r['ideal']:.0f} | - | - | - | 0 |")
            continue
        x = f"{r['x_gym']:.2f}x" if r.get("x_gym") else "-"
        out.append(
            f"| {r['contender']} | {r['n']} | {r['frames_per_s']:.0f} | {r['min']:.0f}-{r['max']:.0f} | "
            f"{r['ideal']:.0f} | {100 * r['share']:.0f}% | {x} | {r['main_cores']:.2f} | {r['rounds']} |"
        )
    notes = [f"- {r['contender']} N={r['n']}: {r['note'].splitlines()[0][:300]}" for r in rows if r.get("note")]
    return "\n".join(out + ([""] + notes if notes else []))


def write_csv(path: str, rows: list[dict], header: list[str]) -> None:
    import csv

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", newline="") as f:
        for line in header:
            f.write(f"# {line}\n")
        w = csv.writer(f, lineterminator="\n")
        w.writerow(
            ["pipeline", "label", "n", "frames_per_s", "min", "max", "ratio_to_gym", "ideal_frames_per_s", "share"]
        )
        for r in rows:
            if "frames_per_s" not in r:
                continue
            w.writerow(
                [
                    r["contender"],
                    many_cores.CONTENDERS[r["contender"]][2],
                    r["n"],
                    round(r["frames_per_s"]),
                    round(r["min"]),
                    round(r["max"]),
                    "" if r.get("x_gym") is None or r["contender"] == "gym" else f"{r['x_gym']:.2f}",
                    round(r["ideal"]),
                    f"{r['share']:.3f}",
                ]
            )


def calibration_table(results: dict, ideal15: float, spread: float, step_times) -> str:
    """The H200 record beside the emulator's figures."""
    h = many_cores.H200

    def got(name: str) -> float | None:
        res = results.get(name)
        return fps(res) if res is not None else None

    gym15, readme15, async15 = got(cell("gym", 15)), got(cell("readme", 15)), got(cell("async", 15))
    torchrl15 = got(cell("torchrl-async", 15))
    share = many_cores.lockstep_share(step_times, 15, spread)
    rows = [
        (
            "one real PickCube-v1 env here, steps/s",
            h["raw_steps_per_s"],
            got("ceiling real h200"),
            "this machine's speed now (its main processes run at it)",
        ),
        ("one raw env, steps/s (`h200`)", h["raw_steps_per_s"], got("ceiling raw h200"), "the target's mean"),
        (
            "15 independent, steps/s (`h200`)",
            h["independent_15"],
            got("ceiling independent h200"),
            "sleeps do not contend",
        ),
        (
            "15 independent, steps/s (`h200-loaded`)",
            h["independent_15"],
            got("ceiling independent h200-loaded"),
            "the mean fitted to it",
        ),
        (
            "15 in lockstep, steps/s (`h200-loaded`)",
            h["lockstep_15"],
            got("ceiling lockstep h200-loaded"),
            f"spread fitted: {share:.3f} of independent predicted",
        ),
        ("gym, N=15, repeat 2, frames/s", h["gym_15_r2"], gym15, f"ideal {ideal15:.0f}"),
        (
            "README pipeline, x gym",
            h["readme_15_r2_x_gym"],
            readme15 / gym15 if readme15 and gym15 else None,
            "",
        ),
        (
            "TorchRL AsyncBatchedCollector, x gym",
            h["torchrl_async_15_r2_x_gym"],
            torchrl15 / gym15 if torchrl15 and gym15 else None,
            "",
        ),
        ("asynchronous path, x gym", None, async15 / gym15 if async15 and gym15 else None, "not on record"),
    ]
    out = ["| figure | H200 record | emulator | emulator / record | note |", "|---|---:|---:|---:|---|"]

    def show(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f}" if v < 10 else f"{v:,.0f}"

    for name, record, emu, note in rows:
        r, e = show(record), show(emu)
        q = f"{emu / record:.2f}" if record and emu else "-"
        out.append(f"| {name} | {r} | {e} | {q} | {note} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[1, 4, 8, 15, 32, 64], help="sub-envs (default 1 4 8 15 32 64)")
    p.add_argument("--repeat", type=int, nargs="+", default=[2], help=argparse.SUPPRESS)
    p.add_argument("--rounds", type=int, default=3, help="alternating rounds per N (default 3)")
    p.add_argument("--seconds", type=float, default=5.0, help="timed collection per run (default 5)")
    p.add_argument("--contenders", nargs="+", default=list(many_cores.CONTENDERS), choices=list(many_cores.CONTENDERS))
    p.add_argument("--step-ms", default="h200-loaded", help="target mean sim-step time: ms or a name (h200, ...)")
    p.add_argument("--spread", default="auto", help="spread of the step times, 0-1, or auto (fitted to the H200)")
    p.add_argument("--calibrate", action="store_true", help="also run the calibration against the H200 record")
    p.add_argument("--csv", default=None, help=f"write the sweep's CSV here (the docs' is {os.path.relpath(CSV)})")
    p.add_argument("--out", default=None, help="write all results as JSON here")
    add_alternation_args(p, retries=1)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.child is not None:
        many_cores.run_child(args.child, args.n[0], args.repeat[0], args.seconds)
        return 0

    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    from benchmarks.replay_task import load_recording

    repeat = args.repeat[0]
    rec = load_recording()
    spread = many_cores.fit_spread(rec["step_s"], many_cores.H200["lockstep_15"] / many_cores.H200["independent_15"])
    if args.spread != "auto":
        spread = float(args.spread)
    step_times, reset_times = many_cores.scaled_times(args.step_ms, spread)
    mean_step, mean_reset = float(step_times.mean()), float(reset_times.mean())

    def ideal(n: int) -> float:
        return many_cores.ideal_fps(n, repeat, mean_step, mean_reset)

    command = "python -m benchmarks.bench_many_cores " + shlex.join(argv if argv is not None else sys.argv[1:])
    print(machine_line())
    print(
        f"replay of {rec['meta']['env_id']} (recorded {rec['meta']['date']}): step {1e3 * mean_step:.3f} ms mean "
        f"(--step-ms {args.step_ms}), reset {1e3 * mean_reset:.2f} ms, spread {spread:g} (--spread {args.spread}); "
        f"lockstep of 15 predicted at {many_cores.lockstep_share(rec['step_s'], 15, spread):.3f} of independent",
        flush=True,
    )
    t0 = time.perf_counter()
    env = child_env(args.step_ms, spread)
    names = list(args.contenders)
    groups = []
    for n in args.n:
        group = [contender(cell(c, n), many_cores.spec_for(c, n), n, repeat, args.seconds, env) for c in names]
        if args.calibrate and n == 15:
            group.append(contender(cell("torchrl-async", 15), "async:auto", 15, repeat, args.seconds, env))
        groups.append(group)
    if args.calibrate:
        if 15 not in args.n:
            groups.append(
                [
                    contender(cell(c, 15), many_cores.spec_for(c, 15), 15, repeat, args.seconds, env)
                    for c in ["gym", "readme", "async", "torchrl-async"]
                ]
            )
        ceilings = []
        for kind, target in (
            ("real", "h200"),
            ("raw", "h200"),
            ("independent", "h200"),
            ("independent", "h200-loaded"),
            ("lockstep", "h200-loaded"),
        ):
            ceilings.append(
                contender(
                    f"ceiling {kind} {target}", f"ceiling:{kind}", 15, repeat, args.seconds, child_env(target, spread)
                )
            )
        groups.append(ceilings)
    results: dict[str, ProcessResult] = {}
    runs: list[dict] = []

    def on_result(name: str, r: int, payload: dict) -> None:
        runs.append({"name": name, "round": r, "result": payload})

    for group in groups:
        results.update(run_alternating(group, args, cwd=ROOT, on_result=on_result))
    took = time.perf_counter() - t0
    names_shown = names + (["torchrl-async"] if args.calibrate else [])
    rows = sweep_rows(results, names_shown, sorted(set(args.n) | ({15} if args.calibrate else set())), ideal)
    table = fmt_sweep(rows)
    print(
        f"\n{rec['meta']['env_id']} replayed (ReplayPickCube-v1), repeat {repeat}, random actions; frames = agent "
        f"steps; median of {args.rounds} rounds x {args.seconds:g} s, one process per run ({took:.0f} s in all). "
        f"Emulated ideal: N / ({EPISODE_NOTE}).\n"
    )
    print(table)
    calibration = None
    if args.calibrate:
        calibration = calibration_table(results, ideal(15), spread, rec["step_s"])
        print("\nCalibration against the H200 record (DESIGN.md, RESULTS.md; 2026-11-27/28):\n")
        print(calibration)
    header = [
        "Written by benchmarks/bench_many_cores.py: collection frames/s on the many-core emulator (the replay task, "
        "benchmarks/replay_task.py); median of the rounds, min-max; ratio_to_gym at the same N; ideal_frames_per_s: "
        "N envs that never wait; share: frames_per_s / ideal.",
        f"Machine: {machine_line()}; date {dt.date.today().isoformat()}. Emulated: step {1e3 * mean_step:.3f} ms mean "
        f"(--step-ms {args.step_ms}), reset {1e3 * mean_reset:.2f} ms, spread {spread:g}; repeat {repeat}.",
        f"Command: {command}",
    ]
    csv_path = args.csv
    if csv_path:
        write_csv(csv_path, [r for r in rows if r["contender"] in many_cores.CONTENDERS], header)
        print(f"\nwrote {csv_path}")
    if args.out:
        save_json(
            args.out,
            {
                "benchmark": "bench_many_cores",
                "command": command,
                "step_ms": args.step_ms,
                "spread": spread,
                "mean_step_s": mean_step,
                "mean_reset_s": mean_reset,
                "wall_s": took,
                "rows": rows,
                "table": table,
                "calibration": calibration,
                "runs": runs,
                "results": {k: v.as_dict() for k, v in results.items()},
            },
        )
        print(f"wrote {args.out}")
    return 0


EPISODE_NOTE = "50 sim steps x mean step + mean reset) x 25 agent steps per episode"


if __name__ == "__main__":
    sys.exit(main())
