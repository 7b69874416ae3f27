"""Losses TorchRL 0.14's objectives lack for ManiSkill's baselines.

- :class:`SACLoss`: TorchRL's :class:`~torchrl.objectives.SACLoss` with ``backup_entropy``, the
  switch of ManiSkill's RLPD baseline (and of the RLPD and JaxRL code it comes from): ``False``
  leaves the entropy term out of the critic's target. Its config is the ``loss`` node
  ``sac_backup_entropy`` (``import maniskill_torchrl.configs``).
"""

from maniskill_torchrl.objectives.sac import SACLoss

__all__ = ["SACLoss"]
