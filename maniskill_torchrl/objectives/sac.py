"""TorchRL's SAC loss with RLPD's ``backup_entropy`` switch."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.objectives import SACLoss as _TorchRLSACLoss

__all__ = ["SACLoss"]


class SACLoss(_TorchRLSACLoss):
    """:class:`torchrl.objectives.SACLoss` whose critic target may leave out the entropy term.

    TorchRL's SAC (v2) backs up ``Q(s', a') - alpha * log p(a' | s')``. RLPD (Ball et al., 2023), as
    ManiSkill's RLPD baseline runs it (``backup_entropy: False`` in ``base_rlpd_ms3.yml``), backs up
    ``Q(s', a')`` alone: with a sparse 0/1 reward and alpha learnt from 1.0, the entropy term outweighs
    the reward in the target for most of a run. The actor and alpha losses are TorchRL's either way.

    Every argument but ``backup_entropy`` is :class:`torchrl.objectives.SACLoss`'s.

    Args:
        backup_entropy: ``True`` (default): TorchRL's target. ``False``: the target without the entropy term.

    Example:
        >>> from maniskill_torchrl.objectives import SACLoss
        >>> loss = SACLoss(actor, qvalue, backup_entropy=False, target_entropy=-4.0)  # doctest: +SKIP
    """

    def __init__(self, *args: Any, backup_entropy: bool = True, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.backup_entropy = backup_entropy
        self._in_target = False

    @property
    def _alpha(self) -> torch.Tensor:
        # TorchRL's target reads alpha through this property, once; zero there drops the entropy term.
        alpha = super()._alpha
        return torch.zeros_like(alpha) if self._in_target else alpha

    def _compute_target_v2(self, tensordict: TensorDictBase) -> torch.Tensor:
        self._in_target = not self.backup_entropy
        try:
            return super()._compute_target_v2(tensordict)
        finally:
            self._in_target = False
