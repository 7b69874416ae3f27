"""What :class:`~maniskill_torchrl.ManiSkillWrapper` refuses, and how it says so: its arguments
(a device that is not there, ``frame_skip``), envs it cannot serve (auto-resetting wrappers,
a reconfiguration that partial resets cannot do), unknown info keys, a step without its action,
a call after ``close()`` (where TorchRL or a closed ManiSkill sim would fail with unrelated errors).

Private to the library (not exported from :mod:`maniskill_torchrl`); no TorchRL import.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from maniskill_torchrl._maniskill import (
    auto_resetting_wrapper,
    canonical_device,
    ignores_terminations,
    maniskill_base_env,
)

__all__ = [
    "checked_base_env",
    "checked_device",
    "checked_batch_size",
    "check_frame_skip",
    "check_info_keys",
    "MissingActionError",
    "action_error",
    "ClosedEnv",
]


def checked_base_env(env: Any, *, from_pixels: bool, pixels_only: bool) -> Any:
    """The ManiSkill env (or the engine, :class:`~maniskill_torchrl.CPUVectorEnv`) under ``env``, after
    checking the wrapper's arguments. An engine is known by the capabilities it declares
    (``maniskill_torchrl.engines``): this module does not import it."""
    if env is None:
        raise TypeError(
            "ManiSkillWrapper needs a ManiSkill env: ManiSkillWrapper(gym.make('PickCube-v1')) "
            "or ManiSkillEnv('PickCube-v1')."
        )
    base = env if _is_engine(env) else maniskill_base_env(env)
    if base is None:
        raise TypeError(
            f"ManiSkillWrapper wraps ManiSkill 3 envs only, got {type(env).__name__} "
            f"(unwrapped: {type(getattr(env, 'unwrapped', env)).__name__}). Make one with "
            "gym.make('<Task>-v1', ...) after `import mani_skill.envs`, or CPUVectorEnv('<Task>-v1', N) "
            "for N CPU-sim envs; for other gym envs use torchrl.envs.GymWrapper."
        )
    resetter = auto_resetting_wrapper(env)
    if resetter is not None:
        raise ValueError(
            f"{resetter} resets done envs inside its step and returns the next episode's first "
            "observation in place of the last one, which TorchRL would then reset a second time: the "
            "final observations would be lost. TorchRL resets done envs itself (partial resets): wrap "
            "the ManiSkill env without it, ManiSkillWrapper(gym.make(...)), or "
            "ManiSkillVectorEnv(env, auto_reset=False), or use ManiSkillEnv(...)."
        )
    freq = getattr(base, "reconfiguration_freq", 0) or 0
    partial = getattr(base, "reconfigures_partially", False)
    if base.num_envs > 1 and freq and not partial and not ignores_terminations(env):
        raise ValueError(
            f"reconfiguration_freq={freq} with num_envs={base.num_envs}: ManiSkill cannot reconfigure "
            "some of its envs only, and TorchRL resets each done env on its own (partial resets), "
            "which would fail mid-run ('Cannot do a partial reset and reconfigure the environment'). "
            "Make the env with reconfiguration_freq=0, or, for evaluation episodes that all run to the "
            "time limit and reset together, wrap it in ManiSkillVectorEnv(env, auto_reset=False, "
            "ignore_terminations=True) first (ManiSkillVectorEnv has the same rule)."
        )
    if pixels_only and not from_pixels:
        raise ValueError("pixels_only=True needs from_pixels=True.")
    if from_pixels and base.render_mode != "rgb_array":
        raise ValueError(
            f"from_pixels=True needs an env made with render_mode='rgb_array' (got render_mode={base.render_mode!r})."
        )
    return base


def _is_engine(env: Any) -> bool:
    """Whether ``env`` is an engine of ``maniskill_torchrl.engines`` wrapped as is: it declares its
    capabilities (a ManiSkill ``BaseEnv`` and gym wrappers declare none)."""
    return getattr(env, "seeds_partial_resets", False) is True and getattr(env, "unwrapped", None) is env


def checked_device(device: Any, sim_device: torch.device) -> torch.device:
    """The env's device: ``device`` (where its outputs go), else the sim's own device."""
    if device is None:
        return sim_device
    try:
        device = canonical_device(device)
    except RuntimeError as e:
        raise ValueError(f"device={device!r} is not a torch device: {e}") from e
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"device={str(device)!r}, but torch.cuda.is_available() is False: leave device out (the sim's "
            f"device, {sim_device}) or install a CUDA build of torch."
        )
    return device


def checked_batch_size(batch_size: Any, num_envs: int) -> torch.Size:
    """The env's batch size: ``[num_envs]`` (``batch_size=None``), or ``[]`` for one env asked unbatched."""
    if batch_size is None:
        return torch.Size([num_envs])
    try:
        size = torch.Size(batch_size)
    except TypeError:
        size = None
    if size == torch.Size([num_envs]) or (size == torch.Size([]) and num_envs == 1):
        return size
    raise ValueError(
        f"batch_size={batch_size!r} does not fit a ManiSkill env with num_envs={num_envs}: leave it out "
        f"(batch_size [{num_envs}], ManiSkill's num_envs), or pass batch_size=[] with num_envs=1 for one "
        "unbatched env (batch_size [], what ParallelEnv / SerialEnv stack)."
    )


def check_frame_skip(frame_skip: Any) -> None:
    """Refuses ``frame_skip > 1``: TorchRL's frame skip would sum rewards past an episode's end."""
    if frame_skip is not None and frame_skip != 1:
        raise ValueError(
            f"frame_skip={frame_skip} is not supported: TorchRL's FrameSkipTransform keeps stepping an "
            "env after its episode ends. Use TransformedEnv(env, ActionRepeat(k)) from "
            "maniskill_torchrl.transforms, ManiSkill's ActionRepeatWrapper semantics: rewards summed "
            "over the steps each env really took, its last observation kept."
        )


def check_info_keys(info_keys: list[str], infos: Mapping[str, Any], base: Any) -> None:
    """Every one of ``info_keys`` must be in ``base.get_info()`` (``infos``)."""
    missing = [k for k in info_keys if k not in infos]
    if missing:
        raise ValueError(
            f"info_keys {missing} are not reported by {base.spec.id if base.spec else base}: "
            f"available info keys are {sorted(infos)}."
        )


class MissingActionError(KeyError):
    """A KeyError whose message prints as written (KeyError prints the repr of its argument)."""

    def __str__(self) -> str:
        return str(self.args[0])


def action_error(
    env_name: str,
    key: str | tuple[str, str],
    action: torch.Tensor | None,
    expected: torch.Size,
    entries: list[Any],
    action_keys: list[Any],
) -> Exception:
    """The error of ``env.step(td)`` when ``td`` has no entry at the action ``key`` (``action`` is
    ``None``; ``entries`` are the keys ``td`` has) or one of another shape than ``expected``."""
    if action is None:
        return MissingActionError(
            f"{env_name}.step() found no action at {key!r} in the tensordict, whose entries are "
            f"{entries}. Set the action entries {action_keys} (shapes from env.full_action_spec), e.g. "
            "td = env.rand_action(td) for random actions, or run a policy that writes them."
        )
    if isinstance(key, tuple):
        return ValueError(f"ManiSkill action {key[1]!r} of shape {tuple(action.shape)}, expected {tuple(expected)}.")
    return ValueError(
        f"ManiSkill action of shape {tuple(action.shape)}, expected "
        f"{tuple(expected)} ([*env.batch_size, *single_action_space.shape])."
    )


class ClosedEnv:
    """Takes the ManiSkill env's place after ``close()``: stepping, resetting or rendering says that
    the env is closed (a closed ManiSkill sim fails with unrelated AttributeErrors)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def _closed(self, *args: Any, **kwargs: Any) -> Any:
        raise RuntimeError(
            f"{self.name} is closed: it cannot step, reset or render any more. "
            "Make a new env (ManiSkillEnv(...) or ManiSkillWrapper(gym.make(...))) instead of reusing a closed one."
        )

    step = reset = render = _closed

    @property
    def unwrapped(self) -> Any:
        return self._closed()

    def close(self) -> None:
        return None
