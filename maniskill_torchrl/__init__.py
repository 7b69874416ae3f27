"""ManiSkill 3 as a first-class TorchRL citizen.

- :class:`ManiSkillEnv` / :class:`ManiSkillWrapper`: ManiSkill tasks as TorchRL envs.
- :class:`CPUVectorEnv`: N CPU-sim envs, one per process, with the GPU sim's batched API.
- :class:`ManiSkillAsyncEnvPool` and :class:`AsyncPoolCollector`: the same envs as TorchRL's
  ``AsyncEnvPool``, collected out of lockstep.
- :mod:`maniskill_torchrl.transforms`: ``ActionRepeat``, ``CPUUnbatch``,
  ``IgnoreTerminations``, ``EpisodeMetrics`` as TorchRL transforms.
- :mod:`maniskill_torchrl.wrappers`: drop-in ``CPUGymWrapper`` / ``ActionRepeatWrapper``.

The public names are imported on first use, so ``import maniskill_torchrl.wrappers``
(the gym shim, loaded in every gymnasium vector-env worker) does not import TorchRL.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"


def _require_maniskill() -> None:
    # ManiSkill is an extra (release) or the user's own install (nightly): one clear error when neither is there.
    try:
        found = importlib.util.find_spec("mani_skill") is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        raise ImportError(
            "maniskill_torchrl needs ManiSkill 3 (the `mani_skill` package), which is not installed. "
            'Install the release with `pip install "maniskill-torchrl[maniskill]"` (mani-skill 3.0.x), '
            "or the nightly with `pip install mani-skill-nightly`; both provide `mani_skill`.",
            name="mani_skill",
        )


_require_maniskill()

# No global state is changed here: the multiprocessing start method stays what it was (``import torchrl``,
# which the envs import, sets "spawn" when nothing is set: TorchRL's own choice). The library's own
# worker processes name their context (``multiprocessing.get_context``), as gymnasium's AsyncVectorEnv does.


def _register_dataset_prefix() -> None:
    """The ``maniskill:`` prefix of TorchRL's ``load_dataset``, registered as TorchRL registers its own: a
    ``"module:attribute"`` string, resolved (the data module imported) when first used. Only TorchRL's registry
    changes, and only where TorchRL is imported: ``import maniskill_torchrl`` does not import it (the gym shim's
    workers never do); the library's TorchRL modules (envs, transforms, data, configs) call this on import."""
    if "torchrl.data.datasets" not in sys.modules and "torchrl" not in sys.modules:
        return
    from torchrl.data.datasets import register_dataset

    # replace=True: the same string again on a second call (or a reload).
    register_dataset("maniskill", "maniskill_torchrl.data.datasets:load_maniskill_dataset", replace=True)


_register_dataset_prefix()

_EXPORTS = {
    "ManiSkillEnv": "maniskill_torchrl.envs",
    "ManiSkillWrapper": "maniskill_torchrl.envs",
    "CPUVectorEnv": "maniskill_torchrl.engines.cpu_vector",
    "ManiSkillAsyncEnvPool": "maniskill_torchrl.envs.async_pool",
    "AsyncPoolCollector": "maniskill_torchrl.async_collector",
    "ActionRepeat": "maniskill_torchrl.transforms",
    "CPUUnbatch": "maniskill_torchrl.transforms",
    "EnvStates": "maniskill_torchrl.transforms",
    "EpisodeMetrics": "maniskill_torchrl.transforms",
    "IgnoreTerminations": "maniskill_torchrl.transforms",
    "RenderDeviceError": "maniskill_torchrl.errors",
}

__all__ = [*_EXPORTS, "__version__"]

if TYPE_CHECKING:
    from maniskill_torchrl.async_collector import AsyncPoolCollector
    from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv
    from maniskill_torchrl.envs import ManiSkillEnv, ManiSkillWrapper
    from maniskill_torchrl.envs.async_pool import ManiSkillAsyncEnvPool
    from maniskill_torchrl.errors import RenderDeviceError
    from maniskill_torchrl.transforms import (
        ActionRepeat,
        CPUUnbatch,
        EnvStates,
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
