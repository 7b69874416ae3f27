"""Sphinx extension: draws the pictures of ``docs/curves.md`` from the data in git when the site is
built (``builder-inited``), into ``docs/_generated/curves/`` (git-ignored; no image is in git).

- the learning curves: ``benchmarks/ppo/pullcube_cpu_30min.csv`` (PPO, PullCube-v1)
  and ``pullcube_ppotrainer.csv`` (TorchRL's PPOTrainer), ``benchmarks/sac/pushcube_ee_b256.csv`` and
  ``pushcube_sactrainer.csv`` (SAC, PushCube-v1),
  ``benchmarks/rlpd/pickcube_offline_to_online{,_backup_entropy,_auto_entropy}.csv``
  (RLPD through TorchRL's OfflineToOnlineTrainer, PickCube-v1),
  ``benchmarks/bc/mlp_1000demos.csv`` (behaviour cloning). They are drawn by ``benchmarks/plot_ppo.py``
  and ``benchmarks/plot_runs.py``, the scripts that plot a run's ``metrics.jsonl``: each CSV row becomes
  one record of such a log;
- the collection figures, frames/s against N, this library against gym:
  ``benchmarks/collection/sweep_2cores.csv`` and ``benchmarks/collection/sweep_16cores_h200.csv``
  (the tables of ``benchmarks/RESULTS.md``, copied), and ``benchmarks/collection/many_cores_emulated.csv``
  (written by ``python -m benchmarks.bench_many_cores --csv ...``: the many-core emulator's sweep,
  with its ideal).

``draw_all(out_dir)`` draws every picture; ``tests/docs/test_curves.py`` runs it into a temporary
folder.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUT = "_generated/curves"  # under docs/, where docs/curves.md finds the pictures

# The evaluations of the PPO and SAC examples play 50 seeded episodes (benchmarks/RESULTS.md, "PPO"
# and "SAC"); their CSVs do not repeat it, plot_ppo's axis label says it.
RL_EVAL_EPISODES = 50


def read_csv(path: Path) -> list[dict]:
    """The rows of a CSV, ``#`` comment lines skipped, numbers as numbers, empty cells as None."""
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    rows = []
    for row in csv.DictReader(lines):
        rows.append({k: _number(v) for k, v in row.items()})
    return rows


def _number(v: str):
    if v == "":
        return None
    for kind in (int, float):
        try:
            return kind(v)
        except ValueError:
            pass
    return v


def _write_jsonl(rows: list[dict], path: Path) -> Path:
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def _quiet(main, argv: list[str]):
    """Runs a plot script's ``main`` without its "wrote ..." line; returns the figure it drew
    (still open: the scripts save it and leave it), for the touches below."""
    import matplotlib.pyplot as plt

    with contextlib.redirect_stdout(io.StringIO()):
        main(argv)
    return plt.gcf()


def _thousands(ax) -> None:
    from matplotlib.ticker import FuncFormatter

    ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0"))


def draw_ppo(out: Path, tmp: Path) -> Path:
    from benchmarks import plot_ppo

    rows = read_csv(ROOT / "benchmarks" / "ppo" / "pullcube_cpu_30min.csv")
    log = _write_jsonl([{**r, "episodes": RL_EVAL_EPISODES} for r in rows], tmp / "ppo.jsonl")
    png = out / "ppo_pullcube.png"
    title = "PPO on PullCube-v1 (pd_ee_delta_pos), CPU sim, 2 cores, 2026-11-23"
    fig = _quiet(plot_ppo.main, [str(log), "--out", str(png), "--title", title, "--target", "0.8"])
    # plot_ppo's wall-minutes axis puts a tick past the run's end (its interpolation stops at the
    # last evaluation, so 35 lands on 30); frames as 50k, not 50000, so that the labels do not touch.
    last_min = rows[-1]["wall_s"] / 60
    for ax in fig.axes:
        _thousands(ax)
        for top in ax.child_axes:
            top.set_xticks([m for m in range(0, int(last_min) + 1, 5)])
    fig.savefig(png, dpi=110)
    return png


def draw_ppo_rgb(out: Path, tmp: Path) -> Path:
    """PPO from 64-px rgb on PushCube-v1, 2 cores (issue 63): 20 seeded episodes per evaluation."""
    from benchmarks import plot_ppo

    rows = read_csv(ROOT / "benchmarks" / "ppo" / "pushcube_rgb_cpu.csv")
    log = _write_jsonl([{**r, "episodes": 20} for r in rows], tmp / "ppo_rgb.jsonl")
    png = out / "ppo_pushcube_rgb.png"
    title = "PPO from 64-px rgb on PushCube-v1 (pd_joint_delta_pos), CPU sim, 2 shared cores, 2026-12-02"
    fig = _quiet(plot_ppo.main, [str(log), "--out", str(png), "--title", title, "--target", "0.8"])
    for ax in fig.axes:
        _thousands(ax)
    fig.savefig(png, dpi=110)
    return png


def _draw_rl_runs(out: Path, tmp: Path, png_name: str, runs: list[tuple[str, str]], title: str):
    """RL runs side by side, one evaluation per CSV row (``runs``: label, CSV under benchmarks/),
    drawn by plot_runs; returns the figure, still open, for the caller's touches."""
    from benchmarks import plot_runs

    specs = []
    for label, name in runs:
        rows = read_csv(ROOT / "benchmarks" / f"{name}.csv")
        log = _write_jsonl([{**r, "episodes": RL_EVAL_EPISODES} for r in rows], tmp / f"{Path(name).name}.jsonl")
        specs.append(f"{label}={log}")
    fig = _quiet(plot_runs.main, [*specs, "--out", str(out / png_name), "--title", title])
    # plot_runs labels its axes for RL and BC runs together: these are RL runs.
    for ax in fig.axes[0::2]:
        ax.set_xlabel("frames (env steps)")
        _thousands(ax)
    fig.axes[0].set_ylabel(f"success_once ({RL_EVAL_EPISODES} seeded episodes)")
    fig.axes[2].set_ylabel("episode return (deterministic policy)")
    return fig


def _relegend(fig) -> None:
    """The legend below the axes again, with the lines added after the plot script drew it."""
    from benchmarks import plot_style

    for legend in list(fig.legends):
        legend.remove()
    plot_style.legend_below(fig, fig.axes)


def _target(fig, level: float = 0.8) -> None:
    """The success_once target, dotted (a reference level), on both success axes."""
    from benchmarks import plot_style

    for ax in fig.axes[:2]:
        ax.axhline(level, **plot_style.reference(), label=f"target success {level:g}")
    _relegend(fig)


def draw_sac(out: Path, tmp: Path) -> Path:
    runs = [("examples/sac_torchrl.py", "sac/pushcube_ee_b256"), ("TorchRL's SACTrainer", "sac/pushcube_sactrainer")]
    title = "SAC on PushCube-v1 (pd_ee_delta_pos, batch 256), CPU sim, 2 cores"
    fig = _draw_rl_runs(out, tmp, "sac_pushcube.png", runs, title)
    fig.savefig(out / "sac_pushcube.png", dpi=90)
    return out / "sac_pushcube.png"


def draw_ppo_trainer(out: Path, tmp: Path) -> Path:
    runs = [("examples/ppo_torchrl.py", "ppo/pullcube_cpu_30min"), ("TorchRL's PPOTrainer", "ppo/pullcube_ppotrainer")]
    title = "PPO on PullCube-v1 (pd_ee_delta_pos), CPU sim, 2 cores"
    fig = _draw_rl_runs(out, tmp, "ppo_pullcube_trainer.png", runs, title)
    _target(fig)
    fig.savefig(out / "ppo_pullcube_trainer.png", dpi=90)
    return out / "ppo_pullcube_trainer.png"


def draw_rlpd(out: Path, tmp: Path) -> Path:
    from benchmarks import plot_style

    runs = [
        ("target entropy -4, no entropy backup (the YAML's)", "rlpd/pickcube_offline_to_online"),
        ("target entropy -4, entropy backed up", "rlpd/pickcube_offline_to_online_backup_entropy"),
        ('target entropy -8 ("auto"), entropy backed up', "rlpd/pickcube_offline_to_online_auto_entropy"),
    ]
    title = "RLPD on PickCube-v1 (sparse reward, 200 demos), CPU sim, 2 cores"
    fig = _draw_rl_runs(out, tmp, "rlpd_pickcube.png", runs, title)
    # ManiSkill's RLPD README: PickCube-v1 in "around 50K" env samples with its sample-efficient config
    # (UTD 16, 10 critics, 1000 RL demos); this run is its walltime config's (UTD 0.5, 200k frames).
    fig.axes[0].axvline(50_000, **plot_style.reference(), label="ManiSkill's ~50k frames (another config)")
    fig.axes[0].annotate(
        "ManiSkill's ~50k\n(sample-efficient config)",
        (50_000, 0.5),
        xytext=(4, 0),
        textcoords="offset points",
        fontsize=8,
    )
    _target(fig)
    fig.suptitle(f"{title}: an evaluation every 10,000 frames")
    fig.savefig(out / "rlpd_pickcube.png", dpi=90)
    return out / "rlpd_pickcube.png"


def draw_bc(out: Path, tmp: Path) -> Path:
    from benchmarks import plot_runs

    rows = read_csv(ROOT / "benchmarks" / "bc" / "mlp_1000demos.csv")
    runs = []
    for task in dict.fromkeys(r["task"] for r in rows):
        records = [{k: v for k, v in r.items() if k != "task"} for r in rows if r["task"] == task]
        runs.append(f"{task}={_write_jsonl(records, tmp / f'bc_{task}.jsonl')}")
    png = out / "bc.png"
    title = "Behaviour cloning (MLP, 1000 demos), CPU sim, 2 cores, 2026-11-25"
    fig = _quiet(plot_runs.main, [*runs, "--out", str(png), "--title", title, "--markers-only"])
    # plot_runs labels its axes for RL and BC runs together; the two runs' wall clocks start at different
    # points. Two evaluations per run: points, not lines through them.
    episodes = rows[0]["episodes"]
    fig.suptitle(f"{title}: an evaluation every 2500 iterations")
    for ax in fig.axes[0::2]:
        ax.set_xlabel("iterations (gradient steps)")
        ax.set_xlim(0, max(r["iteration"] for r in rows) * 1.06)
    for ax in fig.axes[1::2]:
        ax.set_xlabel("wall minutes (PushCube-v1's include making the demos)")
        ax.set_xlim(0, max(r["wall_s"] for r in rows) / 60 * 1.06)
    fig.axes[0].set_ylabel(f"success_once ({episodes} seeded episodes)")
    fig.axes[2].set_ylabel("episode return (deterministic policy)")
    fig.savefig(png, dpi=90)
    return png


# The legend's names of the benchmark's pipelines (their ids in the CSVs, as ``bench_collection`` and
# ``bench_many_cores`` name them); each caption of docs/curves.md explains them and gives the ids.
LABELS = {
    "gym": "ManiSkill's gym path (AsyncVectorEnv of CPUGymWrapper)",
    "gym:t1": "ManiSkill's gym path, one torch thread per process",
    "gym-nograd": "ManiSkill's gym path, its sleeps without the grad-mode factor",
    "batched:t1,rp,dev,em": "README pipeline (Collector over ManiSkillEnv)",
    "batched:t1,rp,dev,em,workers": "README pipeline, every sub-env in a worker process",
    "readme": "README pipeline (Collector over ManiSkillEnv, lockstep)",
    "async:auto": "TorchRL's AsyncBatchedCollector over single envs",
    "async": "asynchronous pool (ManiSkillAsyncEnvPool + AsyncPoolCollector)",
}


def draw_collection(csv_path: Path, png: Path, title: str, error_bars: bool) -> Path:
    """frames/s against N, one line per pipeline, gym's first; the table's ratios to gym written
    beside their points; min-max bars where the CSV has them; a dotted line for N x gym's N=1."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks import plot_style

    rows = read_csv(csv_path)
    pipelines = list(dict.fromkeys(r["pipeline"] for r in rows))
    ns = sorted({r["n"] for r in rows})
    fig, ax = plt.subplots(figsize=(8.5, 6))
    # a small sideways shift per pipeline, so that points and bars at the same N do not hide each other
    shift = 0.012 * (ns[-1] - ns[0] or 1)
    notes = []
    for i, name in enumerate(pipelines):
        mine = sorted((r for r in rows if r["pipeline"] == name), key=lambda r: r["n"])
        xs = [r["n"] + (i - (len(pipelines) - 1) / 2) * shift for r in mine]
        ys = [r["frames_per_s"] for r in mine]
        marker = "os^D"[i % 4]
        style = plot_style.baseline(i, marker) if name.startswith("gym") else plot_style.measured(i, marker)
        label = LABELS.get(name, mine[0]["label"])
        if error_bars:
            err = [[r["frames_per_s"] - r["min"] for r in mine], [r["max"] - r["frames_per_s"] for r in mine]]
            ax.errorbar(xs, ys, yerr=err, capsize=4, label=label, **style)
        else:
            ax.plot(xs, ys, label=label, **style)
        notes += [(x, r, f"C{i}") for x, r in zip(xs, mine) if r.get("ratio_to_gym") is not None]
    # The table's ratios beside their points: left of the first N, right of the others; at one N,
    # the highest point's above and the next ones lower down, so that close points' notes do not overlap.
    for n in ns:
        here = sorted((t for t in notes if t[1]["n"] == n), key=lambda t: -t[1]["frames_per_s"])
        for rank, (x, r, color) in enumerate(here):
            first = n == ns[0]
            ax.annotate(
                f"{r['ratio_to_gym']:.2f}x gym",
                (x, r["frames_per_s"]),
                textcoords="offset points",
                xytext=(-10 if first else 10, 8 - 14 * rank),
                fontsize=9,
                color=color,
                ha="right" if first else "left",
                va="center",
                bbox=dict(fc="white", ec="none", alpha=0.8, pad=0.5),
            )
    gym1 = next(r["frames_per_s"] for r in rows if r["pipeline"] == "gym" and r["n"] == ns[0])
    ax.plot(
        ns,
        [n * gym1 / ns[0] for n in ns],
        **plot_style.reference(),
        label="N times gym's rate at N=1 (perfect scaling)",
    )
    ax.set_xticks(ns)
    ax.set_xlim(ns[0] - 0.12 * (ns[-1] - ns[0]), ns[-1] + 0.12 * (ns[-1] - ns[0]))
    ax.set_xlabel("N (sub-envs, one process each)")
    ax.set_ylabel("frames/s (agent steps per second)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=11)
    plot_style.legend_below(fig, [ax], ncol=1)
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return png


def draw_many_cores(csv_path: Path, png: Path) -> Path:
    """The emulator's sweep: frames/s against N with the emulated ideal (left, both axes on log
    scales), and each contender's share of that ideal (right); min-max bars, gym dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks import plot_style

    rows = read_csv(csv_path)
    meta = [line[2:] for line in csv_path.read_text().splitlines() if line.startswith("# ")]
    date = next((m.split("date ")[1].split(".")[0] for m in meta if "date " in m), "")
    pipelines = list(dict.fromkeys(r["pipeline"] for r in rows))
    ns = sorted({r["n"] for r in rows})
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 6.4))
    ideal = {r["n"]: r["ideal_frames_per_s"] for r in rows}
    left.plot(ns, [ideal[n] for n in ns], **plot_style.reference(), label="emulated ideal (N envs that never wait)")
    right.axhline(100, **plot_style.reference())
    for i, name in enumerate(pipelines):
        mine = sorted((r for r in rows if r["pipeline"] == name), key=lambda r: r["n"])
        xs = [r["n"] * (1 + 0.03 * (i - (len(pipelines) - 1) / 2)) for r in mine]
        marker = "os^D"[i % 4]  # gym, and gym-nograd (its sleeps without the grad-mode factor): the baselines
        style = plot_style.baseline(i, marker) if name.startswith("gym") else plot_style.measured(i, marker)
        err = [[r["frames_per_s"] - r["min"] for r in mine], [r["max"] - r["frames_per_s"] for r in mine]]
        label = LABELS.get(name, mine[0]["label"])
        left.errorbar(xs, [r["frames_per_s"] for r in mine], yerr=err, capsize=3, label=label, **style)
        right.plot(xs, [100 * r["share"] for r in mine], **style)
        for x, r in zip(xs, mine):
            if r.get("ratio_to_gym") is not None and r["n"] in (ns[-1], 15):
                right.annotate(
                    f"{r['ratio_to_gym']:.2f}x gym",
                    (x, 100 * r["share"]),
                    textcoords="offset points",
                    xytext=(6, 4),
                    fontsize=9,
                    color=f"C{i}",
                )
    for ax in (left, right):
        ax.set_xscale("log", base=2)
        ax.set_xlim(ns[0] / 1.3, ns[-1] * 1.7)
        ax.set_xticks(ns)
        ax.set_xticklabels([str(n) for n in ns])
        ax.set_xlabel("N (sub-envs, one process each)", fontsize=10)
        ax.tick_params(labelsize=9)
        ax.grid(alpha=0.3)
    from matplotlib.ticker import FuncFormatter

    left.set_yscale("log")
    left.yaxis.set_major_formatter(FuncFormatter(lambda y, _: f"{y:,.0f}"))
    left.yaxis.set_minor_formatter(FuncFormatter(lambda y, _: ""))
    left.set_ylabel("frames/s (agent steps per second, log scale)", fontsize=10)
    right.set_ylabel("share of the emulated ideal (%)", fontsize=10)
    right.set_ylim(0, 110)
    fig.suptitle(
        f"Collection on many cores, emulated on 2 cores ({date}): PickCube-v1 replayed,\n"
        "each step sleeping its time on the lent H200 machine, action repeat 2",
        fontsize=12,
    )
    plot_style.legend_below(fig, [left], ncol=2, fontsize=10)
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return png


def draw_all(out_dir: Path) -> list[Path]:
    """Draws every picture into ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pngs = []
    with tempfile.TemporaryDirectory(prefix="maniskill_torchrl_curves_") as tmp:
        for draw in (draw_ppo, draw_ppo_trainer, draw_ppo_rgb, draw_sac, draw_rlpd, draw_bc):
            pngs.append(draw(out_dir, Path(tmp)))
            plt.close("all")
    data = ROOT / "benchmarks" / "collection"
    pngs.append(
        draw_collection(
            data / "sweep_2cores.csv",
            out_dir / "collection_2cores.png",
            "Collection of PickCube-v1 (state, CPU sim) on 2 cores, 2026-11-26:\n"
            "the median of 5 rounds of 10 s, bars from the slowest round to the fastest",
            error_bars=True,
        )
    )
    pngs.append(
        draw_collection(
            data / "sweep_16cores_h200.csv",
            out_dir / "collection_16cores.png",
            "Collection of PickCube-v1 (state, CPU sim) on the 16 cores of a lent H200 machine, 2026-11-27:\n"
            "one round of 2 s per point, a first look rather than a median",
            error_bars=False,
        )
    )
    pngs.append(draw_many_cores(data / "many_cores_emulated.csv", out_dir / "collection_many_cores_emulated.png"))
    return pngs


def _builder_inited(app) -> None:
    draw_all(Path(app.srcdir) / OUT)


def setup(app):
    app.connect("builder-inited", _builder_inited)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
