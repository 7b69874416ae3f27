"""ManiSkill's trajectory files as TorchRL data: :class:`ManiSkillExperienceReplay` reads them,
:func:`save_trajectories` writes TorchRL rollouts in their format, and importing this module
registers the ``maniskill:`` prefix of TorchRL's ``load_dataset`` (:func:`load_maniskill_dataset`)."""

from torchrl.data.datasets import register_dataset

from maniskill_torchrl.data.datasets import load_maniskill_dataset
from maniskill_torchrl.data.experience_replay import ManiSkillExperienceReplay
from maniskill_torchrl.data.recording import save_trajectories
from maniskill_torchrl.data.trajectory_file import TrajectoryFile

__all__ = ["ManiSkillExperienceReplay", "TrajectoryFile", "load_maniskill_dataset", "save_trajectories"]

# As TorchRL registers its own prefixes: a "module:attribute" string, resolved when first used.
# replace=True: importing this module again (importlib.reload) registers the same string again.
register_dataset("maniskill", "maniskill_torchrl.data.datasets:load_maniskill_dataset", replace=True)
