"""Learning curve of a PPO run of ``examples/ppo_torchrl.py``: the deterministic evaluations in
its ``metrics.jsonl`` (success_once, success_at_end and return against frames, wall minutes on a
second axis) with the random-policy baseline as a dashed line.

Run: ``python -m benchmarks.plot_ppo outputs/ppo/metrics.jsonl --out benchmarks/ppo_pushcube_cpu.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("metrics", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--title", default=None)
    args = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    evals, random = load(args.metrics)
    frames = [r["frames"] for r in evals]
    fig, (ax_s, ax_r) = plt.subplots(1, 2, figsize=(11, 4))
    for key, style in (("success_once", "o-"), ("success_at_end", "s--")):
        ax_s.plot(frames, [r[key] for r in evals], style, label=f"PPO {key}", ms=4)
    ax_r.plot(frames, [r["return"] for r in evals], "o-", label="PPO return", ms=4)
    if random is not None:
        ax_s.axhline(random["success_once"], color="gray", ls=":", label="random policy success_once")
        ax_r.axhline(random["return"], color="gray", ls=":", label="random policy return")
    ax_s.axhline(0.8, color="red", lw=0.8, alpha=0.5, label="target 0.8")
    ax_s.set_ylim(-0.02, 1.02)
    ax_s.set_ylabel(f"success over {int(evals[-1]['episodes'])} seeded episodes")
    ax_r.set_ylabel("episode return (deterministic policy)")
    for ax in (ax_s, ax_r):
        ax.set_xlabel("frames (env steps)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
        if "wall_s" in evals[-1]:
            top = ax.secondary_xaxis(
                "top",
                functions=(
                    lambda f, e=evals: _interp(f, e, "frames", "wall_s") / 60,
                    lambda m, e=evals: _interp(m * 60, e, "wall_s", "frames"),
                ),
            )
            top.set_xlabel("wall minutes (training + evaluation)")
    fig.suptitle(args.title or str(args.metrics.parent.name))
    fig.tight_layout()
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
