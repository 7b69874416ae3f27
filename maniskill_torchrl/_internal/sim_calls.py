"""How this library's envs call their ManiSkill env: under :func:`torch.inference_mode`
(:class:`InferenceModeEnv`), and not at all once closed (:class:`ClosedEnv`)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch

__all__ = ["ClosedEnv", "InferenceModeEnv"]


class InferenceModeEnv(gym.Wrapper):
    """Runs the env's ``step``, ``reset`` and ``render`` under :func:`torch.inference_mode`.

    The same values for less CPU on the CPU sim: torch records nothing for autograd. What comes
    out is made of inference tensors, which the TorchRL env copies into normal ones.
    """

    def step(self, action: Any) -> Any:
        with torch.inference_mode():
            return self.env.step(action)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> Any:
        with torch.inference_mode():
            return self.env.reset(seed=seed, options=options)

    def render(self) -> Any:
        with torch.inference_mode():
            return self.env.render()


class ClosedEnv:
    """Takes the ManiSkill env's place after ``close()``.

    A closed ManiSkill sim fails with unrelated AttributeErrors; this says it is closed.
    """

    def __init__(self, name: str) -> None:
        self.name = name

    def _closed(self, *args: Any, **kwargs: Any) -> Any:
        raise RuntimeError(
            f"{self.name} is closed: it cannot step, reset or render any more. "
            "Make a new env instead of reusing a closed one."
        )

    step = reset = render = _closed

    @property
    def unwrapped(self) -> Any:
        return self._closed()

    def close(self) -> None:
        return None
