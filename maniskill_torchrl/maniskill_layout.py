"""Where ManiSkill's data goes in :class:`~maniskill_torchrl.ManiSkillWrapper`'s TensorDicts.

:class:`ManiSkillLayout` is the wrapper's mixin for its layout: the specs learnt from the
env's spaces and ``get_info()`` (:func:`maniskill_torchrl.specs.env_specs`), the entries of
each reset and step built from ManiSkill's observation and info tensors, and the error of a
step whose action is missing or misshaped. The wrapper keeps the TorchRL env itself:
stepping, resets and seeding, the CPU workers' action repeat, closing. A mixin, not a helper
object: its methods stay methods of the wrapper, so a step makes no extra call through it.
"""

from __future__ import annotations

from collections.abc import Mapping
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

    Reads the host's ``_env``, ``_inference``, ``batch_size``, ``device``, ``action_keys`` and
    ``render()``; sets the specs and, for ``_step``'s action check, ``_action_names`` (the
    agents of a Dict action space, else None) and ``_action_shapes``.
    """

    def _init_layout(self, *, from_pixels: bool, pixels_only: bool, info_keys: list[str] | None) -> None:
        self._from_pixels = bool(from_pixels)
        self._pixels_only = bool(pixels_only)
        self._requested_info_keys = info_keys

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
            self.batch_size,
            self.device,
            frame_shape=frame_shape,
            pixels_only=self._pixels_only,
        )
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
        if self._pixels_only:
            source = {}
        elif self._inference:  # made under inference mode: copies, normal tensors for the user
            source = _copied(obs) if self._obs_is_dict else {"observation": obs.clone()}
        elif self._obs_is_dict:
            source = dict(obs)
        else:
            source = {"observation": obs}
        # Info tensors may alias ManiSkill's buffers (elapsed_steps is updated in place): clone them.
        for key, td_key in self._info_map:
            source[td_key] = info[key].clone()
        if self._from_pixels:
            source["pixels"] = self._render_batched(self.render())
        return source

    def _action_error(self, tensordict: TensorDictBase, key: str | tuple[str, str], action: Any) -> Exception:
        expected = self._action_shapes[key[1]] if isinstance(key, tuple) else self._action_shapes
        keys = sorted(tensordict.keys(include_nested=True, leaves_only=True), key=str)
        return action_error(type(self).__name__, key, action, expected, keys, self.action_keys)


def _copied(obs: Mapping[str, Any]) -> dict:
    """A nested observation dict with every tensor cloned (other values as they are)."""
    return {
        k: v.clone() if isinstance(v, torch.Tensor) else _copied(v) if isinstance(v, Mapping) else v
        for k, v in obs.items()
    }
