"""Evaluate a policy as ManiSkill's baselines do: gymnasium's ``AsyncVectorEnv`` of ``CPUGymWrapper`` envs.

Each sub-env is ``CPUGymWrapper(gym.make(env_id, num_envs=1, ...),
ignore_terminations=True, record_metrics=True)``, imported from
``maniskill_torchrl.wrappers`` instead of ``mani_skill.utils.wrappers`` (the
one line that changes): episodes run to the time limit and every step's info
carries ``info["episode"]`` (``success_once``, ``success_at_end``, ``return``,
``episode_len``...). The script prints those for each finished episode and
their averages.

The vector env uses ``context="forkserver"``: gymnasium's default ``fork``
hangs once SAPIEN is loaded in the parent. forkserver (like spawn) re-imports
this file in the workers, hence the ``if __name__ == "__main__"`` guard and
the module-level env factory.

Usage::

    python examples/evaluate_gym.py --env-id PickCube-v1 --num-envs 4 --episodes 8
    python examples/evaluate_gym.py --policy zero --max-episode-steps 20
"""
from __future__ import annotations

import argparse
import functools
import sys
import time
from typing import Any

import gymnasium as gym
import numpy as np


def make_env(env_id: str, max_episode_steps: int | None, obs_mode: str) -> gym.Env:
    """One evaluation env, built inside a vector-env worker (hence module-level and picklable)."""
    import warnings

    import mani_skill.envs  # noqa: F401  (registers the tasks in the worker)

    from maniskill_torchrl.wrappers import CPUGymWrapper  # was: from mani_skill.utils.wrappers import CPUGymWrapper

    warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")
    kwargs: dict[str, Any] = {"num_envs": 1, "obs_mode": obs_mode, "sim_backend": "physx_cpu"}
    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = max_episode_steps
    env = gym.make(env_id, **kwargs)
    return CPUGymWrapper(env, ignore_terminations=True, record_metrics=True)


def evaluate(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Runs ``args.episodes`` episodes over ``args.num_envs`` envs; returns one record per episode."""
    thunk = functools.partial(make_env, args.env_id, args.max_episode_steps, args.obs_mode)
    envs = gym.vector.AsyncVectorEnv([thunk] * args.num_envs, context="forkserver")
    try:
        envs.action_space.seed(args.seed)
        obs, _ = envs.reset(seed=args.seed)  # sub-env i is seeded with seed + i
        zero = np.zeros(envs.action_space.shape, dtype=envs.action_space.dtype)
        episodes: list[dict[str, Any]] = []
        while len(episodes) < args.episodes:
            action = zero if args.policy == "zero" else envs.action_space.sample()
            obs, reward, terminated, truncated, infos = envs.step(action)
            done = np.logical_or(terminated, truncated)
            if not done.any():
                continue
            # gymnasium >= 1.0 (next-step autoreset): the done step's info is the episode's last;
            # the next step() resets those envs and ignores their action.
            ep = infos["episode"]
            for i in np.flatnonzero(done):
                if len(episodes) == args.episodes:
                    break
                rec = {"env": int(i)}
                for key in ("success_once", "success_at_end", "fail_once", "fail_at_end", "return", "episode_len"):
                    if key in ep:
                        rec[key] = ep[key][i].item()
                episodes.append(rec)
                print(_format(len(episodes), rec), flush=True)
    finally:
        envs.close()
    return episodes


def _format(n: int, rec: dict[str, Any]) -> str:
    parts = [f"episode {n:3d} (env {rec['env']})"]
    for key in ("success_once", "success_at_end", "fail_once", "fail_at_end"):
        if key in rec:
            parts.append(f"{key}={rec[key]}")
    parts.append(f"return={rec['return']:.4f}")
    parts.append(f"episode_len={rec['episode_len']}")
    return "  ".join(parts)


def print_averages(episodes: list[dict[str, Any]]) -> None:
    """Averages over all episodes, one ``avg <metric>`` line each."""
    print(f"episodes: {len(episodes)}")
    for key in ("success_once", "success_at_end", "fail_once", "fail_at_end", "return", "episode_len"):
        vals = [float(e[key]) for e in episodes if key in e]
        if vals:
            print(f"avg {key}: {np.mean(vals):.4f}")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--env-id", default="PickCube-v1")
    p.add_argument("--num-envs", type=int, default=2, help="AsyncVectorEnv sub-envs (processes)")
    p.add_argument("--episodes", type=int, default=4, help="episodes to evaluate in all")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--policy", choices=("random", "zero"), default="random")
    p.add_argument("--max-episode-steps", type=int, default=None, help="default: the task's time limit")
    p.add_argument("--obs-mode", default="state")
    args = p.parse_args(argv)
    for name in ("num_envs", "episodes"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.max_episode_steps is not None and args.max_episode_steps < 1:
        p.error(f"--max-episode-steps must be >= 1, got {args.max_episode_steps}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    episodes = evaluate(args)
    print_averages(episodes)
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":  # forkserver workers re-import this file
    sys.exit(main())
