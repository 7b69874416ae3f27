"""ManiSkill's ``FlattenRGBDObservationWrapper`` on TensorDicts: cameras concatenated, the state flattened."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data import Bounded, Composite, TensorSpec, Unbounded
from torchrl.envs import Transform

__all__ = ["FlattenRGBD"]


class FlattenRGBD(Transform):
    """The observations of ManiSkill's ``FlattenRGBDObservationWrapper``: ``"rgb"`` / ``"depth"`` (or
    ``"rgbd"``) and ``"state"``, from an env with ``obs_mode="rgb"``, ``"depth"`` or ``"rgbd"``.

    ManiSkill's visual baselines (PPO and SAC from pixels) put this wrapper first; this transform gives
    their networks the same inputs, to the bit, inside a :class:`~torchrl.envs.TransformedEnv`:

    - ``"rgb"``: every camera's ``("sensor_data", cam, "rgb")`` concatenated on the channel dim, in the
      cameras' order (``[*batch, H, W, 3 * cameras]``, uint8); ``"depth"`` likewise (int16);
    - with ``sep_depth=False``, one ``"rgbd"`` entry instead, rgb then depth on the channel dim (int16, as
      torch promotes uint8 with int16);
    - ``"state"``: ManiSkill's ``flatten_state_dict`` of the other observation entries (``state_keys``,
      ManiSkill's ``"agent"`` and ``"extra"``): every leaf in order, a ``[*batch]`` leaf as one column, the
      dtypes promoted as ``torch.hstack`` does;
    - ``"sensor_data"``, ``"sensor_param"`` and the state entries are removed; infos (``"success"``, ...)
      and everything else stay.

    A camera without rgb (or depth) turns that option off, as ManiSkill's wrapper does with its first camera.
    The specs are transformed alike (images keep their bounds, concatenated). It works on any batch: the
    GPU sim's ``[num_envs]``, the batched CPU env's, and one CPU env unbatched by
    :class:`~maniskill_torchrl.transforms.CPUUnbatch` (put this one after it).

    Args:
        rgb (bool): include the rgb images. Defaults to ``True``.
        depth (bool): include the depth images. Defaults to ``True``.
        state (bool): include the flattened state. Defaults to ``True``.
        sep_depth (bool): rgb and depth as two entries (``True``) or one ``"rgbd"``. Defaults to ``True``.

    Keyword Args:
        state_keys (sequence of NestedKey): the observation entries flattened into ``"state"``, in order.
            Defaults to ManiSkill's ``("agent", "extra")``.
        state_key (NestedKey): where the flattened state goes. Defaults to ``"state"``. With ``rgb=False,
            depth=False, state_key="observation"`` on an ``obs_mode="state_dict"`` env, this is ManiSkill's
            ``FlattenObservationWrapper`` (the vector ``obs_mode="state"`` gives).

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import FlattenRGBD
        >>> env = TransformedEnv(ManiSkillEnv("PushCube-v1", obs_mode="rgb"), FlattenRGBD())  # doctest: +SKIP
        >>> env.observation_spec["rgb"].shape, env.observation_spec["state"].shape  # doctest: +SKIP
        (torch.Size([1, 128, 128, 3]), torch.Size([1, 25]))
    """

    SENSOR_DATA, SENSOR_PARAM = "sensor_data", "sensor_param"

    def __init__(
        self,
        rgb: bool = True,
        depth: bool = True,
        state: bool = True,
        sep_depth: bool = True,
        *,
        state_keys: Sequence[NestedKey] = ("agent", "extra"),
        state_key: NestedKey = "state",
    ) -> None:
        images = ["rgbd"] if rgb and depth and not sep_depth else ["rgb"] * rgb + ["depth"] * depth
        super().__init__(in_keys=[self.SENSOR_DATA, *state_keys], out_keys=images + [state_key] * state)
        self.rgb, self.depth, self.state, self.sep_depth = rgb, depth, state, sep_depth
        self.state_keys, self.state_key = tuple(state_keys), state_key
        self._leaves: list | None = None  # the state's leaves in order, from the spec (once)

    # ------------------------------------------------------------------ the rule, on data and specs alike
    def _images(self, cameras: TensorDictBase | Composite) -> dict[str, list]:
        """The rgb and depth entries of every camera, by kind, for the options this data allows."""
        first = cameras[next(iter(cameras.keys()))]
        rgb = self.rgb and "rgb" in first.keys()
        depth = self.depth and "depth" in first.keys()
        names = list(cameras.keys())
        out: dict[str, list] = {}
        if rgb and depth and not self.sep_depth:
            out["rgbd"] = [cameras[c, "rgb"] for c in names] + [cameras[c, "depth"] for c in names]
        else:
            if rgb:
                out["rgb"] = [cameras[c, "rgb"] for c in names]
            if depth:
                out["depth"] = [cameras[c, "depth"] for c in names]
        return out

    def _state_leaves(self, source: TensorDictBase | Composite) -> list:
        """The state's leaf keys, in ManiSkill's order (depth first through each entry, insertion order)."""
        leaves = []
        for key in self.state_keys:
            entry = source.get(key, None)
            if entry is None:
                continue
            if isinstance(entry, (TensorDictBase, Composite)):
                leaves += [(key, *((k,) if isinstance(k, str) else k)) for k in entry.keys(True, True)]
            else:
                leaves.append(key)
        return leaves

    @staticmethod
    def _columns(x: torch.Tensor, batch_dims: int) -> torch.Tensor:
        return x.unsqueeze(-1) if x.ndim == batch_dims else x

    # ------------------------------------------------------------------ data
    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        cameras = next_tensordict.get(self.SENSOR_DATA, None)
        images = self._images(cameras) if cameras is not None else {}
        # rgbd: every camera's rgb, then every camera's depth, as ManiSkill's two concatenations give
        out = {kind: torch.cat(parts, -1) for kind, parts in images.items()}
        if self.state:
            leaves = self._leaves if self._leaves is not None else self._state_leaves(next_tensordict)
            batch_dims = next_tensordict.batch_dims
            columns = [self._columns(next_tensordict.get(key), batch_dims) for key in leaves]
            out[self.state_key] = torch.cat(columns, -1)
        next_tensordict = next_tensordict.exclude(self.SENSOR_DATA, self.SENSOR_PARAM, *self.state_keys)
        next_tensordict.update(out)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._call(tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The rule on stored data (a replay buffer's transform): the root and ``"next"``."""
        nxt = tensordict.get("next", None)
        tensordict = self._call(tensordict)
        if nxt is not None:
            tensordict.set("next", self._call(nxt))
        return tensordict

    # ------------------------------------------------------------------ specs
    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        if self.SENSOR_DATA not in observation_spec.keys() and (self.rgb or self.depth):
            raise KeyError(
                "FlattenRGBD needs camera observations: make the env with obs_mode='rgb', 'depth' or 'rgbd' "
                f"(this one has {sorted(observation_spec.keys())})."
            )
        cameras = observation_spec.get(self.SENSOR_DATA, None)
        batch = observation_spec.shape
        new: dict[str, TensorSpec] = {}
        for kind, specs in (self._images(cameras) if cameras is not None else {}).items():
            low = torch.cat([s.space.low for s in specs], -1)  # promoted as the data is (rgbd: int16)
            high = torch.cat([s.space.high for s in specs], -1)
            new[kind] = Bounded(low, high, shape=low.shape, dtype=low.dtype, device=specs[0].device)
        if self.state:
            self._leaves = self._state_leaves(observation_spec)
            specs = [observation_spec[key] for key in self._leaves]
            width = sum(1 if s.ndim == len(batch) else s.shape[-1] for s in specs)
            new[self.state_key] = Unbounded(
                shape=(*batch, width), dtype=_promoted([s.dtype for s in specs]), device=observation_spec.device
            )
        for key in (self.SENSOR_DATA, self.SENSOR_PARAM, *self.state_keys):
            if key in observation_spec.keys(True):
                del observation_spec[key]
        for key, spec in new.items():
            observation_spec[key] = spec
        self.out_keys = list(new)  # a camera without depth (or rgb) has none to give
        return observation_spec

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(rgb={self.rgb}, depth={self.depth}, state={self.state}, sep_depth={self.sep_depth})"
        )


def _promoted(dtypes: list[torch.dtype]) -> torch.dtype:
    """The dtype ``torch.cat`` / ``torch.hstack`` give tensors of these dtypes."""
    out = dtypes[0]
    for dtype in dtypes[1:]:
        out = torch.promote_types(out, dtype)
    return out
