"""The training episodes' metrics in a TorchRL trainer's logs, as episodes end."""

from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase
from torchrl.trainers import TrainerHookBase

from maniskill_torchrl.evaluation import episode_stats

__all__ = ["LogEpisodeMetrics"]


class LogEpisodeMetrics(TrainerHookBase):
    """Logs ``EpisodeMetrics``' ``("next", "episode", ...)`` entries of the episodes that end in the
    collected batches: ``<prefix>/success_once``, ``<prefix>/success_at_end``, ``<prefix>/return``,
    ``<prefix>/episode_len`` (``<prefix>/fail_once`` where the task reports failures), each the mean
    over the episodes that ended since the last log, and ``<prefix>/episodes``, their number.

    TorchRL's ``LogScalar`` reduces an entry over every step of a batch; these entries mean
    something only at the step an episode ends (``("next", "done")``), and an episode ends in few
    batches. So this hook keeps the finished episodes' sums and logs their means once at least
    ``interval`` frames have passed since its last log (``0``: at every batch in which an episode
    ended), to the trainer's logger at the trainer's frame count (not through the trainer's
    throttled log, which would drop the episodes of the batches between two logs).

    The training env needs ``EpisodeMetrics`` (the last of its transforms). Synchronous collection
    only: with ``async_collection`` the trainer hands no batch to its logging hooks.

    Keyword Args:
        interval (int): frames between two logs (default 0).
        prefix (str): the logged names' prefix (default ``"train"``).
    """

    def __init__(self, *, interval: int = 0, prefix: str = "train") -> None:
        if interval < 0:
            raise ValueError(f"interval must be >= 0 frames, got {interval}")
        self.interval = int(interval)
        self.prefix = prefix
        self.trainer: Any = None
        self._sums: dict[str, float] = {}
        self._episodes = 0
        self._last_log: int | None = None

    def register(self, trainer: Any, name: str = "log_episode_metrics") -> None:
        self.trainer = trainer
        trainer.register_op("pre_steps_log", self)
        trainer.register_module(name, self)

    def __call__(self, batch: TensorDictBase | None) -> None:
        if batch is None:
            return None
        if ("next", "episode", "return") not in batch.keys(True):
            raise KeyError(
                "LogEpisodeMetrics reads ('next', 'episode', ...): end the training env's transforms in "
                "EpisodeMetrics (transform: episode_metrics)."
            )
        stats = episode_stats(batch)
        n = int(stats.pop("episodes"))
        if n:
            for key, value in stats.items():
                self._sums[key] = self._sums.get(key, 0.0) + value * n
            self._episodes += n
        frames = int(self.trainer.collected_frames)
        due = self._last_log is None or frames - self._last_log >= self.interval
        if self._episodes and due:
            self._log(frames)
        return None

    def _log(self, frames: int) -> None:
        logger = self.trainer.logger
        if logger is not None:
            for key, total in self._sums.items():
                logger.log_scalar(f"{self.prefix}/{key}", total / self._episodes, step=frames)
            logger.log_scalar(f"{self.prefix}/episodes", self._episodes, step=frames)
        self._sums, self._episodes, self._last_log = {}, 0, frames

    def state_dict(self) -> dict[str, Any]:
        return {"sums": dict(self._sums), "episodes": self._episodes, "last_log": self._last_log}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._sums = dict(state_dict["sums"])
        self._episodes = state_dict["episodes"]
        self._last_log = state_dict["last_log"]
