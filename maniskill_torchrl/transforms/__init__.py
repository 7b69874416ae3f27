"""TorchRL transforms for ManiSkill envs."""

from maniskill_torchrl import _register_dataset_prefix
from maniskill_torchrl.transforms.action_repeat import ActionRepeat
from maniskill_torchrl.transforms.cached_reset import CachedReset
from maniskill_torchrl.transforms.cpu_unbatch import CPUUnbatch
from maniskill_torchrl.transforms.env_states import EnvStates
from maniskill_torchrl.transforms.episode_metrics import EpisodeMetrics
from maniskill_torchrl.transforms.flatten_action_space import FlattenActionSpace
from maniskill_torchrl.transforms.flatten_rgbd import FlattenRGBD
from maniskill_torchrl.transforms.sparse_reward import SparseReward
from maniskill_torchrl.transforms.terminations import IgnoreTerminations

__all__ = [
    "ActionRepeat",
    "CachedReset",
    "CPUUnbatch",
    "EnvStates",
    "EpisodeMetrics",
    "FlattenActionSpace",
    "FlattenRGBD",
    "IgnoreTerminations",
    "SparseReward",
]

_register_dataset_prefix()  # TorchRL is imported now: the maniskill: prefix of its load_dataset
