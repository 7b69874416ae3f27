""":class:`EnvStates`: each step's ManiSkill sim state in the tensordict, for recording."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, TensorSpec, Unbounded
from torchrl.envs import Transform

__all__ = ["EnvStates"]


class EnvStates(Transform):
    """Adds ``"env_states"``: the sim state of every env (``env.get_state()``, ManiSkill's
    ``get_state_dict()``) after each reset and step, so that a rollout carries what ManiSkill's
    trajectory files keep (:func:`~maniskill_torchrl.data.save_trajectories` writes it, and
    ``env.reset_to_state`` goes back to any step).

    One state read per step: for recording and evaluation, not for fast collection. The states
    have the batch of the env this transform sits on: placed after
    :class:`~maniskill_torchrl.transforms.CPUUnbatch` (or on ``ManiSkillEnv(..., batch_size=[])``)
    they are unbatched (``actors/cube`` of shape ``[13]`` per step), as with it placed before
    ``CPUUnbatch``. A batch the states cannot take (the parent is not one ManiSkill env's batch or
    its unbatched view) is refused with an error.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import EnvStates
        >>> env = TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state"), EnvStates())
        >>> td = env.rollout(2)
        >>> td["next", "env_states", "actors", "cube"].shape
        torch.Size([1, 2, 13])
    """

    def _states(self) -> TensorDictBase:
        parent = self.parent
        if parent is None:
            raise RuntimeError("EnvStates reads the env it is placed on: put it in a TransformedEnv first.")
        base = parent.base_env
        if not hasattr(base, "get_state"):
            raise TypeError(
                f"EnvStates reads ManiSkill sim states (ManiSkillWrapper.get_state()), but it is placed on "
                f"{type(base).__name__}: put it on a ManiSkillEnv / ManiSkillWrapper."
            )
        states = base.get_state()
        batch = parent.batch_size
        if states.batch_size == batch:
            return states
        # After CPUUnbatch the transforms before this one took the env dim away: so do the states.
        if states.batch_size == torch.Size([1]) and batch == torch.Size([]):
            return states.squeeze(0)
        raise ValueError(
            f"EnvStates: the env's states have batch {list(states.batch_size)} but the env it is placed on has "
            f"batch {list(batch)} (a transform before it changed the batch). Put EnvStates first, right on the "
            "ManiSkill env."
        )

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set("env_states", self._states())
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        tensordict_reset.set("env_states", self._states())
        return tensordict_reset

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        # The layout from the env's current state (reading it neither steps nor resets).
        states = self._states()

        def spec(td: TensorDictBase) -> Composite:
            return Composite(
                {
                    k: spec(v) if isinstance(v, TensorDictBase) else Unbounded(v.shape, dtype=v.dtype, device=v.device)
                    for k, v in td.items()
                },
                shape=td.batch_size,
                device=states.device,
            )

        observation_spec["env_states"] = spec(states)
        return observation_spec

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
