"""The masked merge of inner steps on TensorDicts, behind the ``ActionRepeat`` transform.

An env that has ended keeps its last real step; reward is summed and done flags
OR'ed over the inner steps it really took. The rule per tensor is
:func:`~maniskill_torchrl._repeat.keep_where`, which the gym shim and the CPU engine's
workers use on ManiSkill's dicts.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase

from maniskill_torchrl._private import entries, fast_apply, has_names, new_tensordict
from maniskill_torchrl._repeat import keep_where

__all__ = ["any_done", "merge_step"]


def any_done(td: TensorDictBase, done_keys: Sequence[NestedKey]) -> torch.Tensor:
    """Per env of ``td.batch_size``: True where any done entry (at any depth, any agent) is True."""
    out = None
    ndim = td.batch_dims
    for key in done_keys:
        val = td.get(key)
        if val.ndim > ndim:
            val = val.reshape(*val.shape[:ndim], -1).any(-1)
        out = val if out is None else out | val
    return out


def merge_step(
    acc: TensorDictBase,
    new: TensorDictBase,
    running: torch.Tensor | None,
    reward_keys: Sequence[NestedKey],
    done_keys: Sequence[NestedKey],
) -> TensorDictBase:
    """Folds one inner step ``new`` into the data accumulated so far, ``acc``.

    For the envs where ``running`` is True (those that really took this step):
    reward entries are summed, done entries OR'ed and every other entry taken
    from ``new``. The other envs keep ``acc`` untouched: nothing from after
    their episode's end leaks in. ``running=None`` means every env ran.

    Returns a new TensorDict; neither input is modified.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from maniskill_torchrl._masked_merge import merge_step
        >>> acc = TensorDict(reward=torch.ones(2, 1), done=torch.tensor([[True], [False]]),
        ...                  obs=torch.zeros(2, 3), batch_size=[2])
        >>> new = TensorDict(reward=torch.ones(2, 1), done=torch.tensor([[False], [True]]),
        ...                  obs=torch.ones(2, 3), batch_size=[2])
        >>> out = merge_step(acc, new, ~acc["done"].squeeze(-1), ["reward"], ["done"])
        >>> out["reward"].squeeze(-1).tolist(), out["obs"][:, 0].tolist()
        ([1.0, 2.0], [0.0, 1.0])
    """
    if _top_level_only(new, reward_keys, done_keys):
        # This runs once per inner step of an action repeat: build the output's top-level
        # dict directly (no copy of nested containers, no per-entry validation).
        source = entries(new).copy()
        for key in reward_keys:
            source[key] = acc.get(key) + new.get(key)
        for key in done_keys:
            source[key] = acc.get(key) | new.get(key)
        out = new_tensordict(source, batch_size=new.batch_size, device=new.device)
    else:
        out = new.copy()
        for key in reward_keys:
            out.set(key, acc.get(key) + new.get(key))
        for key in done_keys:
            out.set(key, acc.get(key) | new.get(key))
    if running is None:
        return out

    def where(x, y):
        return keep_where(running, x, y)

    # No batch_size here: it would flatten nested batch dims (multi-agent [B, n_agents] sub-tds).
    return fast_apply(out, where, acc, default=None, filter_empty=True)


def _top_level_only(td: TensorDictBase, *key_lists: Sequence[NestedKey]) -> bool:
    """Whether ``td`` is a plain TensorDict and every key to set on its copy is top-level."""
    return type(td) is TensorDict and not has_names(td) and all(isinstance(k, str) for keys in key_lists for k in keys)
