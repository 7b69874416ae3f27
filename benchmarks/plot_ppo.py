"""Learning curve of a PPO run of ``examples/ppo_torchrl.py``: the deterministic evaluations in
its ``metrics.jsonl`` (success_once, success_at_end and return against frames, wall minutes on a
second axis), with the random policy's evaluation dashed and, when given, a target level dotted.

The line styles are the docs' pictures' (``benchmarks/plot_style.py``): solid with markers for what
was measured, dashed for the baseline compared against (here the random policy), dotted for a
reference level (``--target``); the legend sits below the axes, off the data.

Run: ``python -m benchmarks.plot_ppo outputs/ppo/metrics.jsonl --task PullCube-v1 --target 0.8 --out ppo.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks import plot_style


def load(path: Path) -> tuple[list[dict], dict | None]:
    """The policy evaluations, in order, and the random baseline (None if the run has none)."""
    evals, random = [], None
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if rec.get("eval") == "policy":
            evals.append(rec)
        elif rec.get("eval") == "random":
            random = rec
    if not evals:
        raise SystemExit(f"{path}: no evaluation records (was the run made with --eval-every 0?)")
    return evals, random


def title(args: argparse.Namespace, evals: list[dict]) -> str:
    """``--title``, else "PPO on <task>" (``--task``, or the ``env_id`` the log's records name)."""
    if args.title:
        return args.title
    task = args.task or next((r["env_id"] for r in evals if r.get("env_id")), None)
    return f"PPO on {task}" if task else f"PPO ({args.metrics})"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("metrics", type=Path, help="the run's metrics.jsonl")
    p.add_argument("--out", type=Path, required=True, help="the PNG to write")
    p.add_argument("--task", default=None, help="the task, for the title (default: the log's env_id, if any)")
    p.add_argument("--title", default=None, help="the whole title (default: PPO on <task>)")
    p.add_argument("--target", type=float, default=None, help="a success level to draw, dotted (default: none)")
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    evals, random = load(args.metrics)
    frames = [r["frames"] for r in evals]
    fig, (ax_s, ax_r) = plt.subplots(1, 2, figsize=(11, 4.6))
    for i, key in enumerate(("success_once", "success_at_end")):
        ax_s.plot(frames, [r[key] for r in evals], **plot_style.measured(i, marker="os"[i]), label=f"PPO {key}")
    ax_r.plot(frames, [r["return"] for r in evals], **plot_style.measured(0), label="PPO return")
    if random is not None:
        ax_s.axhline(random["success_once"], **plot_style.baseline(0), label="random policy (success_once, return)")
        ax_r.axhline(random["return"], **plot_style.baseline(0))
    if args.target is not None:
        ax_s.axhline(args.target, **plot_style.reference(), label=f"target success {args.target:g}")
    ax_s.set_ylim(0, 1.02)
    ax_s.set_ylabel(f"success over {int(evals[-1]['episodes'])} seeded episodes")
    ax_r.set_ylabel("episode return (deterministic policy)")
    ax_r.set_ylim(bottom=0)
    for ax in (ax_s, ax_r):
        ax.set_xlabel("frames (env steps)")
        ax.grid(alpha=0.3)
        if "wall_s" in evals[-1]:
            top = ax.secondary_xaxis(
                "top",
                functions=(
                    lambda f, e=evals: _interp(f, e, "frames", "wall_s") / 60,
                    lambda m, e=evals: _interp(m * 60, e, "wall_s", "frames"),
                ),
            )
            top.set_xlabel("wall minutes (training + evaluation)")
    fig.suptitle(title(args, evals))
    plot_style.legend_below(fig, [ax_s, ax_r])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


def _interp(x, evals: list[dict], src: str, dst: str):
    import numpy as np

    xs = np.array([0.0] + [r[src] for r in evals])
    ys = np.array([0.0] + [r[dst] for r in evals])
    return np.interp(x, xs, ys)


if __name__ == "__main__":
    sys.exit(main())
