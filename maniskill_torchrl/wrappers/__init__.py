"""The gym shims: ``gym.Wrapper`` drop-ins for ManiSkill's documented wrappers.

Change ``mani_skill.utils.wrappers`` to ``maniskill_torchrl.wrappers`` and everything else stays
the same, bit for bit:

- :class:`CPUGymWrapper` (``wrappers/gymnasium.py``): one CPU env with the unbatched numpy
  gymnasium API, optional episode metrics.
- :class:`ActionRepeatWrapper` (``wrappers/action_repeat.py``): masked action repeat on
  batched torch data.

Both are ``gymnasium.Wrapper`` subclasses on the same core as the TorchRL transforms
(``maniskill_torchrl._internal.repeat``, ``maniskill_torchrl._internal.episode_stats``). They are
not TorchRL env wrappers: the TorchRL wrapper of a ManiSkill env is
:class:`maniskill_torchrl.envs.ManiSkillWrapper` (and :class:`maniskill_torchrl.envs.ManiSkillEnv`
builds one from a task id); the TorchRL counterparts of these two are the transforms
:class:`~maniskill_torchrl.transforms.EpisodeMetrics` / :class:`~maniskill_torchrl.transforms.CPUUnbatch`
and :class:`~maniskill_torchrl.transforms.ActionRepeat`.
"""

from maniskill_torchrl.wrappers.action_repeat import ActionRepeatWrapper
from maniskill_torchrl.wrappers.gymnasium import CPUGymWrapper

__all__ = ["ActionRepeatWrapper", "CPUGymWrapper"]
