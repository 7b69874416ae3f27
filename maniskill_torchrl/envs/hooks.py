"""What this library's transforms may ask of the env under them: one small protocol.

:class:`~maniskill_torchrl.ManiSkillEnv` (this library's, built on the TorchRL adapter
``maniskill_torchrl.envs.maniskill``) implements it; the adapter itself, and any other env,
does not, and the transforms then take their plain path. Nothing else of an env is read by the
transforms: no private attribute, no undeclared method.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv

__all__ = ["EnvHooks", "env_hooks"]


@runtime_checkable
class EnvHooks(Protocol):
    """The env-side hooks of :class:`~maniskill_torchrl.transforms.ActionRepeat`,
    :class:`~maniskill_torchrl.transforms.EpisodeMetrics` and
    :class:`~maniskill_torchrl.transforms.CachedReset`."""

    def request_worker_repeat(self, repeat: int) -> bool:
        """Asks the env to apply the next step's action up to ``repeat`` times inside its CPU
        workers (ManiSkill's ``ActionRepeatWrapper`` rules, per sub-env). Returns whether it will;
        the request holds for the next step only."""

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        """The host copy of ``tensor``, an entry of the env's last step or reset that was moved
        from the host to an accelerator in one transfer; None where there is none. Valid until
        the next step or reset."""

    def request_reset_states(self, states: TensorDictBase, obs: TensorDictBase | None = None) -> bool:
        """Asks the env to make its next reset a reset to saved states (ManiSkill's
        ``options["reset_to_env_states"]``): ``states`` has one row per env being reset, in env
        order (:meth:`~maniskill_torchrl.ManiSkillWrapper.get_state`'s layout); ``obs``, rows of
        this env's reset tensordicts taken at those states, gives their observations, so that the
        sim skips computing them (no camera renders). Returns whether it will; the request holds
        for the next reset only."""


def env_hooks(env: EnvBase) -> EnvHooks | None:
    """The env under ``env``'s :class:`~torchrl.envs.TransformedEnv` layers if it implements
    :class:`EnvHooks`, else None (a ``ParallelEnv``, a toy env, the plain TorchRL adapter)."""
    while isinstance(env, TransformedEnv):
        env = env.base_env
    # isinstance on the class's attributes: batched envs forward unknown attributes to their
    # sub-envs, so an instance lookup would find them there.
    return env if issubclass(type(env), EnvHooks) else None
