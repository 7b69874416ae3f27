"""The collector's random-action frames into an off-policy trainer's replay buffer."""

from __future__ import annotations

from typing import Any

from tensordict import TensorDictBase
from torchrl.trainers import TrainerHookBase

from maniskill_torchrl._private import trainer_ops

__all__ = ["KeepRandomFrames"]


class KeepRandomFrames(TrainerHookBase):
    """Stores the batches collected during the collector's ``init_random_frames`` in the replay
    buffer, as a hand-written off-policy loop does (``examples/sac_torchrl.py``, ManiSkill's SAC
    and RLPD baselines' seed steps).

    TorchRL 0.14's ``SACTrainer`` (and ``OfflineToOnlineTrainer``, ``TD3Trainer``...) extends its
    replay buffer at ``"pre_epoch"``, inside the optimization loop, which the trainer skips until
    ``collector.init_random_frames`` frames are collected: the random batches are dropped, and the
    first updates sample the one batch that reached the threshold. This hook runs at
    ``"batch_process"`` and hands each batch that will not reach the optimization loop to the
    trainer's own ``extend`` op (the one it registered at ``"pre_epoch"``: a
    ``ReplayBufferTrainer``'s, or an ``OfflineToOnlineReplayBufferHook``'s, which aligns online
    keys to the offline data), so the buffer holds every collected frame, the random ones first.

    Register it after the trainer is built (the trainer configs' ``hooks`` field does).
    """

    def __init__(self) -> None:
        self.trainer: Any = None
        self.kept = 0  # random frames stored by this hook

    def register(self, trainer: Any, name: str = "keep_random_frames") -> None:
        self.trainer = trainer
        self._extend = _buffer_extend(trainer)
        trainer.register_op("batch_process", self)
        trainer.register_module(name, self)

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        trainer = self.trainer
        threshold = getattr(trainer.collector, "init_random_frames", 0) or 0
        mask = batch.get(("collector", "mask"), None)
        frames = batch.numel() if mask is None else int(mask.sum())
        # The trainer counts this batch after the batch_process ops: it reaches the optimization
        # loop (and its pre_epoch extend) once the count, this batch included, reaches the threshold.
        if trainer.collected_frames + frames * trainer.frame_skip < threshold:
            self._extend(batch)
            self.kept += frames
        return batch

    def state_dict(self) -> dict[str, Any]:
        return {"kept": self.kept}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.kept = state_dict["kept"]


def _buffer_extend(trainer: Any) -> Any:
    """The replay buffer's ``extend`` op the trainer registered at ``"pre_epoch"``."""
    for op, kwargs in trainer_ops(trainer, "pre_epoch"):
        fn = getattr(op, "__wrapped__", op)
        owner = getattr(fn, "__self__", None)
        if getattr(fn, "__name__", None) == "extend" and hasattr(owner, "replay_buffer"):
            return lambda batch, fn=fn, kwargs=kwargs: fn(batch, **kwargs)
    raise ValueError(
        "KeepRandomFrames found no replay-buffer extend op at the trainer's 'pre_epoch' (an off-policy "
        "trainer with a local replay buffer and synchronous collection registers one)."
    )
