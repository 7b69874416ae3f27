"""Learning curves of several runs side by side: the evaluations in each run's ``metrics.jsonl``
(``examples/ppo_torchrl.py``, ``sac_torchrl.py``, ``bc_torchrl.py``), success_once and return
against the run's own progress (frames, or iterations for BC) and against wall minutes, with each
run's random-policy evaluation (where it has one) as a dashed line.

Run::

    python -m benchmarks.plot_runs sac=outputs/sac/metrics.jsonl ppo=benchmarks/ppo/pushcube_cpu_30min_bootstrap.jsonl \
        --title "PushCube-v1, 2 CPU cores" --out benchmarks/sac/pushcube.png
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="label=path/to/metrics.jsonl")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--title", default="")
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7))
    for i, spec in enumerate(args.runs):
        label, _, path = spec.partition("=")
        evals, random = load(Path(path))
        color = f"C{i}"
        progress = "frames" if "frames" in evals[0] else "iteration"
        for row, key in enumerate(("success_once", "return")):
            if key not in evals[0]:
                continue
            ys = [e[key] for e in evals]
            axes[row, 0].plot([e[progress] for e in evals], ys, "o-", color=color, label=f"{label} ({progress})")
            axes[row, 1].plot([e["wall_s"] / 60 for e in evals], ys, "o-", color=color, label=label)
            if random is not None and key in random:
                for ax in axes[row]:
                    ax.axhline(random[key], color=color, ls="--", lw=1)
    for row, key in enumerate(("success_once", "return")):
        axes[row, 0].set_ylabel(key)
        axes[row, 0].set_xlabel("frames (RL) or iterations (BC)")
        axes[row, 1].set_xlabel("wall minutes (training and evaluation)")
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    axes[0, 1].legend(fontsize=8)
    fig.suptitle(f"{args.title} (dashed: random policy)".strip())
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
