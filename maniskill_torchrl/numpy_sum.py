"""Episode returns summed bit for bit as ``numpy.sum`` gives them.

``numpy.sum`` of a float32 array adds pairwise: blocks of 8 running partial sums folded as a
tree, recursion above 128 elements (numpy's ``pairwise_sum``), so the split points move as an
episode grows and no running total reproduces it past 8 steps. ManiSkill's ``CPUGymWrapper``
reports ``np.sum(self.returns)``; :class:`NumpyOrderSums` keeps each env's rewards at their
positions in the episode and lets numpy itself sum them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

__all__ = ["NumpyOrderSums"]


class NumpyOrderSums:
    """Per-env episode returns equal to ``numpy.sum`` of the episode's float32 rewards.

    :meth:`add` writes each env's reward at its position in its episode (its length so far,
    which the caller keeps) and returns numpy's sum of the rewards up to there. The history is
    indexed by position, not appended to, so a rollout that branches again from an earlier step
    of the same episode (``env.rollout(tensordict=root)`` twice) overwrites the abandoned branch.

    One numpy reduction per env per step, on the host: the CPU sim's summation (a handful of
    envs). The GPU sim's anchor, ``ManiSkillVectorEnv(record_metrics=True)``, keeps a running
    float32 sum instead (:class:`~maniskill_torchrl.episode_stats.EpisodeStats`,
    ``summation="running"``).

    Args:
        batch_size: the env batch.
        native (bool): keep the rewards' own dtype, as ``numpy.sum`` of ManiSkill's numpy rewards
            does (bool rewards sum to int64, float64 ones to float64: what ``CPUGymWrapper``
            reports); False (default): rewards and sums in float32.

    Examples:
        >>> import numpy as np, torch
        >>> sums = NumpyOrderSums([1])
        >>> rewards = torch.rand(300).float()
        >>> for n, r in enumerate(rewards):
        ...     total = sums.add(r.reshape(1), torch.tensor([n]))
        >>> total.item() == float(np.sum(rewards.numpy()))
        True
    """

    def __init__(self, batch_size: Sequence[int] | torch.Size, *, native: bool = False) -> None:
        self.batch_size = torch.Size(batch_size)
        self.native = native
        self._hist = np.zeros((self.batch_size.numel(), 256), np.float32)

    def add(self, reward: torch.Tensor, position: torch.Tensor) -> torch.Tensor:
        """Each env's return after ``reward`` at ``position`` (0 for an episode's first step).

        ``reward`` and ``position`` are shaped as the batch; the result is float32, shaped as the
        batch, on ``reward``'s device.
        """
        on_host = reward.device.type == "cpu"
        rewards = reward.detach().reshape(-1)
        if not self.native and (not on_host or rewards.dtype != torch.float32):
            rewards = rewards.to("cpu", torch.float32)
        rewards = rewards.cpu().numpy()
        positions = position.reshape(-1).tolist()
        hist = self._hist
        last = max(positions, default=0)
        if last >= hist.shape[1] or hist.dtype != rewards.dtype:
            grown = np.zeros((hist.shape[0], max(hist.shape[1], 2 * (last + 1))), rewards.dtype)
            grown[:, : hist.shape[1]] = hist
            hist = self._hist = grown
        # numpy.sum's dtype: float32 for float32 rewards, int64 for bool ones, float64 for float64.
        totals = np.empty(len(positions), np.add.reduce(hist[:1, :1], axis=1).dtype)
        for i, k in enumerate(positions):
            hist[i, k] = rewards[i]
            totals[i] = np.add.reduce(hist[i, : k + 1])
        out = torch.from_numpy(totals).view(self.batch_size)
        return out if on_host else out.to(reward.device)
