"""ManiSkill's trajectory files as TorchRL data: :class:`ManiSkillExperienceReplay` reads them,
:func:`save_trajectories` writes TorchRL rollouts in their format, and importing this module
registers the ``maniskill:`` prefix of TorchRL's ``load_dataset`` (:func:`load_maniskill_dataset`)."""

from maniskill_torchrl import _register_dataset_prefix
from maniskill_torchrl.data.datasets import load_maniskill_dataset
from maniskill_torchrl.data.experience_replay import ManiSkillExperienceReplay
from maniskill_torchrl.data.recording import save_trajectories
from maniskill_torchrl.data.trajectory_file import TrajectoryFile

__all__ = ["ManiSkillExperienceReplay", "TrajectoryFile", "load_maniskill_dataset", "save_trajectories"]

_register_dataset_prefix()  # TorchRL is imported now (experience_replay)
