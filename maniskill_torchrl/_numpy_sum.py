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

    The caller's state decides, not the history: :meth:`add` is given the return the caller
    holds for the step before (``previous``). An env continues numpy's sum only where that
    return is the one :meth:`add` gave at that position of the history it still holds (the
    last branch written, not overwritten since). Otherwise (a step kept from an earlier
    episode, another env's state, a state made by hand), the history does not hold that
    episode's rewards: the env goes on with a running sum, ``previous + reward``, until its
    next reset. So ``numpy.sum``'s bits hold on linear rollouts and on branches from a root of
    the last episode run (what ``CPUGymWrapper`` sees); elsewhere the return is a float32
    running sum from the caller's state, never another episode's rewards. (A step of another
    episode whose return has the very same bits at the same length is taken for the one held:
    the sum is then over rewards with that same float32 prefix sum, equal up to rounding.)

    One numpy reduction per env per step, on the host: the CPU sim's summation (a handful of
    envs). The GPU sim's anchor, ``ManiSkillVectorEnv(record_metrics=True)``, keeps a running
    float32 sum instead (:class:`~maniskill_torchrl._episode_stats.EpisodeStats`,
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
        >>> total = None
        >>> for n, r in enumerate(rewards):
        ...     total = sums.add(r.reshape(1), torch.tensor([n]), total)
        >>> total.item() == float(np.sum(rewards.numpy()))
        True
    """

    def __init__(self, batch_size: Sequence[int] | torch.Size, *, native: bool = False) -> None:
        self.batch_size = torch.Size(batch_size)
        self.native = native
        n = self.batch_size.numel()
        # Per env and position in the episode: the reward, the return add() gave, and whether
        # that return was numpy's sum of the episode's rewards (False: a running sum).
        self._hist = np.zeros((n, 256), np.float32)
        self._sums = np.zeros((n, 256), np.float32)
        self._exact = np.zeros((n, 256), bool)
        # The last position written per env: the positions after it are an abandoned branch.
        self._top = [-1] * n

    def _fit(self, last: int, dtype: np.dtype) -> None:
        """Room for position ``last`` in rewards of ``dtype``."""
        hist = self._hist
        if last < hist.shape[1] and hist.dtype == dtype:
            return
        width = max(hist.shape[1], 2 * (last + 1))
        # numpy.sum's dtype: float32 for float32 rewards, int64 for bool ones, float64 for float64.
        sum_dtype = np.add.reduce(np.zeros((1, 1), dtype), axis=1).dtype
        for name, kind in (("_hist", dtype), ("_sums", sum_dtype), ("_exact", bool)):
            old = getattr(self, name)
            grown = np.zeros((old.shape[0], width), kind)
            grown[:, : old.shape[1]] = old
            setattr(self, name, grown)

    def add(self, reward: torch.Tensor, position: torch.Tensor, previous: torch.Tensor | None = None) -> torch.Tensor:
        """Each env's return after ``reward`` at ``position`` (0 for an episode's first step).

        ``reward``, ``position`` and ``previous`` are shaped as the batch. ``previous`` is the
        return the caller holds for position - 1 (not read at position 0): where it is not the
        one this history gave there, the env's return is ``previous + reward`` (see the class
        docstring). None: every env continues the history (a caller that keeps no state). The
        result is float32 (or numpy.sum's dtype with ``native``), shaped as the batch, on
        ``reward``'s device.
        """
        on_host = reward.device.type == "cpu"
        rewards = reward.detach().reshape(-1)
        if not self.native and (not on_host or rewards.dtype != torch.float32):
            rewards = rewards.to("cpu", torch.float32)
        rewards = rewards.cpu().numpy()
        positions = position.reshape(-1).tolist()
        held = None if previous is None else previous.detach().reshape(-1).tolist()
        self._fit(max(positions, default=0), rewards.dtype)
        hist, sums, exact, top = self._hist, self._sums, self._exact, self._top
        scalar = sums.dtype.type
        totals = np.empty(len(positions), sums.dtype)
        # One env at a time: each sums its own episode's length.
        for i, k in enumerate(positions):
            hist[i, k] = rewards[i]
            # Continues the history: a first step, or the return given at k - 1 on the branch
            # last written (nothing after top[i] is). Else a running sum from the caller's return.
            follows = k == 0 or held is None or (k <= top[i] + 1 and exact[i, k - 1] and sums[i, k - 1] == held[i])
            total = np.add.reduce(hist[i, : k + 1]) if follows else scalar(held[i]) + rewards[i]
            totals[i] = sums[i, k] = total
            exact[i, k] = follows
            top[i] = k
        out = torch.from_numpy(totals).view(self.batch_size)
        return out if on_host else out.to(reward.device)
