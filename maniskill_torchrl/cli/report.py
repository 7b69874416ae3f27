"""What the demo leaves behind: the summary table, the returns plot and the rollout video."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

__all__ = ["plot_returns", "print_summary", "record_video", "summarize"]


def summarize(episodes: Sequence[dict[str, Any]]) -> dict[str, float | None]:
    """Means over finished episodes (``None`` where no episode finished or the task has no such metric)."""

    def mean(key: str) -> float | None:
        vals = [float(e[key]) for e in episodes if key in e]
        return sum(vals) / len(vals) if vals else None

    return {
        "mean_return": mean("return"),
        "mean_episode_len": mean("episode_len"),
        "success_rate": mean("success_once"),
        "fail_rate": mean("fail_once"),
    }


def print_summary(summary: dict[str, Any]) -> None:
    """The table printed at the end of the demo."""
    means = summarize(summary["episodes"])

    def fmt(value, spec: str, suffix: str = "") -> str:
        return "n/a" if value is None else f"{value:{spec}}{suffix}"

    rows = [
        ("env", f"{summary['env_id']} (CPU sim), {summary['policy']} policy"),
        (
            "pipeline",
            f"ManiSkillEnv(num_envs={summary['workers']}) -> ActionRepeat({summary['repeat']}) -> EpisodeMetrics",
        ),
        ("frames (agent steps)", f"{summary['frames']}"),
        ("sim steps", f"{summary['sim_steps']}"),
        ("start-up + 1st batch", fmt(summary["startup_s"], ".1f", " s")),
        ("frames/s (steady)", fmt(summary["frames_per_s"], ".1f")),
        ("sim steps/s (steady)", fmt(summary["sim_steps_per_s"], ".1f")),
        ("run time", f"{summary['wall_s']:.1f} s (collection {summary['collect_wall_s']:.1f} s)"),
        ("episodes finished", f"{summary['episodes_finished']}"),
        ("mean episode length", fmt(means["mean_episode_len"], ".1f", " agent steps")),
        ("mean return", fmt(means["mean_return"], ".3f")),
        ("success rate", fmt(None if means["success_rate"] is None else 100 * means["success_rate"], ".1f", " %")),
    ]
    if means["fail_rate"] is not None:
        rows.append(("fail rate", fmt(100 * means["fail_rate"], ".1f", " %")))
    for name, path in summary["files"].items():
        rows.append((name, path))
    width = max(len(r[0]) for r in rows)
    line = "-" * (width + 2 + max(len(r[1]) for r in rows))
    print(line)
    print("maniskill-torchrl demo summary")
    print(line)
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
    print(line)
    sys.stdout.flush()


def plot_returns(episodes: Sequence[dict[str, Any]], path: Path, title: str) -> None:
    """Per-episode returns in finishing order (successes in green), with a running mean."""
    from maniskill_torchrl._internal.extras import require

    matplotlib = require("matplotlib", "the demo's plot")
    matplotlib.use("Agg")  # no display needed
    import matplotlib.pyplot as plt

    returns = [e["return"] for e in episodes]
    success = [bool(e.get("success_once", False)) for e in episodes]
    fig, ax = plt.subplots(figsize=(7, 3.5), dpi=100)
    if returns:
        xs = range(1, len(returns) + 1)
        ax.scatter(
            xs, returns, s=12, c=["tab:green" if s else "tab:gray" for s in success], label="episode (green: success)"
        )
        k = max(1, len(returns) // 10)
        running = [
            sum(returns[max(0, i - k + 1) : i + 1]) / len(returns[max(0, i - k + 1) : i + 1])
            for i in range(len(returns))
        ]
        ax.plot(xs, running, color="tab:blue", label=f"running mean ({k})")
        ax.legend(loc="best", fontsize=8)
    else:
        ax.text(
            0.5, 0.5, "no episode finished: collect more --frames", ha="center", va="center", transform=ax.transAxes
        )
    ax.set_xlabel("finished episode")
    ax.set_ylabel("return")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def record_video(env: Any, make_policy: Any, path: Path, *, steps: int, seed: int, repeat: int) -> int:
    """Writes an mp4 of ``env`` (a single env made with ``render_mode="rgb_array"``) run by
    ``make_policy(env)``; closes ``env`` and returns the number of frames.

    CPU rendering is the slow part, so one frame per agent step, not per sim step.
    """
    from torchrl.envs.utils import step_mdp

    from maniskill_torchrl._internal.extras import require

    imageio = require("imageio.v2", "the demo's video")

    base = env.base_env
    env.set_seed(seed + 10_000)  # episodes unlike the collected ones
    policy = make_policy(env)
    frames = []
    td = env.reset()
    frames.append(base.render()[0].cpu().numpy())
    with torch.no_grad():
        for _ in range(steps):
            td = env.step(policy(td))
            # Render before any reset so that an episode's last frame (a success) is kept.
            frames.append(base.render()[0].cpu().numpy())
            done = bool(td.get(("next", "done")).any())
            td = step_mdp(td)
            if done:
                td = env.reset()
    control_freq = getattr(base.unwrapped, "control_freq", 20) or 20  # before close(), which drops it
    env.close()
    fps = max(1, round(control_freq / repeat))
    imageio.mimsave(path, frames, fps=fps, macro_block_size=16)
    return len(frames)
