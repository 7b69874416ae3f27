"""Sums of float32 rewards bit for bit as ``numpy.sum`` gives them.

``numpy.sum`` of a float32 array adds pairwise: blocks of 8 running partial sums
folded as a tree, recursion above 128 elements (numpy's ``pairwise_sum``). A
running ``+=`` differs from it in the last bits after 8 steps, so an episode
return that must equal ManiSkill's ``CPUGymWrapper`` (``np.sum(self.returns)``)
follows numpy's order exactly.

- :func:`pairwise_sum`: the sum over the last dim, on any device.
- :class:`RunningNumpySum`: per-env running sums, one reward per env per step.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

__all__ = ["PW_BLOCK", "RunningNumpySum", "pairwise_sum"]

PW_BLOCK = 128  # numpy's PW_BLOCKSIZE
# Up to this many envs on the CPU (a single CPU env, the gym shim), numpy sums each episode
# itself: fewer ops per step than the incremental torch tree.
_NUMPY_MAX_ENVS = 8


def _expand(mask: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return mask.reshape(mask.shape + (1,) * (like.ndim - mask.ndim))


def _tree8(r: torch.Tensor) -> torch.Tensor:
    # numpy: ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    return ((r[..., 0] + r[..., 1]) + (r[..., 2] + r[..., 3])) + ((r[..., 4] + r[..., 5]) + (r[..., 6] + r[..., 7]))


def _pairwise(x: torch.Tensor) -> torch.Tensor:
    """numpy's ``pairwise_sum`` on the last dim of ``x`` (same order of float ops)."""
    n = x.shape[-1]
    if n < 8:
        res = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
        for i in range(n):
            res = res + x[..., i]
        return res
    if n <= PW_BLOCK:
        full = n - n % 8
        blocks = x[..., :full].unflatten(-1, (full // 8, 8))
        r = blocks[..., 0, :]
        for i in range(1, full // 8):
            r = r + blocks[..., i, :]
        res = _tree8(r)
        for i in range(full, n):
            res = res + x[..., i]
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(x[..., :n2]) + _pairwise(x[..., n2:])


def pairwise_sum(x: torch.Tensor) -> torch.Tensor:
    """Sum over the last dim, bit for bit as ``numpy.sum`` does it for float arrays.

    Examples:
        >>> import numpy as np, torch
        >>> from maniskill_torchrl.numpy_sum import pairwise_sum
        >>> x = torch.rand(300)
        >>> pairwise_sum(x).item() == float(np.sum(x.numpy()))
        True
    """
    # numpy adds the pairwise sum to an initial +0.0
    return _pairwise(x) + 0.0


class RunningNumpySum:
    """Per-env sums of reward sequences that grow by one reward per env per step.

    :meth:`add` takes each env's running total, its new reward and its length so
    far, and returns the new totals, each equal to ``numpy.sum`` of that env's
    rewards since its length was 0. One of three strategies does the work:

    - a few envs on the CPU: numpy sums each episode's history itself;
    - otherwise, up to 128 rewards: numpy's 8-wide blocks kept incrementally in torch
      (no history read, no host sync on an accelerator);
    - beyond 128 rewards: the history summed again (numpy on the CPU, :func:`pairwise_sum`
      elsewhere).

    Args:
        batch_size: the env batch.
        device: where the sums live.
    """

    def __init__(self, batch_size: Sequence[int] | torch.Size, device: torch.device) -> None:
        b = self.batch_size = torch.Size(batch_size)
        self._blocks = torch.zeros(b + (8,), dtype=torch.float32, device=device)
        self._part = torch.zeros(b + (8,), dtype=torch.float32, device=device)
        self._hist = torch.zeros(b + (PW_BLOCK * 2,), dtype=torch.float32, device=device)
        # Host-side bound on every env's length (no device sync to read it).
        self._max_len = 0
        #: whether numpy sums each episode itself (the first strategy above)
        self.uses_numpy = device.type == "cpu" and b.numel() <= _NUMPY_MAX_ENVS

    def reset(self) -> None:
        """Every env starts again (masked restarts need no call: lengths say where each env is)."""
        self._max_len = 0

    def add(self, total: torch.Tensor, reward: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """The new totals: ``total`` (sums of ``n`` rewards per env) with ``reward`` added."""
        self._record(reward, n)
        if self.uses_numpy:
            return self._numpy_totals(reward, n)
        total = self._block_totals(total, reward, n)
        if self._max_len > PW_BLOCK:
            total = self._long_totals(total, n + 1)
        return total

    def _record(self, reward: torch.Tensor, n: torch.Tensor) -> None:
        """Writes ``reward`` at position ``n`` of each env's history, growing it when needed."""
        self._max_len += 1
        if self._max_len == PW_BLOCK + 1 or self._max_len > self._hist.shape[-1]:
            # Masked restarts leave this bound stale (it only grows): re-read the true longest
            # episode (one sync) before taking the long path or growing the history.
            self._max_len = int(n.max()) + 1
        if self._max_len > self._hist.shape[-1]:
            self._hist = torch.cat([self._hist, torch.zeros_like(self._hist)], -1)
        if not self.uses_numpy:
            self._hist.view(-1, self._hist.shape[-1]).scatter_(1, n.reshape(-1, 1), reward.reshape(-1, 1))

    def _numpy_totals(self, reward: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        hist_np = self._hist.view(-1, self._hist.shape[-1]).numpy()
        rew_np = reward.reshape(-1).numpy()
        total_np = np.empty(rew_np.shape, np.float32)
        for i, k in enumerate(n.reshape(-1).tolist()):
            hist_np[i, k] = rew_np[i]
            total_np[i] = np.add.reduce(hist_np[i, : k + 1])
        return torch.from_numpy(total_np).view(self.batch_size)

    def _block_totals(self, total: torch.Tensor, reward: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """numpy's order up to 128 rewards: tail elements added one by one to the tree of full blocks."""
        self._part.view(-1, 8).scatter_(1, n.reshape(-1, 1) % 8, reward.reshape(-1, 1))
        total = total + reward
        n1 = n + 1
        block_end = n1 % 8 == 0
        # On an accelerator .any() would be a host sync per step: always take the (masked) update.
        if n1.device.type != "cpu" or block_end.any():
            blocks = torch.where(_expand(n1 == 8, self._part), self._part, self._blocks + self._part)
            self._blocks = torch.where(_expand(block_end, blocks), blocks, self._blocks)
            total = torch.where(block_end, _tree8(self._blocks) + 0.0, total)
        return total

    def _long_totals(self, total: torch.Tensor, n1: torch.Tensor) -> torch.Tensor:
        """Totals of the envs past 128 rewards, summed again from their histories."""
        long = n1 > PW_BLOCK
        if not long.any():
            return total
        total = total.clone()
        # Flat views: the batch may have any number of dims, none included.
        flat_total = total.view(-1)
        (idx,) = long.reshape(-1).nonzero(as_tuple=True)
        lens = n1.reshape(-1)[idx]
        hist = self._hist.view(-1, self._hist.shape[-1])
        if hist.device.type == "cpu":
            # numpy itself is the reference: its sum over a zero-copy view is exact and
            # O(1) python calls, where the torch replica costs ~30 ops per 128 rewards.
            hist_np = hist.numpy()
            for i, length in zip(idx.tolist(), lens.tolist()):
                flat_total[i] = float(np.add.reduce(hist_np[i, :length]))
        else:
            rows = hist[idx]
            for length in lens.unique().tolist():
                sel = lens == length
                flat_total[idx[sel]] = pairwise_sum(rows[sel, :length])
        return total
