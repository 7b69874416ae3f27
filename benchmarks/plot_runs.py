"""Learning curves of several runs side by side: the evaluations in each run's ``metrics.jsonl``
(``examples/ppo_torchrl.py``, ``sac_torchrl.py``, ``bc_torchrl.py``), success_once and return
against the run's own progress (frames, or iterations for BC) and against wall minutes, with each
run's random-policy evaluation (where it has one) dashed in its colour (``benchmarks/plot_style.py``:
solid for what was measured, dashed for the baseline, dotted for a reference; the legend below the
axes). ``--markers-only`` draws the evaluations as points (runs of a few evaluations); success axes
run from 0 to 1, return axes from 0. A run whose records carry a ``seed`` (several seeds of one
configuration, e.g. from ``scripts/trainer_csv.py``) is drawn as the median over its seeds, the i-th
evaluation of each, with their range (min to max) shaded.

Run::

    python -m benchmarks.plot_runs sac=outputs/sac/metrics.jsonl ppo=benchmarks/ppo/pushcube_cpu_30min_bootstrap.jsonl \
        --title "PushCube-v1, 2 CPU cores" --out benchmarks/sac/pushcube.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks import plot_style


def load(path: Path) -> tuple[list[dict], dict | None]:
    """The policy evaluations in order and the random one. PPO's and SAC's evaluations say
    ``"eval": "policy"`` (PPO's training records have none); BC's records are all evaluations."""
    evals, random = [], None
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if rec.get("eval") == "random":
            random = rec
        elif rec.get("eval") == "policy" or ("eval" not in rec and "frames" not in rec and "success_once" in rec):
            evals.append(rec)
    if not evals:
        raise SystemExit(f"{path}: no evaluation records")
    return evals, random


def seeds_median(evals: list[dict]) -> tuple[list[dict], list[dict], list[dict], int]:
    """Several seeds' evaluations (records with a ``seed``) as one curve: (median, min, max) records of the
    i-th evaluation of every seed, up to the shortest seed's count, and the number of seeds."""
    import statistics

    per_seed: dict = {}
    for e in evals:
        per_seed.setdefault(e["seed"], []).append(e)
    n = min(len(v) for v in per_seed.values())
    keys = [k for k, v in evals[0].items() if isinstance(v, (int, float)) and k != "seed"]
    med, lo, hi = [], [], []
    for i in range(n):
        points = [v[i] for v in per_seed.values()]
        values = {k: [p[k] for p in points if isinstance(p.get(k), (int, float))] for k in keys}
        med.append({k: statistics.median(v) for k, v in values.items() if v})
        lo.append({k: min(v) for k, v in values.items() if v})
        hi.append({k: max(v) for k, v in values.items() if v})
    return med, lo, hi, len(per_seed)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="label=path/to/metrics.jsonl")
    p.add_argument("--out", type=Path, required=True, help="the PNG to write")
    p.add_argument("--title", default="", help="the figure's title")
    p.add_argument("--markers-only", action="store_true", help="points, no lines between the evaluations")
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.4))
    for i, spec in enumerate(args.runs):
        label, _, path = spec.partition("=")
        evals, random = load(Path(path))
        progress = "frames" if "frames" in evals[0] else "iteration"
        style = plot_style.measured(i, marker="osD^"[i % 4])
        if args.markers_only:
            style.update(ls="none", ms=7)
        band = None
        if "seed" in evals[0]:
            evals, lo, hi, n_seeds = seeds_median(evals)
            band = (lo, hi)
            label = f"{label} (median and range of {n_seeds} seeds)"
        for row, key in enumerate(("success_once", "return")):
            if key not in evals[0]:
                continue
            ys = [e[key] for e in evals]
            axes[row, 0].plot([e[progress] for e in evals], ys, **style, label=label)
            axes[row, 1].plot([e["wall_s"] / 60 for e in evals], ys, **style)
            if band is not None:
                lows, highs = [e[key] for e in band[0]], [e[key] for e in band[1]]
                color = axes[row, 0].lines[-1].get_color()
                axes[row, 0].fill_between([e[progress] for e in evals], lows, highs, color=color, alpha=0.18, lw=0)
                axes[row, 1].fill_between([e["wall_s"] / 60 for e in evals], lows, highs, color=color, alpha=0.18, lw=0)
            if random is not None and key in random:
                for ax in axes[row]:
                    ax.axhline(random[key], **plot_style.baseline(i), label=f"{label}: random policy")
    for row, key in enumerate(("success_once", "return")):
        axes[row, 0].set_ylabel(key)
        axes[row, 0].set_xlabel("frames (RL) or iterations (BC)")
        axes[row, 1].set_xlabel("wall minutes (training and evaluation)")
    for ax in axes[0]:
        ax.set_ylim(0, 1.02)
    for ax in axes[1]:
        ax.set_ylim(bottom=0)
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    fig.suptitle(args.title)  # the legend names the random policy's dashed lines
    plot_style.legend_below(fig, list(axes.flat))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
