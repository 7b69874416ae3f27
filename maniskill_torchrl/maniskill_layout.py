"""Where ManiSkill's data goes in :class:`~maniskill_torchrl.ManiSkillWrapper`'s TensorDicts.

:class:`ManiSkillLayout` is the wrapper's mixin for its layout: the specs learnt from the
env's spaces and ``get_info()`` (:func:`maniskill_torchrl.specs.env_specs`), the entries of
each reset and step built from ManiSkill's observation and info tensors, and the error of a
step whose action is missing or misshaped. The wrapper keeps the TorchRL env itself:
stepping, resets and seeding, the CPU workers' action repeat, closing. A mixin, not a helper
object: its methods stay methods of the wrapper, so a step makes no extra call through it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import torch
from tensordict import TensorDictBase

from maniskill_torchrl._maniskill import render_frame_shape, wrapper_attr
from maniskill_torchrl.cpu_vector import CPUVectorEnv
from maniskill_torchrl.errors import action_error, check_info_keys
from maniskill_torchrl.specs import env_specs

__all__ = ["ManiSkillLayout"]


class ManiSkillLayout:
    """The TensorDict layout of :class:`~maniskill_torchrl.ManiSkillWrapper` (mixed into it).

    Reads the host's ``_env``, ``_copies``, ``batch_size``, ``device``, ``action_keys`` and
    ``render()``; sets the specs and, for ``_step``'s action check, ``_action_names`` (the
    agents of a Dict action space, else None) and ``_action_shapes``.

    An unbatched env (``batch_size=[]``, one ManiSkill env) has the specs of the batch-``[1]``
    env with that dim squeezed out, as :class:`~maniskill_torchrl.transforms.CPUUnbatch` gives
    them, and its entries drop it as they are built (no transform, no second pass).
    """

    def _init_layout(
        self, *, from_pixels: bool, pixels_only: bool, info_keys: list[str] | None, unbatched: bool
    ) -> None:
        self._from_pixels = bool(from_pixels)
        self._pixels_only = bool(pixels_only)
        self._requested_info_keys = info_keys
        self._unbatched = unbatched
        # How one ManiSkill tensor becomes an entry. Infos are always cloned: they may alias
        # ManiSkill's buffers (elapsed_steps is updated in place). Observations are cloned where
        # ManiSkill may write into them later (the GPU sim, sapien_cuda pictures) or made them
        # under inference mode (the user gets normal tensors).
        self._obs_leaf = _LEAVES[unbatched, self._copies]
        self._info_leaf = _LEAVES[unbatched, True]

    def _make_specs(self, env: Any) -> None:
        base = env.unwrapped
        obs_space = wrapper_attr(env, "single_observation_space")
        act_space = wrapper_attr(env, "single_action_space")
        frame_shape = None
        if self._from_pixels:
            frame_shape = base.render_frame_shape() if isinstance(base, CPUVectorEnv) else render_frame_shape(base)
        specs = env_specs(
            obs_space,
            act_space,
            self._infos(base),
            torch.Size([base.num_envs]),
            self.device,
            frame_shape=frame_shape,
            pixels_only=self._pixels_only,
        )
        if self._unbatched:
            fields = ("observation", "action", "reward", "done")
            specs = specs._replace(**{f: getattr(specs, f).squeeze(0) for f in fields})
        self._obs_is_dict = isinstance(obs_space, gym.spaces.Dict)
        self._info_map: list[tuple[str, str]] = specs.info_map
        action_spec = specs.action["action"]
        self._action_names = list(act_space.spaces.keys()) if isinstance(act_space, gym.spaces.Dict) else None
        self._action_shapes = (
            {k: action_spec[k].shape for k in self._action_names}
            if self._action_names is not None
            else action_spec.shape
        )
        self.observation_spec = specs.observation
        self.full_action_spec = specs.action
        self.reward_spec = specs.reward
        self.done_spec = specs.done

    def _infos(self, base: Any) -> dict[str, Any]:
        """The info entries to declare: ``info_keys`` (checked) or all of them."""
        # From get_info(): a probe step or reset would change what later seeded resets give.
        infos = base.get_info()
        if self._requested_info_keys is None:
            return infos
        check_info_keys(self._requested_info_keys, infos, base)
        return {k: infos[k] for k in self._requested_info_keys}

    def _render_batched(self, frame: Any) -> torch.Tensor:
        frame = torch.as_tensor(frame, device=self.device)
        if frame.ndim == 3:
            frame = frame.unsqueeze(0)
        return frame

    def _to_tensordict(self, obs: Any, info: Mapping[str, Any]) -> dict:
        leaf = self._obs_leaf
        if self._pixels_only:
            source = {}
        elif self._obs_is_dict:
            source = dict(obs) if leaf is None else _mapped(obs, leaf)
        else:
            source = {"observation": obs if leaf is None else leaf(obs)}
        leaf = self._info_leaf
        for key, td_key in self._info_map:
            source[td_key] = leaf(info[key])
        if self._from_pixels:
            frame = self._render_batched(self.render())
            source["pixels"] = frame[0] if self._unbatched else frame
        return source

    def _action_error(self, tensordict: TensorDictBase, key: str | tuple[str, str], action: Any) -> Exception:
        expected = self._action_shapes[key[1]] if isinstance(key, tuple) else self._action_shapes
        keys = sorted(tensordict.keys(include_nested=True, leaves_only=True), key=str)
        return action_error(type(self).__name__, key, action, expected, keys, self.action_keys)


def _mapped(obs: Mapping[str, Any], leaf: Callable[[torch.Tensor], torch.Tensor]) -> dict:
    """A nested observation dict with ``leaf`` applied to every tensor (other values as they are)."""
    return {
        k: leaf(v) if isinstance(v, torch.Tensor) else _mapped(v, leaf) if isinstance(v, Mapping) else v
        for k, v in obs.items()
    }


def _clone(x: torch.Tensor) -> torch.Tensor:
    return x.clone()


def _unbatch(x: torch.Tensor) -> torch.Tensor:
    return x[0]


def _unbatch_clone(x: torch.Tensor) -> torch.Tensor:
    return x[0].clone()


# (unbatched, copy) -> what a ManiSkill tensor goes through (None: nothing).
_LEAVES: dict[tuple[bool, bool], Callable[[torch.Tensor], torch.Tensor] | None] = {
    (False, False): None,
    (False, True): _clone,
    (True, False): _unbatch,
    (True, True): _unbatch_clone,
}
