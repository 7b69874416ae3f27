"""Drop-in gym shim: change ``mani_skill.utils.wrappers`` to ``maniskill_torchrl.wrappers``.

- :class:`CPUGymWrapper` (``wrappers/gymnasium.py``): one CPU env with the
  unbatched numpy gymnasium API, optional episode metrics.
- :class:`ActionRepeatWrapper` (``wrappers/action_repeat.py``): masked action
  repeat on batched torch data.

Both give ManiSkill's outputs bit for bit, on the same core as the TorchRL
transforms (``maniskill_torchrl._internal.repeat``, ``maniskill_torchrl._internal.episode_stats``).
"""

from maniskill_torchrl.wrappers.action_repeat import ActionRepeatWrapper
from maniskill_torchrl.wrappers.gymnasium import CPUGymWrapper

__all__ = ["ActionRepeatWrapper", "CPUGymWrapper"]
