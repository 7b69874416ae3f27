""":class:`EnvStates`: each step's ManiSkill sim state in the tensordict, for recording."""

from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.data import Composite, TensorSpec, Unbounded
from torchrl.envs import Transform

__all__ = ["EnvStates"]


class EnvStates(Transform):
    """Adds ``"env_states"``: the sim state of every env (``env.get_state()``, ManiSkill's
    ``get_state_dict()``) after each reset and step, so that a rollout carries what ManiSkill's
    trajectory files keep (:func:`~maniskill_torchrl.data.save_trajectories` writes it, and
    ``env.reset_to_state`` goes back to any step).

    One state read per step: for recording and evaluation, not for fast collection. Put it
    directly on the :class:`~maniskill_torchrl.ManiSkillWrapper` (first in a ``Compose``), so that
    it reads the env it wraps.

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
        return self.parent.base_env.get_state()

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
