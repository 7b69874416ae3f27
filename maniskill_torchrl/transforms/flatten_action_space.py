"""ManiSkill's ``FlattenActionSpaceWrapper`` on TensorDicts: a Dict action (one Box per agent) as one Box."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.data import Bounded, Composite, TensorSpec
from torchrl.envs import Transform

__all__ = ["FlattenActionSpace"]


class FlattenActionSpace(Transform):
    """One flat ``"action"`` Box for an env whose action is a Dict of Boxes (ManiSkill's multi-agent tasks,
    ``TwoRobotPickCube-v1``: ``("action", "panda_wristcam-0")`` and ``("action", "panda_wristcam-1")``).

    ManiSkill's ``FlattenActionSpaceWrapper``: the policy writes one ``[*batch, sum of widths]`` action, the
    agents' Boxes side by side in the Dict's order; on the way in, this transform cuts it back into each
    agent's entry (the inverse), so ManiSkill steps exactly what the wrapper would give it. The action spec
    is the Boxes' bounds concatenated. As ManiSkill's wrapper, it takes a flat Dict of 1-D Boxes.
    TorchRL's own :class:`~torchrl.envs.transforms.FlattenAction` does something else: it flattens adjacent
    dims of one action tensor.

    Args:
        action_key (NestedKey): the Dict action's key. Defaults to ``"action"``.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import FlattenActionSpace
        >>> env = TransformedEnv(ManiSkillEnv("TwoRobotPickCube-v1", obs_mode="state"), FlattenActionSpace())
        >>> env.action_spec.shape
        torch.Size([1, 16])
        >>> env.rollout(2)["next", "observation"].shape
        torch.Size([1, 2, 66])
    """

    def __init__(self, action_key: NestedKey = "action") -> None:
        super().__init__(in_keys=[], out_keys=[], in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.action_key = action_key
        self._names: list[str] | None = None
        self._widths: list[int] | None = None

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        actions = input_spec["full_action_spec"].get(self.action_key)
        if not isinstance(actions, Composite):
            raise TypeError(
                f"FlattenActionSpace flattens a Dict action (one Box per agent); {self.action_key!r} is already one "
                f"{type(actions).__name__}: the transform is not needed."
            )
        specs = [actions[name] for name in actions.keys()]
        if any(isinstance(spec, Composite) or spec.ndim != actions.ndim + 1 for spec in specs):
            raise ValueError(
                "FlattenActionSpace takes a flat Dict of 1-D Boxes, as ManiSkill's FlattenActionSpaceWrapper does."
            )
        self._names = list(actions.keys())
        self._widths = [spec.shape[-1] for spec in specs]
        low = torch.cat([spec.space.low for spec in specs], -1)
        high = torch.cat([spec.space.high for spec in specs], -1)
        flat: TensorSpec = Bounded(low, high, shape=low.shape, dtype=specs[0].dtype, device=specs[0].device)
        input_spec["full_action_spec"].set(self.action_key, flat)
        return input_spec

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self._names is None:  # the specs make the layout; a transform never asked for them has none
            self.transform_input_spec(self.parent.input_spec.clone())
        flat = tensordict.get(self.action_key)
        parts = flat.split(self._widths, -1)
        batch = flat.shape[:-1]
        tensordict.set(self.action_key, TensorDict(dict(zip(self._names, parts)), batch_size=batch))
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}(action_key={self.action_key!r})"
