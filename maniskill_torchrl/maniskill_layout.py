"""Where ManiSkill's data goes in :class:`~maniskill_torchrl.ManiSkillWrapper`'s TensorDicts.

:class:`ManiSkillLayout` is the wrapper's mixin for its layout: the specs learnt from the
env's spaces and ``get_info()`` (:func:`maniskill_torchrl.specs.env_specs`), the entries of
each reset and step built from ManiSkill's observation and info tensors, ``render()``, and each
step's action as ManiSkill takes it (or the error of one missing or misshaped). Every output is
on the env's device: the sim's by default, or the one asked for (a CPU-sim env with
``device="cuda"``). The wrapper keeps the TorchRL env itself: stepping, resets and seeding,
closing. A mixin, not a helper object: its methods stay methods of the wrapper.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import torch
from tensordict import TensorDictBase

from maniskill_torchrl._maniskill import render_frame_shape, wrapper_attr
from maniskill_torchrl.errors import action_error, check_info_keys, checked_device
from maniskill_torchrl.host_gather import HostGather
from maniskill_torchrl.specs import env_specs

if TYPE_CHECKING:
    from torchrl.envs import EnvBase

__all__ = ["ManiSkillLayout"]


class ManiSkillLayout:
    """The TensorDict layout of :class:`~maniskill_torchrl.ManiSkillWrapper` (mixed into it).

    Reads the host's ``_env``, ``_copies``, ``_sim_device``, ``_sim_mode``, ``batch_size``,
    ``device`` and ``action_keys``; sets ``_moves`` / ``_copy_out`` (whether outputs are copied
    to ``device``) and ``_gather`` (the CPU sim feeding an accelerator: a
    :class:`~maniskill_torchrl.host_gather.HostGather` that sends each step up in one copy, else
    None), again at every :meth:`to`; the specs and, for ``_step``'s action check,
    ``_action_names`` (the agents of a Dict action space, else None) and ``_action_shapes``.

    An unbatched env (``batch_size=[]``, one ManiSkill env) has the specs of the batch-``[1]``
    env with that dim squeezed out, as :class:`~maniskill_torchrl.transforms.CPUUnbatch` gives
    them, and its entries drop it as they are built (no transform, no second pass).
    """

    def _init_layout(
        self,
        *,
        device: torch.device,
        from_pixels: bool,
        pixels_only: bool,
        info_keys: list[str] | None,
        unbatched: bool,
    ) -> None:
        self._from_pixels = bool(from_pixels)
        self._pixels_only = bool(pixels_only)
        self._requested_info_keys = info_keys
        self._unbatched = unbatched
        self._set_device_rule(device)

    def _set_device_rule(self, device: torch.device) -> None:
        """How outputs reach ``device`` and actions the sim: at build time, and again at every
        ``env.to(device)``."""
        # Every output goes to the env's device. What the sim hands out is copied there once where
        # it must be: ManiSkill may write into it later (the GPU sim, sapien_cuda pictures), it
        # was made under inference mode (the user gets normal tensors), or it is elsewhere
        # (a CPU-sim env with device="cuda"; sapien_cuda pictures of a CPU-sim env on the CPU).
        unbatched = self._unbatched
        self._moves = device != self._sim_device
        self._copy_out = self._copies or self._moves
        # The CPU sim feeding an accelerator: a step's host outputs go up in one transfer
        # (HostGather), its sapien_cuda pictures are copied on the device.
        self._gather = HostGather(device) if self._moves and self._sim_device.type == "cpu" else None
        if self._gather is not None:
            self._obs_leaf = self._info_leaf = _unbatch if unbatched else None
        else:
            self._obs_leaf = _leaf(device, unbatched, self._copy_out)
            self._info_leaf = _leaf(device, unbatched, True)  # infos may alias ManiSkill's (elapsed_steps)

    def to(self, device: Any) -> EnvBase:
        """This env with its outputs on ``device`` from now on, and its actions taken there.

        Every output (steps, resets, ``"pixels"``, :meth:`render`, infos, :meth:`get_state`)
        follows, as if the env had been built with ``device=device``: TorchRL calls this for
        ``Collector(env, policy, device=...)``, ``env_device=``, ``TransformedEnv.to`` and
        ``SerialEnv.to``. Returns this env.
        """
        device = checked_device(device, self._sim_device)
        super().to(device)
        self._set_device_rule(self.device)
        return self

    def _make_specs(self, env: Any) -> None:
        base = env.unwrapped
        obs_space = wrapper_attr(env, "single_observation_space")
        act_space = wrapper_attr(env, "single_action_space")
        frame_shape = None
        if self._from_pixels:
            # An engine (CPUVectorEnv) asks one of its sub-envs; a ManiSkill env has no such method.
            engine_frame_shape = getattr(base, "render_frame_shape", None)
            frame_shape = engine_frame_shape() if callable(engine_frame_shape) else render_frame_shape(base)
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

    def render(self) -> Any:
        """ManiSkill's ``render()`` (batched ``[B, H, W, 3]`` uint8 tensor for ``rgb_array``) on
        ``env.device``, a copy where ManiSkill renders into a buffer that its next render overwrites."""
        with self._sim_mode():
            frame = self._env.render()
        if self._copy_out and isinstance(frame, torch.Tensor):
            frame = frame.to(self.device, copy=True)
        return frame

    def _render_batched(self) -> torch.Tensor:
        """The ``"pixels"`` frame, batched: on ``env.device``, or as rendered where a gather moves it."""
        if self._gather is None:
            frame = torch.as_tensor(self.render(), device=self.device)
        else:
            with self._sim_mode():
                frame = torch.as_tensor(self._env.render())
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
        if leaf is None:
            for key, td_key in self._info_map:
                source[td_key] = info[key]
        else:
            for key, td_key in self._info_map:
                source[td_key] = leaf(info[key])
        if self._from_pixels:
            frame = self._render_batched()
            source["pixels"] = frame[0] if self._unbatched else frame
        return source

    def _on_device(self, source: dict) -> dict:
        """``source`` (a step's or reset's entries) on ``env.device``: as it is, or gathered up."""
        return source if self._gather is None else self._gather(source)

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        """The host values of ``tensor`` if it is an entry of this env's last step or reset that
        came up from the host in its one transfer (a CPU-sim env on an accelerator), else None.

        What :class:`~maniskill_torchrl.transforms.EpisodeMetrics` reads rewards and flags from
        instead of the device. Valid until the next step or reset.
        """
        gather = self._gather
        return None if gather is None else gather.host_value(tensor)

    def _sim_action(self, tensordict: TensorDictBase) -> Any:
        """The step's action as ManiSkill takes it (batched, on the sim's device), or an error that
        says what is missing or misshaped."""
        action = tensordict.get("action", None)
        if action is None:
            raise self._action_error(tensordict, "action", None)
        if self._action_names is None:
            if action.shape != self._action_shapes:
                raise self._action_error(tensordict, "action", action)
            if self._unbatched:  # ManiSkill's own batch of one
                action = action.unsqueeze(0)
            return action.to(self._sim_device) if self._moves else action
        action = {k: action.get(k, None) for k in self._action_names}
        for k, a in action.items():
            if a is None or a.shape != self._action_shapes[k]:
                raise self._action_error(tensordict, ("action", k), a)
        if self._unbatched:
            action = {k: a.unsqueeze(0) for k, a in action.items()}
        if self._moves:  # actions come on env.device; the sim takes them on its own
            action = {k: a.to(self._sim_device) for k, a in action.items()}
        return action

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


def _leaf(device: torch.device, unbatched: bool, copy: bool) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """What a ManiSkill tensor goes through to become an entry (None: nothing): the env dim
    dropped for an unbatched env, one copy onto ``device`` where asked."""
    if not copy:
        return _unbatch if unbatched else None
    if unbatched:
        return lambda x: x[0].to(device, copy=True)
    return lambda x: x.to(device, copy=True)


def _unbatch(x: torch.Tensor) -> torch.Tensor:
    return x[0]
