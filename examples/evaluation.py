"""Evaluation shared by the training examples (``ppo_torchrl.py``, ``sac_torchrl.py``, ``bc_torchrl.py``)
and ``evaluate_gym.py``: the evaluation env, seeded full episodes scored by ``EpisodeMetrics``, and
the episode statistics of a collected batch.

Not TorchRL's ``torchrl.collectors.Evaluator``: it runs a collector-style rollout for a number of
trajectories, but the evaluation here seeds every episode (episode ``k`` gets ``seed + k``, so that
two policies, or the gym and TorchRL paths, meet the same initial states) and runs each batch of
episodes to the time limit with ``IgnoreTerminations``, as ManiSkill's baselines evaluate; that is
one ``env.rollout`` per batch of episodes.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, RandomPolicy, set_exploration_type

from maniskill_torchrl.pipeline import make_env as make_pipeline
from sim_device import resolve


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
    """Means of EpisodeMetrics' ``("next", "episode")`` entries over the episodes that ended in ``batch``."""
    done = batch.get(("next", "done")).squeeze(-1)
    n = int(done.sum())
    out: dict[str, float] = {"episodes": n}
    if n == 0:
        return out
    ep = batch.get(("next", "episode"))[done]
    out["return"] = ep.get("return").float().mean().item()
    out["episode_len"] = ep.get("episode_len").float().mean().item()
    for key in ("success_once", "success_at_end", "fail_once"):
        if key in ep.keys():
            out[key] = ep.get(key).float().mean().item()
    return out


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
