"""Many cores, emulated on few: collection frames/s at N = 1 to 64 on the replay task (issues 51, 59).

The task is ``benchmarks/replay_task.py``'s ``ReplayPickCube-v1``: PickCube-v1's recorded outputs,
each step *sleeping* its recorded time scaled to a target machine. A sleeping worker needs no core,
so ``N`` of them on 2 cores stand in for ``N`` sims on ``N`` cores; what really needs a core (the
main process, each worker's own overhead around its sim) competes for the 2 cores as it would for
one core per process. Contenders, at action repeat 2, from ``collection_pipelines.py`` (its frame
rule: frames are agent steps, a reset is never a frame):

- ``gym``: gymnasium's ``AsyncVectorEnv(context="forkserver")`` of ManiSkill's ``CPUGymWrapper(
  ActionRepeatWrapper(gym.make(id), 2))``, stepped with ``action_space.sample()`` (``gym``); its sims
  step in autograd's grad mode, so its sleeps carry the **grad-mode factor** (``--grad-factor``,
  default ``measure``: measured first in the same run, on this machine, ``many_cores.grad_factor``:
  real PickCube-v1 episodes alternating between grad and inference mode; ``h200``: 484 / 386);
- ``gym-nograd``: the same, its sleeps without that factor (as if gym's sims stepped in inference
  mode): the figures against gym are given against both;
- ``readme``: the README pipeline, ``Collector(TransformedEnv(ManiSkillEnv(id, num_envs=N),
  Compose(ActionRepeat(2), EpisodeMetrics())), RandomPolicy)`` (``batched:t1,rp,dev,em``), every
  sub-env in a worker at N > 1 (``workers``: what the library picks on a machine with more cores
  than sub-envs, the one emulated);
- ``async``: ``AsyncPoolCollector(ManiSkillAsyncEnvPool(id, N, repeat=2))``, random actions
  (``async:lib``).

**Every contender's envs replay distinct episodes**: a seeded reset replays ``seed % 20``, an
unseeded one the episode after the env's last (``replay_task``), so gym's workers (seeded ``s + i``,
then auto-reset unseeded), the README pipeline's (seeded ``s + i`` at every reset) and the
asynchronous pool's (each env its own seed stream) each go on from their own offset, as real envs,
whose actions differ, would; the lockstep share fitted below assumes the same.

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

**Per-env costs and a prediction**: each run's main-process and workers' CPU per frame; for the
asynchronous path, what they predict on N + 1 real cores (``predicted_fps``): each env a core for its
sims plus its worker's CPU, the main process a core and a server the envs queue at (mean value
analysis of that closed network), checked against the run at N = 1 and 4, where 2 cores are not
saturated; the former model without the main process's time and queue beside it; issue 59's targets
(``TARGETS``). ``--busy K`` runs K busy-loop processes beside every run (a learner's stand-in).

**What it cannot model**, and which way that biases each contender (measured 2026-11-29,
``benchmarks/RESULTS.md``, "Many cores, emulated"):

- the workers' and the main process's own CPU (pipes, copies, wrappers, TorchRL) runs on 2 shared
  cores, slower than the target's (``ceiling real``: a real PickCube-v1 env here, against 484 steps/s
  on the H200), instead of one core each. It saturates the 2 cores past N=15, and at N=15 it already
  costs gym (0.85 ms of worker CPU per frame) and TorchRL's ``AsyncBatchedCollector`` (3.3 ms) most:
  the emulator is pessimistic for every contender, the more so the heavier its workers and the larger
  N (gym 0.72 of its H200 figure at N=15; ``AsyncBatchedCollector`` 0.45x gym against 0.97x there).
  Work after a sleep also runs slower than back to back (cold caches, an idle vCPU);
- contention between real sims: memory bandwidth, shared caches, turbo falling as cores fill up
  (15 independent envs on the H200 ran at 0.77 of one alone). Sleeping workers do not slow each
  other down: ``h200-loaded`` folds the N=15 slow-down into the mean, and ``--spread auto`` the
  spread it brings into the step times, as constants. Past 15 the emulator understates both, which
  favours the lockstep contenders (gym, README) that wait for the slowest env of each step; below 15
  it overstates them, which favours the asynchronous path;
- autograd's mode: a real sim step in grad mode (gymnasium's worker loop) cost 484/386 = 1.25x more on
  one H200 env, 1.13x here (2026-12-01); one factor, measured on one env, is applied at every N, though
  under contention it may differ: hence ``gym-nograd`` beside ``gym``;
- 20 recorded episodes: past N = 20 several envs replay one episode at once (in lockstep, at the same
  step), milder stragglers than distinct real envs would give: a bias for gym and README at 32, 64;
- sleep itself: each sleep overshoots by some tens of microseconds (the replay sets Linux's timer
  slack to 1 ns; one raw replay env reaches about 0.94 of its target), alike for all.

Run (from the repository root)::

    python -m benchmarks.bench_many_cores [--n 1 4 8 15 32 64] [--rounds 3] [--seconds 5]
        [--step-ms h200-loaded] [--spread auto] [--grad-factor measure] [--contenders gym gym-nograd
        readme async async+sched=other] [--busy 0] [--calibrate] [--csv PATH] [--out results.json]

About 25 minutes on 2 cores for the default sweep, 30 with ``--calibrate``. ``--report JSON`` prints
the tables (and writes ``--csv``) again from a run's ``--out``. Quick check of the code: ``--n 1 4
--rounds 1 --seconds 1 --max-wait 0 --retries 0``.
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


def child_env(step_ms: str, spread: float, grad: float = 1.0) -> dict[str, str]:
    from benchmarks.replay_task import GRAD_FACTOR_ENV, REPLAY_ID, SPREAD_ENV, STEP_MS_ENV

    return {
        "BENCH_ENV_ID": REPLAY_ID,
        STEP_MS_ENV: str(step_ms),
        SPREAD_ENV: repr(spread),
        GRAD_FACTOR_ENV: repr(grad),
    }


def contender(name: str, spec: str, n: int, repeat: int, seconds: float, env: dict) -> ProcessContender:
    argv = [sys.executable, "-m", "benchmarks.bench_many_cores", "--child", spec, "--n", str(n)]
    return ProcessContender(name, argv + ["--repeat", str(repeat), "--seconds", str(seconds)], env=env)


def fps(res: ProcessResult) -> float | None:
    return 1.0 / res.median if res.ok else None


def cell(name: str, n: int) -> str:
    return f"{name} N={n}"


def sweep_rows(results: dict, names: list[str], ns: list[int], ideal) -> list[dict]:
    """One row per contender and N: median frames/s, min-max, share of the ideal, ratio to gym (its
    sleeps with the grad-mode factor, ``x_gym``, and without, ``x_gym_nograd``), the CPU that the
    main process and the workers spent per frame (medians over rounds), and for the asynchronous path
    what those costs predict on N + 1 real cores (:func:`predicted_fps`; ``predicted_no_queue``: the
    former model, :func:`predicted_fps_no_queue`)."""
    rows = []
    for n in ns:
        gym, gym1 = results.get(cell("gym", n)), results.get(cell("gym-nograd", n))
        gym_fps = fps(gym) if gym is not None else None
        gym1_fps = fps(gym1) if gym1 is not None else None
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
                    x_gym_nograd=f / gym1_fps if gym1_fps else None,
                    main_cores=statistics.median(
                        u * p / w for u, p, w in zip(res.units, res.per_unit_cpu, wall) if w > 0
                    ),
                    workers_cores=statistics.median(
                        e.get("workers_cpu_s", 0.0) / w for e, w in zip(res.extra, wall) if w > 0
                    ),
                    main_ms=1e3 * statistics.median(res.per_unit_cpu),
                    workers_ms=1e3
                    * statistics.median(e.get("workers_cpu_s", 0.0) / u for e, u in zip(res.extra, res.units)),
                )
                if name == "async":
                    costs = (n, 1.0 / ideal(1), row["main_ms"] / 1e3, row["workers_ms"] / 1e3)
                    row["predicted"] = predicted_fps(*costs)
                    row["predicted_no_queue"] = predicted_fps_no_queue(*costs)
            rows.append(row)
    return rows


def predicted_fps(n: int, env_s: float, main_s: float, workers_s: float) -> float:
    """Frames/s of the asynchronous path on ``n + 1`` real cores, from its costs measured here, with the
    main process as a server: each env, on a core of its own, spends ``env_s`` per frame on its sims
    and reset (the ideal's) plus its worker's CPU per frame, ``workers_s``, then waits for the main
    process, on its own core, to serve its frame (``main_s`` of CPU), behind the envs already waiting.
    A closed network of ``n`` envs between a delay (``env_s + workers_s``) and one queue (``main_s``),
    solved by mean value analysis: at ``n = 1`` an env's cycle is ``env_s + workers_s + main_s``; as
    ``n`` grows the queue's wait grows and the whole tends to ``1 / main_s``. Costs measured on 2
    crowded cores overstate both (wake-ups, switches, a slower core)."""
    think = env_s + workers_s
    queue = 0.0  # mean envs at the main process
    fps_ = 0.0
    for k in range(1, n + 1):
        response = main_s * (1.0 + queue)
        fps_ = k / (think + response)
        queue = fps_ * response
    return fps_


def predicted_fps_no_queue(n: int, env_s: float, main_s: float, workers_s: float) -> float:
    """The former prediction (issue 51): ``n`` envs at ``env_s + workers_s`` per frame, bounded by the
    main process at ``1 / main_s``; it leaves the main process's time out of each env's cycle and
    ignores the queue behind it, so it is high wherever the main process is not idle."""
    return min(n / (env_s + workers_s), 1.0 / main_s if main_s > 0 else float("inf"))


#: Issue 59's targets on the emulator, checked by :func:`targets` (``None``: a figure to report, no bar).
TARGETS = (
    ("async", 15, "x_gym", 1.4),
    ("async", 15, "x_gym_nograd", 1.4),
    ("readme", 15, "x_gym", 1.0),
    ("readme", 15, "x_gym_nograd", None),
    ("async", 64, "share", None),
)
_WHAT = {"x_gym": "gym", "x_gym_nograd": "gym without the grad-mode factor", "share": "of the ideal on 2 cores"}


def targets(rows: list[dict]) -> str:
    """Each target of :data:`TARGETS` with the figure measured, met or not; then the server model
    (:func:`predicted_fps`) against the asynchronous path measured where 2 cores are not saturated."""
    out = []
    for name, n, key, target in TARGETS:
        row = next((r for r in rows if r["contender"] == name and r["n"] == n and key in r), None)
        if row is None or row[key] is None:
            continue
        got = f"{100 * row[key]:.0f}%" if key == "share" else f"{row[key]:.2f}x"
        line = f"- {name} N={n}: {got} {_WHAT[key]}"
        if target is not None:
            line += f" (target {target:g}x): {'met' if row[key] >= target else 'NOT met'}"
        if key == "share" and row.get("predicted"):
            line += (
                f"; its costs here (main {row['main_ms']:.3f}, workers {row['workers_ms']:.3f} ms CPU per frame) "
                f"predict {row['predicted']:.0f} f/s, {100 * row['predicted'] / row['ideal']:.0f}% of the ideal, "
                f"on {n + 1} real cores (main process as a server; "
                f"{100 * row['predicted_no_queue'] / row['ideal']:.0f}% without its queue)"
            )
        out.append(line)
    for row in rows:
        if row["contender"] == "async" and row["n"] in (1, 4) and row.get("predicted"):
            out.append(
                f"- model check, async N={row['n']} (2 cores not saturated: main + workers "
                f"{row['main_cores'] + row['workers_cores']:.2f} cores): measured {row['frames_per_s']:.0f} f/s, "
                f"predicted {row['predicted']:.0f} ({row['predicted'] / row['frames_per_s']:.2f}x; without the queue "
                f"{row['predicted_no_queue']:.0f}, {row['predicted_no_queue'] / row['frames_per_s']:.2f}x)"
            )
    return "\n".join(out)


def fmt_sweep(rows: list[dict]) -> str:
    out = [
        "| contender | N | frames/s (median) | min-max | emulated ideal | share of ideal | x gym | x gym-nograd "
        "| cores: main / workers | CPU ms per frame: main / workers | on N+1 real cores (predicted) | rounds |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "frames_per_s" not in r:
            out.append(f"| {r['contender']} | {r['n']} | - | - | {r['ideal']:.0f} | - | - | - | - | - | - | 0 |")
            continue
        x = f"{r['x_gym']:.2f}x" if r.get("x_gym") else "-"
        x1 = f"{r['x_gym_nograd']:.2f}x" if r.get("x_gym_nograd") else "-"
        pred = f"{r['predicted']:.0f} ({100 * r['predicted'] / r['ideal']:.0f}%)" if r.get("predicted") else "-"
        out.append(
            f"| {r['contender']} | {r['n']} | {r['frames_per_s']:.0f} | {r['min']:.0f}-{r['max']:.0f} | "
            f"{r['ideal']:.0f} | {100 * r['share']:.0f}% | {x} | {x1} | "
            f"{r['main_cores']:.2f} / {r['workers_cores']:.2f} | "
            f"{r['main_ms']:.3f} / {r['workers_ms']:.3f} | {pred} | {r['rounds']} |"
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
            ["pipeline", "label", "n", "frames_per_s", "min", "max", "ratio_to_gym", "ratio_to_gym_nograd"]
            + ["ideal_frames_per_s", "share", "main_cores", "workers_cores", "main_cpu_ms_per_frame"]
            + ["workers_cpu_ms_per_frame", "predicted_frames_per_s"]
        )
        gyms = ("gym", "gym-nograd")
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
                    "" if r.get("x_gym") is None or r["contender"] in gyms else f"{r['x_gym']:.2f}",
                    "" if r.get("x_gym_nograd") is None or r["contender"] in gyms else f"{r['x_gym_nograd']:.2f}",
                    round(r["ideal"]),
                    f"{r['share']:.3f}",
                    f"{r['main_cores']:.2f}",
                    f"{r['workers_cores']:.2f}",
                    f"{r['main_ms']:.3f}",
                    f"{r['workers_ms']:.3f}",
                    round(r["predicted"]) if r.get("predicted") else "",
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
    p.add_argument(
        "--contenders",
        nargs="+",
        default=list(many_cores.CONTENDERS),
        help=f"of {', '.join(many_cores.CONTENDERS)}; NAME+OPTIONS adds pipeline options (async+sched=other)",
    )
    p.add_argument("--step-ms", default="h200-loaded", help="target mean sim-step time: ms or a name (h200, ...)")
    p.add_argument("--spread", default="auto", help="spread of the step times, 0-1, or auto (fitted to the H200)")
    p.add_argument(
        "--grad-factor",
        default="measure",
        help="gym's sleeps in grad mode, x: 'measure' (on this machine, first, default), 'h200' or a number",
    )
    p.add_argument("--calibrate", action="store_true", help="also run the calibration against the H200 record")
    p.add_argument("--csv", default=None, help=f"write the sweep's CSV here (the docs' is {os.path.relpath(CSV)})")
    p.add_argument("--out", default=None, help="write all results as JSON here")
    p.add_argument("--report", default=None, metavar="JSON", help="no run: the tables (and --csv) from a run's --out")
    add_alternation_args(p, retries=1)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.child is not None:
        many_cores.run_child(args.child, args.n[0], args.repeat[0], args.seconds)
        return 0
    unknown = [c for c in args.contenders if c.partition("+")[0] not in many_cores.CONTENDERS]
    if unknown:
        p.error(f"unknown contenders {unknown}: {', '.join(many_cores.CONTENDERS)}, each with +OPTIONS or not")
    if args.report is not None:
        report_from_json(args.report, args.csv)
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
    results: dict[str, ProcessResult] = {}
    runs: list[dict] = []

    def on_result(name: str, r: int, payload: dict) -> None:
        runs.append({"name": name, "round": r, "result": payload})

    grad, grad_note = measured_grad_factor(args, results, on_result)
    print(f"grad-mode factor on gym's sleeps: {grad:.3f} ({grad_note})", flush=True)
    env = child_env(args.step_ms, spread, grad)
    envs = {
        c: child_env(args.step_ms, spread, grad if c.partition("+")[0] in many_cores.GRAD_MODE else 1.0)
        for c in args.contenders
    }
    names = list(args.contenders)
    groups = []
    for n in args.n:
        group = [contender(cell(c, n), many_cores.spec_for(c, n), n, repeat, args.seconds, envs[c]) for c in names]
        if args.calibrate and n == 15:
            group.append(contender(cell("torchrl-async", 15), "async:auto", 15, repeat, args.seconds, env))
        groups.append(group)
    if args.calibrate:
        if 15 not in args.n:
            groups.append(
                [
                    contender(cell(c, 15), many_cores.spec_for(c, 15), 15, repeat, args.seconds, envs.get(c, env))
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
    for group in groups:
        results.update(run_alternating(group, args, cwd=ROOT, on_result=on_result))
    settings = {
        "command": command,
        "step_ms": args.step_ms,
        "spread": spread,
        "grad_factor": grad,
        "grad_factor_note": grad_note,
        "mean_step_s": mean_step,
        "mean_reset_s": mean_reset,
        "repeat": repeat,
        "rounds": args.rounds,
        "seconds": args.seconds,
        "n": args.n,
        "contenders": names,
        "calibrate": args.calibrate,
        "wall_s": time.perf_counter() - t0,
    }
    report(results, runs, settings, args.csv, args.out)
    return 0


def measured_grad_factor(args: argparse.Namespace, results: dict, on_result) -> tuple[float, str]:
    """The factor on gym's sleeps in grad mode (``--grad-factor``): measured here first (one child,
    ``many_cores.grad_factor``: real PickCube-v1 episodes alternating between the two modes, for 2 x
    ``--seconds``), the H200's (``replay_task.GRAD_FACTOR``) or a number; and how it was had."""
    from benchmarks.replay_task import GRAD_FACTOR

    if args.grad_factor == "h200":
        return GRAD_FACTOR, "the H200's, 484 / 386 steps/s (2026-11-28)"
    if args.grad_factor != "measure":
        return float(args.grad_factor), "given"
    name = "grad factor real"
    c = contender(name, "grad", 1, 1, max(args.seconds, 3.0), {})
    once = argparse.Namespace(**{**vars(args), "rounds": 1})
    results.update(run_alternating([c], once, cwd=ROOT, on_result=on_result))
    res = results[name]
    if not res.ok:
        return GRAD_FACTOR, f"not measured ({res.note}): the H200's"
    e = res.extra[-1]
    return float(e["grad_factor"]), (
        f"measured here: real PickCube-v1 episodes, grad / inference mode, medians of {res.units[-1]} pairs, "
        f"pairs {e['pairs_min']:.2f}-{e['pairs_max']:.2f}; the H200's {GRAD_FACTOR:.3f}"
    )


def report(results: dict, runs: list[dict], settings: dict, csv_path: str | None, out: str | None) -> None:
    """Prints the sweep's table (and the calibration's, the targets), writes the CSV and the JSON."""
    from benchmarks.replay_task import load_recording

    rec = load_recording()
    repeat, spread, calibrate = settings["repeat"], settings["spread"], settings["calibrate"]
    mean_step, mean_reset = settings["mean_step_s"], settings["mean_reset_s"]

    def ideal(n: int) -> float:
        return many_cores.ideal_fps(n, repeat, mean_step, mean_reset)

    names_shown = settings["contenders"] + (["torchrl-async"] if calibrate else [])
    ns = sorted(set(settings["n"]) | ({15} if calibrate else set()))
    rows = sweep_rows(results, names_shown, ns, ideal)
    table = fmt_sweep(rows)
    print(
        f"\n{rec['meta']['env_id']} replayed (ReplayPickCube-v1), repeat {repeat}, random actions; frames = agent "
        f"steps; median of {settings['rounds']} rounds x {settings['seconds']:g} s, one process per run "
        f"({settings['wall_s']:.0f} s in all). Emulated ideal: N / ({EPISODE_NOTE}).\n"
    )
    print(table)
    if "grad_factor" in settings:
        print(f"\ngrad-mode factor on gym's sleeps: {settings['grad_factor']:.3f} ({settings['grad_factor_note']})")
    print("\nTargets (issue 59):\n" + targets(rows))
    calibration = None
    if calibrate:
        calibration = calibration_table(results, ideal(15), spread, rec["step_s"])
        print("\nCalibration against the H200 record (DESIGN.md, RESULTS.md; 2026-11-27/28):\n")
        print(calibration)
    header = [
        "Written by benchmarks/bench_many_cores.py: collection frames/s on the many-core emulator (the replay task, "
        "benchmarks/replay_task.py); median of the rounds, min-max; ratio_to_gym at the same N; ideal_frames_per_s: "
        "N envs that never wait; share: frames_per_s / ideal; cores and CPU ms per frame: the main process's and "
        "its workers' (summed), medians over rounds.",
        f"Machine: {settings.get('machine') or machine_line()}; date {settings.get('date') or dt.date.today()}. "
        f"Emulated: step {1e3 * mean_step:.3f} ms mean (--step-ms {settings['step_ms']}), reset "
        f"{1e3 * mean_reset:.2f} ms, spread {spread:g}; repeat {repeat}; every env its own episodes; gym's sleeps "
        f"x {settings.get('grad_factor', 1.254):.2f} in grad mode, gym-nograd's x 1.",
        f"Grad-mode factor: {settings.get('grad_factor_note', 'the H200s')}.",
        f"Command: {settings['command']}",
    ]
    if csv_path:
        write_csv(csv_path, [r for r in rows if r["contender"] in many_cores.CONTENDERS], header)
        print(f"\nwrote {csv_path}")
    if out:
        save_json(
            out,
            {
                "benchmark": "bench_many_cores",
                **settings,
                "rows": rows,
                "table": table,
                "calibration": calibration,
                "runs": runs,
                "results": {k: v.as_dict() for k, v in results.items()},
            },
        )
        print(f"wrote {out}")


def report_from_json(path: str, csv_path: str | None) -> None:
    """The tables and the CSV again from a run's JSON (``--out``), with this version's columns."""
    import json

    from benchmarks.bench_collection import results_from_runs

    with open(path) as f:
        saved = json.load(f)
    runs = saved["runs"]
    names = list(dict.fromkeys(run["name"] for run in runs))
    results = results_from_runs(names, runs)
    settings = {k: saved[k] for k in ("command", "step_ms", "spread", "mean_step_s", "mean_reset_s", "wall_s")}
    settings.update({k: saved[k] for k in ("grad_factor", "grad_factor_note") if k in saved})
    cells = [name for name in names if not name.startswith(("ceiling", "grad"))]
    settings.update(
        repeat=saved.get("repeat", 2),
        rounds=saved.get("rounds", max(run["round"] for run in runs) + 1),
        seconds=saved.get("seconds", 5.0),
        n=sorted({int(name.split("N=")[1]) for name in cells}),
        contenders=[c for c in many_cores.CONTENDERS if any(name.startswith(c + " ") for name in cells)],
        calibrate=any(name.startswith("ceiling") for name in names),
        machine=machine_line(saved["machine"]),
        date=saved["machine"]["date"],
    )
    report(results, runs, settings, csv_path, None)


EPISODE_NOTE = "50 sim steps x mean step + mean reset) x 25 agent steps per episode"


if __name__ == "__main__":
    sys.exit(main())
