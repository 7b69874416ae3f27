"""ManiSkill 3 as a first-class TorchRL citizen.

- :class:`ManiSkillEnv` / :class:`ManiSkillWrapper`: ManiSkill tasks as TorchRL envs.
- :class:`CPUVectorEnv`: N CPU-sim envs in worker processes with the GPU sim's batched API.
- :mod:`maniskill_torchrl.transforms`: ``ActionRepeat``, ``CPUUnbatch``,
  ``IgnoreTerminations``, ``EpisodeMetrics`` as TorchRL transforms.
- :mod:`maniskill_torchrl.wrappers`: drop-in ``CPUGymWrapper`` / ``ActionRepeatWrapper``.

The public names are imported on first use, so ``import maniskill_torchrl.wrappers``
(the gym shim, loaded in every gymnasium vector-env worker) does not import TorchRL.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from maniskill_torchrl._mp import prefer_spawn

__version__ = "0.1.0"

# As ``import torchrl`` does: without it, the first process any library starts (gymnasium's
# AsyncVectorEnv, say) pins "fork", and a TorchRL ParallelEnv built later in this process forks
# a parent holding a SAPIEN renderer and hangs (see maniskill_torchrl/_mp.py).
prefer_spawn()

_EXPORTS = {
    "ManiSkillEnv": "maniskill_torchrl.env",
    "ManiSkillWrapper": "maniskill_torchrl.env",
    "CPUVectorEnv": "maniskill_torchrl.cpu_vector",
    "ActionRepeat": "maniskill_torchrl.transforms",
    "CPUUnbatch": "maniskill_torchrl.transforms",
    "EpisodeMetrics": "maniskill_torchrl.transforms",
    "IgnoreTerminations": "maniskill_torchrl.transforms",
}

__all__ = [*_EXPORTS, "__version__"]

if TYPE_CHECKING:
    from maniskill_torchrl.cpu_vector import CPUVectorEnv
    from maniskill_torchrl.env import ManiSkillEnv, ManiSkillWrapper
    from maniskill_torchrl.transforms import (
        ActionRepeat,
        CPUUnbatch,
        EpisodeMetrics,
        IgnoreTerminations,
    )


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'maniskill_torchrl' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
