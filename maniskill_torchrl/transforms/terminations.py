"""Run every episode to its time limit: terminations are dropped."""

from __future__ import annotations

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs import Transform

__all__ = ["IgnoreTerminations"]


def _last(key: NestedKey) -> str:
    return key if isinstance(key, str) else key[-1]


class IgnoreTerminations(Transform):
    """Forces ``terminated`` to False and sets ``done`` to ``truncated``.

    Episodes then run until truncation (ManiSkill's time limit), as with
    ``CPUGymWrapper(env, ignore_terminations=True)``: a task that terminates
    early on success or failure (``MS-CartpoleBalance-v1`` on ``fail``) keeps
    running, and its ``success`` / ``fail`` entries keep being reported.
    Specs are unchanged.

    Every group of done entries of the parent is handled, at the root and
    nested (multi-agent ``("agents", "terminated")`` ...): within a group,
    ``terminated`` becomes all False and ``done`` a copy of the group's
    ``truncated`` (all False where the group has none).

    Examples:
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import CPUUnbatch, IgnoreTerminations
        >>> env = TransformedEnv(
        ...     ManiSkillEnv("MS-CartpoleBalance-v1", obs_mode="state", max_episode_steps=50),
        ...     Compose(CPUUnbatch(), IgnoreTerminations()),
        ... )
        >>> _ = env.set_seed(0)
        >>> td = env.rollout(100, break_when_any_done=True)  # stops at the time limit only
        >>> td.shape, bool(td["next", "terminated"].any()), bool(td["next", "truncated"][-1])
        (torch.Size([50]), False, True)
    """

    def __init__(self) -> None:
        super().__init__()

    @property
    def _groups(self) -> list[tuple[NestedKey | None, NestedKey | None, NestedKey | None]]:
        """(terminated, truncated, done) keys per done group of the parent, computed once."""
        groups = self.__dict__.get("_groups_val")
        if groups is None:
            parent = self.parent
            key_groups = parent.done_keys_groups if parent is not None else [["done", "terminated", "truncated"]]
            groups = []
            for group in key_groups:
                by_name = {_last(k): k for k in group}
                groups.append((by_name.get("terminated"), by_name.get("truncated"), by_name.get("done")))
            self.__dict__["_groups_val"] = groups
        return groups

    def set_container(self, container) -> None:
        super().set_container(container)
        self.__dict__.pop("_groups_val", None)

    def empty_cache(self) -> None:
        self.__dict__.pop("_groups_val", None)
        super().empty_cache()

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        for term_key, trunc_key, done_key in self._groups:
            term = next_tensordict.get(term_key, None) if term_key is not None else None
            if term is not None:
                next_tensordict.set(term_key, torch.zeros_like(term))
            if done_key is None:
                continue
            trunc = next_tensordict.get(trunc_key, None) if trunc_key is not None else None
            if trunc is not None:
                # A copy, not the same tensor under two keys: in-place writes to one must not hit the other.
                next_tensordict.set(done_key, trunc.clone())
            else:
                done = next_tensordict.get(done_key, None)
                if done is not None:
                    next_tensordict.set(done_key, torch.zeros_like(done))
        return next_tensordict

    forward = _call

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # Same rule at reset (envs built with allow_done_after_reset may report done there).
        return self._call(tensordict_reset)

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
