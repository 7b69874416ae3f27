"""Evaluation shared by the training examples (``ppo_torchrl.py``, ``sac_torchrl.py``, ``bc_torchrl.py``)
and ``evaluate_gym.py``: the evaluation env (``--sim-backend`` / ``--device`` as ``sim_device``
resolves them) and one logged evaluation. Seeded full episodes scored by ``EpisodeMetrics``
(:func:`evaluate_policy`), the episode statistics of a collected batch (:func:`episode_stats`)
and a task's time limit live in the library, :mod:`maniskill_torchrl.evaluation`, which TorchRL's
trainers use too (``maniskill_torchrl.trainer_hooks``).
"""

from __future__ import annotations

from typing import Any

import torch
from torchrl.envs import EnvBase

from maniskill_torchrl.evaluation import episode_stats, evaluate_policy, time_limit
from maniskill_torchrl.pipeline import make_env as make_pipeline
from sim_device import resolve

__all__ = ["episode_stats", "evaluate_and_log", "evaluate_policy", "make_eval_env", "time_limit"]


def make_eval_env(
    env_id: str,
    num_envs: int,
    device: torch.device | str,
    repeat: int = 1,
    sim_backend: str = "auto",
    **env_kwargs: Any,
) -> EnvBase:
    """The evaluation env, as ManiSkill's PPO baseline evaluates: episodes run to the time limit
    (``IgnoreTerminations``), ``EpisodeMetrics`` reports success_once / success_at_end / return.

    ``device`` is the learner's: the env's outputs arrive there. ``sim_backend`` is the examples'
    ``--sim-backend`` (``sim_device.resolve``): ``"auto"``, the GPU sim for a cuda device and the
    CPU sim otherwise; ``"cpu"``, the CPU sim whatever the device; ``"gpu"``, the GPU sim."""
    sim_backend, device = resolve(sim_backend, device)
    return make_pipeline(
        env_id,
        num_envs=num_envs,
        repeat=repeat,
        ignore_terminations=True,
        sim_backend=sim_backend,
        device=device,
        **env_kwargs,
    )


def evaluate_and_log(
    env: EnvBase,
    policy: Any,
    args: Any,
    max_steps: int,
    log_path: Any,
    start: float,
    which: str,
    frames: int,
    **extra: Any,
) -> dict[str, Any]:
    """:func:`evaluate_policy` with ``args.eval_episodes`` / ``args.eval_seed``, one JSON line
    appended to ``log_path`` (``eval``, ``frames``, ``extra``, ``wall_s`` since ``start``, ``eval_s``,
    then the results) and one printed line; returns that record."""
    import json
    import time

    t = time.perf_counter()
    res = evaluate_policy(env, policy, args.eval_episodes, args.eval_seed, max_steps)
    rec = {
        "eval": which,
        "frames": frames,
        **extra,
        "wall_s": round(time.perf_counter() - start, 1),
        "eval_s": round(time.perf_counter() - t, 1),
        **res,
    }
    with open(log_path, "a") as f:
        f.write(json.dumps(rec) + "\n")
    print(
        f"eval ({which}) at {frames} frames, {rec['wall_s']:.0f} s: "
        + ", ".join(f"{k} {v:.3f}" for k, v in res.items() if k != "episodes"),
        flush=True,
    )
    return rec
