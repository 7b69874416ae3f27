"""TorchRL trainer hooks for ManiSkill: what TorchRL 0.14's trainers lack for its tasks.

TorchRL's config-driven trainers (``torchrl.trainers.algorithms``: ``SACTrainer``,
``PPOTrainer``, ``OfflineToOnlineTrainer``...) run on a ManiSkill env as on any TorchRL env
(``examples/trainers``, the guide "Train with TorchRL's trainers"). Three things ManiSkill users
expect are missing there; each is a :class:`~torchrl.trainers.TrainerHookBase` here, with a
config in TorchRL's ``hook`` group (``import maniskill_torchrl.configs``, the name in brackets)
for the trainer configs' ``hooks`` field:

- :class:`SuccessRateEvaluation` (``success_rate_evaluation``): ``LogValidationReward`` rolls the
  policy out unseeded for a number of frames, every so many *calls*, logs rewards only, and closes
  its env after each use. No hook runs seeded full episodes and logs success rates, ManiSkill's
  measure.
- :class:`LogEpisodeMetrics` (``log_episode_metrics``): ``LogScalar`` reduces an entry over every
  step of a batch, and the trainer's log drops values between two logs; episode metrics mean
  something only where an episode ends (``("next", "done")``).
- :class:`KeepRandomFrames` (``keep_random_frames``): ``SACTrainer`` and
  ``OfflineToOnlineTrainer`` extend their buffer inside the optimization loop, which the trainer
  skips until ``init_random_frames``: the random frames never reach the buffer.

Other gaps, met in the configs (noted for upstream; the guide lists them too):

- The trainers' reward logs read ``"reward_sum"`` (TorchRL's ``RewardSum``): with
  ``EpisodeMetrics``, ``episode_reward_key: [episode, return]``.
- ``OfflineToOnlineTrainer`` with ``enable_logging`` fails on its first batch: its UTD hook reads
  ``write_count``, which ``OfflineToOnlineReplayBuffer`` has not (the RLPD config turns it off).
- ``OfflineToOnlineReplayBuffer`` concatenates offline samples, which carry ``"index"``, with
  online ones, which have none (the library's ``offline_to_online`` node leaves it out); and it
  takes demonstrations' rewards as stored (the RLPD config adds ManiSkill's sparse reward,
  :class:`~maniskill_torchrl.transforms.SparseReward`).
- TorchRL's ``exclude`` node cannot build ``ExcludeTransform`` (``exclude_keys=`` where it takes
  positional keys) nor spell a nested key (the library's ``exclude_keys`` node).
- ``AdamConfig``'s ``eps`` defaults to 1e-4 (PyTorch's: 1e-8); ``MLPConfig``'s ``norm_kwargs``
  reaches ``MLP`` as a ``DictConfig``, which it reads as a list; ``TanhNormalModelConfig``'s key
  defaults do not apply to a node from the ``ConfigStore``.
- The ``tanh_normal`` model has a state-dependent scale only (ManiSkill's PPO learns a
  state-independent log std: the library's ``network/ppo_mlp`` node); ``SACLoss`` always backs
  up the entropy (ManiSkill's RLPD: ``backup_entropy: False``).
- With ``optim_steps_per_batch: null``, ``optim_steps`` counts the sampler's end as a step.
- The on-policy trainers' GAE stops bootstrapping at every termination; ManiSkill's PPO ends
  episodes at success and bootstraps there (``bootstrap_at_done="always"``): the library's
  ``IgnoreTerminations(as_truncations=True)`` turns terminations into truncations.
- The CPU engine's ``num_envs`` needs nothing: ``env: maniskill`` with ``num_envs: N`` is one
  batched env (one process per sub-env on the CPU sim) that TorchRL's ``sync`` collector drives.
"""

from __future__ import annotations

from maniskill_torchrl.trainer_hooks.episode_log import LogEpisodeMetrics
from maniskill_torchrl.trainer_hooks.evaluation import SuccessRateEvaluation
from maniskill_torchrl.trainer_hooks.random_frames import KeepRandomFrames

__all__ = ["KeepRandomFrames", "LogEpisodeMetrics", "SuccessRateEvaluation"]
