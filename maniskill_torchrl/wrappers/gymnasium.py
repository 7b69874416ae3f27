"""Drop-in ``CPUGymWrapper``: ``mani_skill.utils.wrappers.CPUGymWrapper`` on the shared core.

Change ``from mani_skill.utils.wrappers import CPUGymWrapper`` to
``from maniskill_torchrl.wrappers import CPUGymWrapper``; observations, rewards,
flags, infos and ``info["episode"]`` stay the same, value for value and type for
type. The episode metrics come from :class:`maniskill_torchrl._internal.episode_stats.EpisodeStats`,
the same code as the TorchRL ``EpisodeMetrics`` transform.
"""

from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
import torch
from mani_skill.envs.sapien_env import BaseEnv
from mani_skill.utils.common import to_numpy
from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper as _ManiSkillCPUGymWrapper

from maniskill_torchrl._internal.episode_stats import EpisodeField, EpisodeStats
from maniskill_torchrl.wrappers._common import np_unbatch, require_maniskill_env

__all__ = ["CPUGymWrapper"]

_IMAGE_RENDER_MODES = ("rgb_array", "sensors", "all")


# ManiSkill's key order of info["episode"]: the *_once flags, return / episode_len / reward, the *_at_end flags.
_GYM_RANK = {"once": 0, "at_end": 2}


def _gym_layout(fields: tuple[EpisodeField, ...], ignore_terminations: bool) -> list[tuple[str, bool]]:
    """``(name, as np.float32)`` per ``info["episode"]`` entry; ``*_at_end`` only with ``ignore_terminations``."""
    kept = [f for f in fields if f.kind != "at_end" or ignore_terminations]
    kept.sort(key=lambda f: _GYM_RANK.get(f.kind, 1))
    return [(f.name, f.dtype == torch.float32) for f in kept]


def _array(x: Any) -> np.ndarray | None:
    """The env's reward / flag as numpy (a CPU tensor's zero-copy view), for the episode statistics."""
    return x.numpy() if type(x) is torch.Tensor else None if x is None else np.asarray(x)


class CPUGymWrapper(_ManiSkillCPUGymWrapper):
    """A single CPU ManiSkill env with the standard, unbatched numpy gymnasium API.

    The same wrapper as ManiSkill's ``CPUGymWrapper``, which it subclasses (so
    ``isinstance`` checks such as ``RecordEpisode``'s keep working):

    - ``reset`` / ``step`` / ``render`` return numpy data without the batch dim
      of 1: observations (nested dicts included) as numpy arrays, a ``(1,)``
      entry as a python scalar; the reward as a python ``float``,
      ``terminated`` / ``truncated`` as python ``bool``; info entries likewise
      (``info["elapsed_steps"]`` a python ``int``, ``info["success"]`` a ``bool``).
    - ``observation_space`` / ``action_space`` are the env's single (unbatched)
      spaces. Actions may be numpy arrays or torch tensors (or dicts of them for
      multi-agent tasks).
    - ``ignore_terminations=True`` always returns ``terminated=False``, so an
      episode runs until truncation (the time limit), as ManiSkill's evaluation does.
    - ``record_metrics=True`` adds ``info["episode"]``: ``success_once`` /
      ``fail_once`` (python ``bool``, where the task reports success / fail),
      ``return`` (``np.float32``, summed exactly as ``np.sum``), ``episode_len``
      (``int``), ``reward`` (``np.float32``, return / length) and, with
      ``ignore_terminations=True``, ``success_at_end`` / ``fail_at_end``.
      Metrics restart on every ``reset``.

    Why: gymnasium's vector envs (``SyncVectorEnv``,
    ``AsyncVectorEnv(context="forkserver")``) and evaluation code written for
    single gymnasium envs expect this API; ManiSkill's own API is batched torch.
    Apply it last, after any wrapper that works on batched torch data.

    Args:
        env: a ManiSkill env made with ``gym.make(..., num_envs=1)`` on the CPU
            sim, possibly inside further gym wrappers.
        ignore_terminations: report ``terminated=False`` always.
        record_metrics: add the ``info["episode"]`` metrics.

    Raises:
        TypeError: ``env`` is not a ManiSkill env.
        ValueError: ``env`` has ``num_envs != 1`` or runs the GPU sim.

    Examples:
        >>> import gymnasium as gym
        >>> import mani_skill.envs
        >>> from maniskill_torchrl.wrappers import CPUGymWrapper
        >>> env = CPUGymWrapper(gym.make("PickCube-v1", num_envs=1), record_metrics=True)
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, obs.dtype, type(info["elapsed_steps"])
        ((42,), dtype('float32'), <class 'int'>)
        >>> obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        >>> type(reward), type(terminated), info["episode"]["episode_len"]
        (<class 'float'>, <class 'bool'>, 1)
        >>> type(info["episode"]["return"])
        <class 'numpy.float32'>
        >>> env.close()
    """

    def __init__(
        self,
        env: gym.Env,
        ignore_terminations: bool = False,
        record_metrics: bool = False,
    ) -> None:
        base = require_maniskill_env(env, "CPUGymWrapper")
        if base.num_envs != 1:
            raise ValueError(
                f"CPUGymWrapper needs an env with num_envs=1, got num_envs={base.num_envs}. Make "
                "single envs (gym.make(..., num_envs=1)) and vectorise them with gymnasium's "
                "SyncVectorEnv / AsyncVectorEnv(context='forkserver'); for batched GPU envs keep "
                "the batched torch API (mani_skill.vector.wrappers.gymnasium.ManiSkillVectorEnv)."
            )
        if base.gpu_sim_enabled:
            raise ValueError(
                "CPUGymWrapper needs an env on the CPU sim, got one on the GPU sim. Make it with "
                "gym.make(..., num_envs=1, sim_backend='physx_cpu')."
            )
        # The checks above replace ManiSkill's asserts, which now pass.
        super().__init__(env, ignore_terminations, record_metrics)
        self._stats: EpisodeStats | None = None
        self._running: dict[str, np.ndarray] | None = None  # the running metrics (None: a fresh episode)
        self._layouts: dict[bool, list[tuple[str, bool]]] = {}

    @property
    def base_env(self) -> BaseEnv:
        """The ManiSkill ``BaseEnv`` (``env.unwrapped``)."""
        return self.env.unwrapped

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(to_numpy(action))
        out_info = {k: np_unbatch(v) for k, v in info.items()}
        if self.record_metrics:
            out_info["episode"] = self._episode(reward, info)
        return (
            np_unbatch(obs),
            np_unbatch(reward),
            False if self.ignore_terminations else np_unbatch(terminated),
            np_unbatch(truncated),
            out_info,
        )

    def _episode(self, reward: Any, info: dict) -> dict[str, Any]:
        stats = self._stats
        if stats is None:
            stats = self._stats = EpisodeStats(
                (1,),
                has_success="success" in info,
                has_fail="fail" in info,
                summation="numpy",
                native_return=True,  # ManiSkill's np.sum of the task's own rewards
                arrays="numpy",  # as ManiSkill's wrapper: numpy in, numpy out, no tensor op
            )
            self._layouts = {ignore: _gym_layout(stats.fields, ignore) for ignore in (False, True)}
        ep = self._running = stats.update(
            self._running, _array(reward), _array(info.get("success")), _array(info.get("fail"))
        )
        # Key order and python / numpy types as ManiSkill's CPUGymWrapper.
        return {
            name: ep[name][0] if as_numpy else ep[name].item()
            for name, as_numpy in self._layouts[bool(self.ignore_terminations)]
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        self._running = None
        return np_unbatch(obs), np_unbatch(info)

    def render(self) -> np.ndarray | Any | None:
        """The env's frame(s) as unbatched numpy images for ``rgb_array`` / ``sensors`` / ``all``.

        Other render modes (``human``) return ``None``, as ManiSkill's wrapper does.
        """
        ret = self.env.render()
        if self.render_mode in _IMAGE_RENDER_MODES:
            return np_unbatch(ret)
        return None
