"""The ``maniskill-torchrl`` command line: dispatch, and the demo.

``maniskill-torchrl demo`` shows the library end to end on the CPU (about a
minute on 2 idle cores): ``ManiSkillEnv(env_id, num_envs=N)`` on the CPU sim under
``ActionRepeat -> EpisodeMetrics`` (:func:`maniskill_torchrl.pipeline.make_env`), fed to a
:class:`torchrl.collectors.Collector`; it prints a summary table and writes a per-episode
return plot, a short rollout video and a JSON summary. ``EpisodeMetrics`` comes after
``ActionRepeat``: it sees one step per agent decision, so ``episode_len`` counts agent steps,
and the repeated rewards arrive already summed.

- :mod:`~maniskill_torchrl.cli.parser`: the flags and their checks;
- :mod:`~maniskill_torchrl.cli.report`: the summary, the plot and the video;
- :mod:`~maniskill_torchrl.cli.scripted_policy`: the demo's policies.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from maniskill_torchrl.cli.parser import UsageError, build_parser, validate_demo_args
from maniskill_torchrl.cli.report import plot_returns, print_summary, record_video
from maniskill_torchrl.cli.scripted_policy import PickCubeScriptedPolicy, env_kwargs_for, make_policy

__all__ = ["main", "build_parser", "make_demo_env", "run_demo", "PickCubeScriptedPolicy"]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``maniskill-torchrl`` (and ``python -m maniskill_torchrl``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    validate, run = _COMMANDS[args.command]
    try:
        validate(args)
    except UsageError as err:
        args.subparser.error(str(err))  # exits with code 2
    os.environ.setdefault("PYTHONWARNINGS", "ignore::DeprecationWarning")  # reaches spawned workers
    return run(args)


def make_demo_env(env_id: str, num_envs: int, repeat: int, env_kwargs: dict[str, Any]):
    """The demo's env: ``ManiSkillEnv(num_envs=N)`` on the CPU sim -> ``ActionRepeat`` -> ``EpisodeMetrics``."""
    from maniskill_torchrl.pipeline import make_env  # TorchRL: not for ``--help``

    return make_env(env_id, num_envs=num_envs, repeat=repeat, sim_backend="physx_cpu", **env_kwargs)


def run_demo(args: argparse.Namespace) -> int:
    """Runs ``maniskill-torchrl demo`` with validated flags; returns the exit code."""
    from maniskill_torchrl._internal.rendering import quiet_maniskill

    quiet_maniskill()
    policy_name = args.policy
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)

    # Two shared cores: the main process only batches and runs a tiny policy.
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    env_kwargs = env_kwargs_for(args.env_id, policy_name)

    t_start = time.perf_counter()
    episodes, closer, stats = _collect(args, policy_name, env_kwargs)
    collect_s = time.perf_counter() - t_start

    files = {"plot": str(out / "returns.png")}
    try:
        plot_returns(
            episodes,
            out / "returns.png",
            title=f"{args.env_id}: {policy_name} policy, {args.workers} workers, ActionRepeat({args.repeat})",
        )
        if not args.no_video:
            video_path = out / "rollout.mp4"
            n = record_video(
                _video_env(args.env_id, args.repeat, env_kwargs, args.video_size),
                lambda env: make_policy(policy_name, env, args.seed),
                video_path,
                steps=args.video_steps,
                seed=args.seed,
                repeat=args.repeat,
            )
            files["video"] = str(video_path)
            stats["video_frames"] = n
    finally:
        if closer is not None:
            closer.join()

    summary = {
        "env_id": args.env_id,
        "policy": policy_name,
        "workers": args.workers,
        "repeat": args.repeat,
        "seed": args.seed,
        **stats,
        "collect_wall_s": round(collect_s, 2),
        "wall_s": round(time.perf_counter() - t_start, 2),
        "files": files,
        "episodes": episodes,
    }
    files["summary"] = str(out / "summary.json")
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print_summary(summary)
    return 0


def _video_env(env_id: str, repeat: int, env_kwargs: dict[str, Any], size: int):
    """A single env rendering ``size`` x ``size`` frames (``human_render_camera_configs``) for the video."""
    from maniskill_torchrl.pipeline import make_env

    return make_env(
        env_id,
        repeat=repeat,
        metrics=False,
        render_mode="rgb_array",
        human_render_camera_configs=dict(width=size, height=size),
        **env_kwargs,
    )


def _collect(args: argparse.Namespace, policy_name: str, env_kwargs: dict[str, Any]):
    """Runs the collector; returns the finished episodes, the (started) shutdown thread and throughput numbers."""
    from torchrl.collectors import Collector
    from tqdm import tqdm

    # Steps per worker per batch: short batches keep the progress bar moving.
    per_worker = max(1, min(50, math.ceil(args.frames / args.workers)))
    frames_per_batch = per_worker * args.workers
    total_frames = math.ceil(args.frames / frames_per_batch) * frames_per_batch

    t0 = time.perf_counter()
    env = make_demo_env(args.env_id, args.workers, args.repeat, env_kwargs)
    env.set_seed(args.seed)
    policy = make_policy(policy_name, env, args.seed)
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        # Endless, stopped by the loop below: with a frame budget the Collector closes the
        # env (seconds of worker teardown) before it hands over the last batch.
        total_frames=-1,
        # Neither policy has parameters, so neither has a device: without one the Collector
        # casts its carrier to the env's device at every step. trust_policy: the Collector
        # takes the policy as running on that device (it has nothing to move there) instead
        # of warning that it found no parameter.
        device=env.device,
        trust_policy=True,
        # Neither policy keeps a recurrent state: no InitTracker needed.
        auto_register_policy_transforms=False,
    )
    episodes: list[dict[str, Any]] = []
    frames = sim_steps = 0
    t_first = None
    bar = tqdm(
        total=total_frames,
        unit="frame",
        desc="collecting",
        disable=args.no_progress,
        dynamic_ncols=True,
        file=sys.stderr,
    )
    try:
        for batch in collector:
            if t_first is None:
                # Start-up (worker spawn, imports, sim build) is reported apart from throughput.
                t_first = time.perf_counter()
                startup_s = t_first - t0
                first_frames = batch.numel()
            frames += batch.numel()
            sim_steps += _sim_steps(batch)
            episodes.extend(_finished_episodes(batch))
            bar.update(batch.numel())
            bar.set_postfix(episodes=len(episodes))
            if frames >= total_frames:
                break
    finally:
        t_end = time.perf_counter()
        bar.close()
        # Worker teardown takes seconds: it runs in the background while the plot and video
        # are made; run_demo joins it before returning.
        closer = threading.Thread(target=_shutdown, args=(collector, env), name="demo-shutdown")
        closer.start()
    steady_s = t_end - t_first
    steady_frames = frames - first_frames
    return (
        episodes,
        closer,
        {
            "frames": frames,
            "sim_steps": sim_steps,
            "startup_s": round(startup_s, 2),
            "frames_per_s": round(steady_frames / steady_s, 1) if steady_frames else None,
            "sim_steps_per_s": round(steady_frames / steady_s * sim_steps / frames, 1) if steady_frames else None,
            "episodes_finished": len(episodes),
        },
    )


def _shutdown(collector, env) -> None:
    collector.shutdown()
    if not env.is_closed:
        env.close()


def _sim_steps(batch) -> int:
    """Simulator steps behind a batch of agent steps (ManiSkill's ``elapsed_steps`` counts them)."""
    if "elapsed_steps" not in batch.keys():
        return batch.numel()
    nxt = batch.get(("next", "elapsed_steps")).long()
    prev = batch.get("elapsed_steps").long()
    return int((nxt - prev).clamp_min(0).sum())


def _finished_episodes(batch) -> list[dict[str, Any]]:
    """One record per episode that ended in ``batch``, from EpisodeMetrics' ``("next", "episode")``."""
    done = batch.get(("next", "done")).reshape(batch.shape)
    if not done.any():
        return []
    ep = batch.get(("next", "episode"))[done]
    cols = {k: ep.get(k).tolist() for k in ep.keys() if ep.get(k).ndim == 1}
    terminated = batch.get(("next", "terminated")).reshape(batch.shape)[done].tolist()
    records = []
    for i in range(int(done.sum())):
        rec = {k: v[i] for k, v in cols.items()}
        rec["terminated"] = terminated[i]
        records.append(rec)
    return records


# subcommand -> (flag checks, runner)
def run_make_demos(args: argparse.Namespace) -> int:
    """Runs ``maniskill-torchrl make-demos``; returns the exit code."""
    from maniskill_torchrl.data.motion_planning import Numpy1Missing, make_demos

    try:
        path = make_demos(args.env_id, args.num_demos, args.control_mode, args.out, processes=args.processes)
    except (Numpy1Missing, RuntimeError) as err:
        print(f"maniskill-torchrl make-demos: {err}", file=sys.stderr)
        return 1
    print(path)
    return 0


_COMMANDS = {"demo": (validate_demo_args, run_demo), "make-demos": (lambda args: None, run_make_demos)}


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
