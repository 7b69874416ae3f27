"""Success-rate evaluation inside a TorchRL trainer: seeded episodes every ``interval`` frames."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from tensordict import TensorDictBase
from torchrl._utils import logger as torchrl_logger
from torchrl.envs import Compose, EnvBase
from torchrl.trainers import TrainerHookBase

from maniskill_torchrl.evaluation import evaluate_policy

__all__ = ["SuccessRateEvaluation"]


class SuccessRateEvaluation(TrainerHookBase):
    """Evaluates the trainer's policy as ManiSkill's baselines do, and logs the success rates.

    Every ``interval`` collected frames, and once training reaches its ``total_frames``, it runs
    ``episodes`` full episodes on the evaluation env, episode ``k`` seeded ``seed + k`` (every
    evaluation meets the same initial states), the policy acting deterministically (a
    TanhNormal's ``tanh(loc)``), through :func:`maniskill_torchrl.evaluation.evaluate_policy`.
    It logs the means to the trainer's logger at the trainer's frame count:
    ``<prefix>/success_once``, ``<prefix>/success_at_end``, ``<prefix>/return`` (and
    ``<prefix>/episodes``, ``<prefix>/seconds``, and ``<prefix>/wall_s``: seconds since the hook was registered,
    the trainer built, to this evaluation's end, training and evaluations included; what
    ``scripts/trainer_csv.py`` reads as the committed curves' ``wall_s``).

    Args:
        create_env_fn: the evaluation env, or a callable that builds it (called at the first
            evaluation; what it built is closed when training ends). A Hydra env node with
            ``_partial_: true`` is such a callable (Hydra builds its nested nodes, the base env
            among them, when the config is instantiated). It
            runs each episode to the time limit and scores it: a batched env whose transforms end
            in ``IgnoreTerminations`` then ``EpisodeMetrics``, e.g.
            ``make_env(env_id, num_envs=2, ignore_terminations=True)``. Its batch is the number
            of episodes run at once.

    Keyword Args:
        interval (int): frames between two evaluations (``0``: only the last one).
        episodes (int): seeded episodes per evaluation.
        seed (int): the first episode's seed.
        max_steps (int, optional): agent steps per episode. Default: the base env's time limit
            (``max_episode_steps``) divided by the ``repeat`` of any ``ActionRepeat``.
        policy (module, optional): the policy to evaluate. Default: the trainer's
            ``loss_module.actor_network``, the trained weights themselves.
        at_start (bool): evaluate once before training too (at frame 0; the untrained policy).
        prefix (str): the logged names' prefix.

    Examples:
        >>> from functools import partial
        >>> from maniskill_torchrl.pipeline import make_env
        >>> hook = SuccessRateEvaluation(  # doctest: +SKIP
        ...     partial(make_env, "PushCube-v1", num_envs=2, ignore_terminations=True, obs_mode="state"),
        ...     interval=20_000,
        ...     episodes=50,
        ... )
        >>> hook.register(trainer)  # doctest: +SKIP
    """

    def __init__(
        self,
        create_env_fn: EnvBase | Callable[[], EnvBase],
        *,
        interval: int = 20_000,
        episodes: int = 50,
        seed: int = 10_000,
        max_steps: int | None = None,
        policy: Any = None,
        at_start: bool = False,
        prefix: str = "eval",
    ) -> None:
        if interval < 0:
            raise ValueError(f"interval must be >= 0 frames, got {interval}")
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        self.create_env_fn = create_env_fn
        self.interval = int(interval)
        self.episodes = int(episodes)
        self.seed = int(seed)
        self.max_steps = max_steps
        self.policy = policy
        self.at_start = bool(at_start)
        self.prefix = prefix
        self.trainer: Any = None
        self.env: EnvBase | None = None
        self.next_eval = self.interval
        self.results: list[dict[str, float]] = []  # every evaluation, with its frame count

    # ---------------------------------------------------------------- the hook
    def register(self, trainer: Any, name: str = "success_rate_evaluation") -> None:
        self.trainer = trainer
        self._registered = time.perf_counter()  # wall_s counts from here
        trainer.register_op("post_steps_log", self)
        trainer.register_op("shutdown", self.close)
        if self.at_start:
            trainer.register_op("setup", self.evaluate)
        trainer.register_module(name, self)

    def __call__(self, batch: TensorDictBase | None = None) -> None:
        frames = self.trainer.collected_frames
        last = frames >= self.trainer.total_frames
        if (self.interval and frames >= self.next_eval) or last:
            while self.interval and self.next_eval <= frames:
                self.next_eval += self.interval
            self.evaluate()
        return None  # logged here, at every evaluation: not through the trainer's throttled log

    def evaluate(self) -> dict[str, float]:
        """One evaluation now, logged at the trainer's frame count; returns its record."""
        env = self._env()
        policy = self.policy if self.policy is not None else self.trainer.loss_module.actor_network
        frames = int(self.trainer.collected_frames)
        start = time.perf_counter()
        training = getattr(policy, "training", False)
        if training:
            policy.eval()
        try:
            result = evaluate_policy(env, policy, self.episodes, self.seed, self._max_steps(env))
        finally:
            if training:
                policy.train()
        result["seconds"] = time.perf_counter() - start
        result["wall_s"] = time.perf_counter() - getattr(self, "_registered", start)
        logger = self.trainer.logger
        if logger is not None:
            for key, value in result.items():
                logger.log_scalar(f"{self.prefix}/{key}", value, step=frames)
        torchrl_logger.info(
            f"{self.prefix} at {frames} frames: "
            + ", ".join(f"{k} {v:.3f}" for k, v in result.items() if k not in ("episodes", "seconds", "wall_s"))
        )
        self.results.append({"frames": frames, **result})
        return result

    def close(self) -> None:
        """Closes the evaluation env if this hook built it (at the trainer's shutdown)."""
        if self.env is not None and self.env is not self.create_env_fn and not self.env.is_closed:
            self.env.close()
        self.env = None

    # ---------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        return {"next_eval": self.next_eval, "results": list(self.results)}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.next_eval = state_dict["next_eval"]
        self.results = list(state_dict["results"])

    # ---------------------------------------------------------------- helpers
    def _env(self) -> EnvBase:
        if self.env is None:
            env = self.create_env_fn if isinstance(self.create_env_fn, EnvBase) else self.create_env_fn()
            if ("episode", "return") not in env.observation_spec.keys(True):
                raise ValueError(
                    "SuccessRateEvaluation's env must score its episodes: end its transforms in "
                    "IgnoreTerminations, then EpisodeMetrics (maniskill_torchrl.pipeline.make_env(..., "
                    "ignore_terminations=True))."
                )
            self.env = env
        return self.env

    def _max_steps(self, env: EnvBase) -> int:
        if self.max_steps is not None:
            return int(self.max_steps)
        limit = getattr(getattr(env, "base_env", env), "max_episode_steps", None)
        if limit is None:
            raise ValueError("The evaluation env has no time limit: pass max_steps (agent steps per episode).")
        transform = getattr(env, "transform", None)
        repeat = 1
        for t in transform if isinstance(transform, Compose) else [transform]:
            repeat *= int(getattr(t, "repeat", 1))
        return math.ceil(limit / repeat)
