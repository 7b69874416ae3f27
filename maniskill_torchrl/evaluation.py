"""Evaluation as ManiSkill's baselines evaluate: seeded full episodes scored by ``EpisodeMetrics``.

What the examples (``examples/evaluation.py``), the TorchRL trainer hooks
(:mod:`maniskill_torchrl.trainer_hooks`) and the CLI share:

- :func:`evaluate_policy`: ``episodes`` full episodes on an env that ends each one at the time
  limit (``IgnoreTerminations``) and scores it (``EpisodeMetrics``), episode ``k`` seeded
  ``seed + k``, the policy acting deterministically; the means of ``success_once``,
  ``success_at_end`` and ``return``.
- :func:`episode_stats`: the same means over the episodes that ended in a collected batch.
- :func:`time_limit`: a task's registered episode length.

Not TorchRL's ``torchrl.collectors.Evaluator``: it runs a collector-style rollout for a number of
trajectories, but here every episode is seeded (two policies, or the gym and TorchRL paths, meet
the same initial states) and each batch of episodes is one ``env.rollout`` to the time limit.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, RandomPolicy, set_exploration_type

__all__ = ["episode_stats", "evaluate_policy", "time_limit"]

#: The ``("episode", ...)`` entries of ``EpisodeMetrics`` averaged over finished episodes.
EPISODE_KEYS = ("return", "episode_len", "success_once", "success_at_end", "fail_once")


def time_limit(env_id: str, max_episode_steps: int | None = None) -> int:
    """The task's episode length: ``max_episode_steps`` if given, else the registered time limit."""
    if max_episode_steps is not None:
        return max_episode_steps
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the tasks)

    limit = gym.spec(env_id).max_episode_steps
    if limit is None:
        raise SystemExit(f"{env_id} has no registered time limit: pass --max-episode-steps to evaluate it")
    return limit


@torch.no_grad()
def evaluate_policy(
    env: EnvBase,
    policy: Any,
    episodes: int,
    seed: int,
    max_steps: int,
    exploration: ExplorationType = ExplorationType.DETERMINISTIC,
) -> dict[str, float]:
    """Runs ``episodes`` full episodes, seeded ``seed``, ``seed + 1``, ...; the policy acts
    deterministically (the TanhNormal's ``tanh(loc)``), or samples with
    ``exploration=ExplorationType.RANDOM``. ``policy=None``: uniform random actions.

    ``env`` runs each episode to its time limit and scores it: a batched env ending in
    ``IgnoreTerminations`` then ``EpisodeMetrics`` (``examples/evaluation.py``'s ``make_eval_env``).
    Returns the means of ``success_once``, ``success_at_end`` and ``return`` (and ``episodes``).
    ``max_steps``: agent steps per episode (the time limit divided by any ActionRepeat)."""
    n = env.batch_size.numel()
    acting = RandomPolicy(env.full_action_spec) if policy is None else policy
    finished = []
    for first in range(0, episodes, n):
        env.set_seed(seed + first)  # sub-env i starts with seed + first + i
        with set_exploration_type(exploration):
            rollout = env.rollout(max_steps, acting, break_when_any_done=False)
        done = rollout.get(("next", "done")).squeeze(-1)
        if not bool(done[..., -1].all()):
            raise RuntimeError(
                f"evaluation episodes did not end after {max_steps} steps: pass the task's time limit "
                "(--max-episode-steps) divided by the ActionRepeat"
            )
        finished.append(rollout.get(("next", "episode"))[..., -1])
    ep = torch.cat(finished)[:episodes]
    out = {"episodes": float(ep.batch_size[0])}
    for key in ("success_once", "success_at_end", "return"):
        if key in ep.keys():
            out[key] = ep.get(key).float().mean().item()
    return out


def episode_stats(batch: TensorDictBase) -> dict[str, float]:
    """Means of EpisodeMetrics' ``("next", "episode")`` entries over the episodes that ended in
    ``batch`` (``return``, ``episode_len``, and ``success_once`` / ``success_at_end`` /
    ``fail_once`` where the task reports them), and their number, ``episodes``."""
    done = batch.get(("next", "done")).squeeze(-1)
    mask = batch.get(("collector", "mask"), None)
    if mask is not None:  # padded steps of a split batch are not steps
        done = done & mask
    n = int(done.sum())
    out: dict[str, float] = {"episodes": n}
    if n == 0:
        return out
    ep = batch.get(("next", "episode"))[done]
    for key in EPISODE_KEYS:
        if key in ep.keys():
            out[key] = ep.get(key).float().mean().item()
    return out
