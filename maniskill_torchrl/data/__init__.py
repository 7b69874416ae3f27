"""ManiSkill's trajectory files as TorchRL data: :class:`ManiSkillExperienceReplay` reads them,
:func:`save_trajectories` writes TorchRL rollouts in their format."""

from maniskill_torchrl.data.experience_replay import ManiSkillExperienceReplay
from maniskill_torchrl.data.recording import save_trajectories
from maniskill_torchrl.data.trajectory_file import TrajectoryFile

__all__ = ["ManiSkillExperienceReplay", "TrajectoryFile", "save_trajectories"]
