"""ManiSkill's trajectory files as TorchRL data: :class:`ManiSkillExperienceReplay`."""

from maniskill_torchrl.data.experience_replay import ManiSkillExperienceReplay
from maniskill_torchrl.data.trajectory_file import TrajectoryFile

__all__ = ["ManiSkillExperienceReplay", "TrajectoryFile"]
