"""TorchRL trainer hooks for ManiSkill: what TorchRL 0.14's trainers lack for its tasks.

TorchRL's config-driven trainers (``torchrl.trainers.algorithms``: ``SACTrainer``,
``PPOTrainer``, ``OfflineToOnlineTrainer``...) run on a ManiSkill env as on any TorchRL env
(``examples/trainers``, the guide "Train with TorchRL's trainers"). Three things ManiSkill users
expect are missing there; each is a :class:`~torchrl.trainers.TrainerHookBase` here, with a
config in TorchRL's ``hook`` group (``import maniskill_torchrl.configs``) for the trainer
configs' ``hooks`` field:

=============================  ==========================  ========================================
hook                           config (group ``hook``)     the gap in TorchRL 0.14.1
=============================  ==========================  ========================================
:class:`SuccessRateEvaluation` ``success_rate_evaluation`` ``LogValidationReward`` rolls the policy
                                                           out unseeded for a number of frames, every
                                                           so many *calls*, and logs rewards only
                                                           (then closes its env). No hook runs seeded
                                                           full episodes and logs success rates,
                                                           ManiSkill's measure.
:class:`LogEpisodeMetrics`     ``log_episode_metrics``     ``LogScalar`` reduces an entry over every
                                                           step of a batch, and the trainer's log
                                                           drops values between two logs; episode
                                                           metrics mean something only where an
                                                           episode ends (``("next", "done")``).
:class:`KeepRandomFrames`      ``keep_random_frames``      ``SACTrainer`` and ``OfflineToOnline
                                                           Trainer`` extend their buffer inside the
                                                           optimization loop, which is skipped until
                                                           ``init_random_frames``: the random frames
                                                           never reach the buffer.
=============================  ==========================  ========================================

Other gaps, met without a hook (noted for upstream):

- No trainer logs episode returns without TorchRL's ``RewardSum`` (``episode_reward_key``
  defaults to ``"reward_sum"``); with ``EpisodeMetrics`` set ``episode_reward_key:
  [episode, return]``.
- ``SACLoss`` always backs up the entropy term; ManiSkill's RLPD runs ``backup_entropy: False``.
- TorchRL's ``TanhNormal`` model config has a state-dependent scale only; ManiSkill's PPO
  learns a state-independent log std (``AddStateIndependentNormalScale``).
- ``OfflineToOnlineReplayBuffer`` samples offline data with an ``"index"`` entry that the online
  half lacks, and takes demonstrations' rewards as stored: the RLPD config adds ManiSkill's sparse
  reward and drops the extra entries with transforms (``examples/trainers/config``).
- The CPU engine's ``num_envs``: nothing to add. ``env: maniskill`` with ``num_envs: N`` is one
  batched env (one process per sub-env on the CPU sim) that TorchRL's single-process ``sync``
  collector drives; TorchRL's ``batched_env`` node (a ``ParallelEnv`` of single envs) works too.
"""

from __future__ import annotations

from maniskill_torchrl.trainer_hooks.episode_log import LogEpisodeMetrics
from maniskill_torchrl.trainer_hooks.evaluation import SuccessRateEvaluation
from maniskill_torchrl.trainer_hooks.random_frames import KeepRandomFrames

__all__ = ["KeepRandomFrames", "LogEpisodeMetrics", "SuccessRateEvaluation"]
