"""TorchRL transforms for ManiSkill envs."""
from maniskill_torchrl.transforms.action_repeat import ActionRepeat

__all__ = [
    "ActionRepeat",
]
