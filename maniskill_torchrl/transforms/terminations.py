"""Drop terminations: run every episode to its time limit, or end it there as a truncation."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from torchrl.envs import EnvBase, Transform

__all__ = ["IgnoreTerminations"]

# (terminated, truncated, done) keys of one group of done entries.
_Group = tuple[NestedKey, NestedKey, NestedKey]


def _sibling(key: NestedKey, name: str) -> NestedKey:
    """``key`` with its last element replaced by ``name``."""
    return name if isinstance(key, str) else unravel_key((*key[:-1], name))


def _last(key: NestedKey) -> str:
    return key if isinstance(key, str) else key[-1]


class IgnoreTerminations(Transform):
    """Forces ``terminated`` to False and sets ``done`` to ``truncated``.

    Episodes then run until truncation (ManiSkill's time limit), as with
    ``CPUGymWrapper(env, ignore_terminations=True)``: a task that terminates
    early on success or failure (``MS-CartpoleBalance-v1`` on ``fail``) keeps
    running, and its ``success`` / ``fail`` entries keep being reported.
    Specs are unchanged.

    Each terminated key names a group of done entries, at the root or nested
    (multi-agent ``("agents", "terminated")`` ...): within a group,
    ``terminated`` becomes all False and its sibling ``done`` a copy of its
    sibling ``truncated`` (all False where the group has none).

    On stored data (a replay buffer's transform, which runs :meth:`forward` on
    each sample) the root flags and those under ``"next"`` are both rewritten:
    ``("next", "terminated")`` / ``("next", "done")`` are the ones that end a
    transition.

    With ``as_truncations=True`` a termination still ends its episode but as a
    truncation: ``terminated`` becomes all False, ``truncated`` takes its True
    entries and ``done`` is unchanged, so the env resets there as before while
    value estimators (TorchRL's ``GAE``, the SAC losses) bootstrap from the
    final observation at every done. This is ManiSkill's PPO baseline's
    ``bootstrap_at_done="always"`` with partial resets: a success termination
    must not look like the end of all future reward, or the policy learns to
    hover short of success.

    Args:
        in_keys (sequence of NestedKey, optional): the terminated entries to
            clear, one per group. Defaults to every terminated key of the parent
            env (``"terminated"`` where there is no env).
        as_truncations (bool, optional): end the episode at a termination, as a
            truncation, instead of running it to the time limit. Defaults to
            ``False``.

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

    def __init__(self, in_keys: Sequence[NestedKey] | None = None, *, as_truncations: bool = False) -> None:
        super().__init__(in_keys=in_keys)
        self.as_truncations = as_truncations
        # The groups of in_keys, computed on first use and dropped with the parent.
        self._groups: list[_Group] | None = None

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = Transform.in_keys.fget(self)
        if keys:
            return keys
        # Not given: the parent's terminated keys, as RewardSum takes the parent's reward keys.
        parent = self.parent
        if parent is None:
            return ["terminated"]
        return [key for key in parent.done_keys if _last(key) == "terminated"]

    @in_keys.setter
    def in_keys(self, value: Sequence[NestedKey] | NestedKey | None) -> None:
        Transform.in_keys.fset(self, value)
        self._groups = None

    def _group_keys(self) -> list[_Group]:
        groups = self._groups
        if groups is None:
            groups = [(key, _sibling(key, "truncated"), _sibling(key, "done")) for key in self.in_keys]
            # Without a parent the keys may differ from one tensordict to the next: no cache.
            if self.parent is not None:
                self._groups = groups
        return groups

    def set_container(self, container: Transform | EnvBase) -> None:
        super().set_container(container)
        self._groups = None

    def empty_cache(self) -> None:
        self._groups = None
        super().empty_cache()

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        for term_key, trunc_key, done_key in self._group_keys():
            term = next_tensordict.get(term_key, None)
            if term is not None:
                next_tensordict.set(term_key, torch.zeros_like(term))
            trunc = next_tensordict.get(trunc_key, None)
            if self.as_truncations:
                if term is not None and trunc is not None:  # done unchanged: it is still terminated | truncated
                    next_tensordict.set(trunc_key, trunc | term)
                continue
            if trunc is not None:
                # A copy, not the same tensor under two keys: in-place writes to one must not hit the other.
                next_tensordict.set(done_key, trunc.clone())
            else:
                done = next_tensordict.get(done_key, None)
                if done is not None:
                    next_tensordict.set(done_key, torch.zeros_like(done))
        return next_tensordict

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The rule on stored data: the root flags and the ``"next"`` ones."""
        self._call(tensordict)
        next_tensordict = tensordict.get("next", None)
        if next_tensordict is not None:
            tensordict.set("next", self._call(next_tensordict))
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        # Same rule at reset (envs built with allow_done_after_reset may report done there).
        return self._call(tensordict_reset)

    def __repr__(self) -> str:
        given = Transform.in_keys.fget(self)
        args = [f"in_keys={given}"] if given else []
        if self.as_truncations:
            args.append("as_truncations=True")
        return f"{type(self).__name__}({', '.join(args)})"
