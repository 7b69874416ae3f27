"""Masked action repeat as a TorchRL transform.

:class:`ActionRepeat` folds its inner steps with :func:`merge_step`: an env that has ended keeps
its last real step; reward is summed and done flags OR'ed over the inner steps it really took.
The rule per tensor is :func:`~maniskill_torchrl._internal.repeat.keep_where`, which the gym shim
and the CPU engine's workers use on ManiSkill's dicts.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torchrl.envs import Compose, EnvBase, Transform, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase

from maniskill_torchrl._internal.repeat import check_repeat, keep_where
from maniskill_torchrl._private import complete_done, entries, env_step, fast_apply, has_names, new_tensordict
from maniskill_torchrl.envs.hooks import EnvHooks, env_hooks

__all__ = ["ActionRepeat", "any_done", "merge_step"]


class ActionRepeat(Transform):
    """Repeats each action up to ``repeat`` times, per env, never past an episode's end.

    Per outer step the parent env (the env with the transforms placed before
    this one) is stepped up to ``repeat`` times with the same action. For each
    env of the batch:

    - every reward entry is the sum over the inner steps the env really took;
    - ``terminated`` / ``truncated`` / ``done`` (every done entry) are OR'ed;
    - every other ``"next"`` entry (observations at any depth, infos such as
      ``success`` / ``elapsed_steps``) comes from its last real inner step: an
      env that ends at inner step ``k`` keeps step ``k``'s data.

    The inner loop stops as soon as every env is done. Reward and done entries
    are the parent's ``reward_keys`` / ``done_keys``, nested and multi-agent
    ones included; an env has ended when any of its ``"done"`` entries (at any
    level, for any agent) is True.

    Envs that have ended are not stepped again where the parent can skip them:

    - on the batched CPU env (``ManiSkillEnv(env_id, num_envs=N)`` on the CPU
      sim, a :class:`~maniskill_torchrl.ManiSkillWrapper` of a
      :class:`~maniskill_torchrl.CPUVectorEnv`), when this transform
      sits directly on it (no transform before this one), the repeat runs inside
      each sub-env's process (ManiSkill's ``ActionRepeatWrapper`` per sub-env):
      one round trip per outer step, each sub-env stops at its own episode's end;
    - on a :class:`~torchrl.envs.SerialEnv` / :class:`~torchrl.envs.ParallelEnv`
      the extra inner steps carry TorchRL's ``"_step"`` partial-step mask, so a
      ``ParallelEnv`` of CPU ManiSkill envs spends no physics on finished envs.
      Placed inside each worker instead (``ParallelEnv(n, lambda:
      TransformedEnv(ManiSkillEnv(...), Compose(CPUUnbatch(), ActionRepeat(k))))``)
      every worker stops on its own.

    One batch-locked simulator (ManiSkill's GPU sim, or the batched CPU env with
    transforms before this one) steps all its envs together; the results of the
    finished ones are discarded, as ManiSkill's ``ActionRepeatWrapper`` does.
    The results are the same bits on every path.

    Specs are unchanged. Transforms placed before this one act on every inner
    step (a :class:`~torchrl.envs.StepCounter` there counts inner steps: state
    entries of the parent's ``full_state_spec`` are carried from one inner step
    to the next); transforms placed after it see one outer step.

    Unlike :class:`~torchrl.envs.FrameSkipTransform`, this transform neither
    adds rewards from after an episode's end nor loses a termination that
    happens mid-repeat, and the parent's own inverse transforms are applied
    once per outer step, not once more per inner step. Like it, it only works
    inside a :class:`~torchrl.envs.TransformedEnv`: :meth:`forward` raises.

    Args:
        repeat (int): inner steps per outer step, ``>= 1``. ``repeat=1`` is a
            plain step.

    Raises:
        TypeError: ``repeat`` is not an int.
        ValueError: ``repeat < 1``.

    Examples:
        >>> from torchrl.envs import Compose, StepCounter, TransformedEnv
        >>> from maniskill_torchrl import ManiSkillEnv
        >>> from maniskill_torchrl.transforms import ActionRepeat
        >>> env = TransformedEnv(
        ...     ManiSkillEnv("PickCube-v1", obs_mode="state"),
        ...     Compose(ActionRepeat(3), StepCounter()),  # the StepCounter counts outer steps
        ... )
        >>> _ = env.set_seed(0)
        >>> td = env.rollout(4)
        >>> td["next", "elapsed_steps"].squeeze(0).tolist()  # inner steps taken
        [3, 6, 9, 12]
        >>> td["next", "step_count"].squeeze(-1).squeeze(0).tolist()
        [1, 2, 3, 4]
    """

    def __init__(self, repeat: int) -> None:
        repeat = check_repeat(repeat)
        super().__init__()
        self.repeat = repeat
        self._cache: _ParentInfo | None = None
        self._delegated = False  # this step's repeat was handed to the parent's CPU workers

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Raises: the transform steps its parent env, and a tensordict alone has none."""
        raise RuntimeError(
            "ActionRepeat steps the env it is appended to, so it can only be used inside a "
            "TransformedEnv, as TorchRL's FrameSkipTransform: "
            "TransformedEnv(env, ActionRepeat(repeat)). Called on a tensordict alone it would "
            "return it unchanged."
        )

    # ------------------------------------------------------------- internals
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # The last hook before the parent steps. Nothing of ``tensordict`` is kept.
        self._begin_step(tensordict)
        return tensordict

    def _begin_step(self, tensordict: TensorDictBase) -> None:
        """Before each step of the parent: where its CPU workers can repeat this step
        themselves, asks them now (a later ActionRepeat calls it before each of its inner
        steps, which skip the inverse pass)."""
        self._delegated = False
        if self.repeat > 1 and self.parent is not None:
            self._delegate(tensordict)

    def _delegate(self, tensordict: TensorDictBase) -> bool:
        """Asks the parent's CPU workers to repeat this step themselves, where they can.

        The request holds for the next parent step only (the env drops it after that
        step), so a transform removed or moved leaves plain steps behind and no step is
        repeated twice. Not with an outer partial step (a ``"_step"`` mask that is not all
        True): the inner loop keeps the envs it skips as they were.
        """
        workers = self._parent_info().workers
        if workers is None:
            return False
        outer_mask = tensordict.get("_step", None)
        if outer_mask is not None and not bool(outer_mask.all()):
            return False
        self._delegated = workers.request_worker_repeat(self.repeat)
        return self._delegated

    def _parent_info(self) -> _ParentInfo:
        """What the inner loop needs to know about the parent, cached per parent."""
        parent = self.parent
        info = self._cache
        if info is not None and info.parent is parent:
            return info
        if parent is None:
            raise RuntimeError("ActionRepeat must be used inside a TransformedEnv.")
        info = self._cache = _ParentInfo(parent)
        return info

    def empty_cache(self) -> None:
        self._cache = None
        super().empty_cache()

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self.repeat == 1:
            return next_tensordict
        if self._delegated:  # the sub-envs repeated it: one outer step already
            self._delegated = False
            return next_tensordict
        # ``tensordict`` is the step's input after every inverse transform, the parent's own
        # included: the inner steps go to the parent's base env with it, then through the
        # parent's transforms' forward pass (parent._step would apply their inverses again).
        # A shallow copy: the inner loop sets "_step" and state entries on it.
        td = tensordict.exclude("next")
        info = self._parent_info()
        reward_keys, done_keys, stop_keys = info.reward_keys, info.done_keys, info.stop_keys

        running = ~any_done(next_tensordict, stop_keys)
        outer_mask = td.get("_step", None)
        if outer_mask is not None:  # an outer partial step: skipped envs stay skipped
            running = running & outer_mask.reshape(running.shape)
        n_envs = running.numel()
        acc = new = next_tensordict
        last = self.repeat - 1
        for i in range(1, self.repeat):
            # One host sync per inner step (ManiSkill's wrapper has two).
            n_running = int(running.sum())
            if n_running == 0:
                break
            all_running = n_running == n_envs
            if info.state_keys:  # e.g. a StepCounter placed before: the next inner step starts where this one ended
                td.update(new.select(*info.state_keys, strict=False))
            if info.partial:
                if all_running:
                    td.pop("_step", None)
                else:
                    td.set("_step", running)
            new = info.step(td)
            # All envs running: a plain fold, no masking at all.
            acc = merge_step(acc, new, None if all_running else running, reward_keys, done_keys)
            if i < last:
                running = running & ~any_done(new, stop_keys)
        return acc

    def __repr__(self) -> str:
        return f"{type(self).__name__}(repeat={self.repeat})"


class _ParentInfo:
    """The parent's keys and how to step it, computed once per parent."""

    __slots__ = (
        "parent",
        "reward_keys",
        "done_keys",
        "stop_keys",
        "state_keys",
        "partial",
        "workers",
        "_base",
        "_transform",
        "_repeats",
        "_complete",
    )

    def __init__(self, parent: TransformedEnv) -> None:
        self.parent = parent
        self.reward_keys = list(parent.reward_keys)
        self.done_keys = list(parent.done_keys)
        # An env ends when a "done" entry is set (TorchRL keeps done = terminated | truncated at
        # every level); fall back to every done entry where no key is named "done".
        self.stop_keys = [k for k in self.done_keys if (k if isinstance(k, str) else k[-1]) == "done"] or self.done_keys
        self.state_keys = list(parent.full_state_spec.keys(True, True))
        base: EnvBase = parent
        while isinstance(base, TransformedEnv):
            base = base.base_env
        self.partial = isinstance(base, BatchedEnvBase)
        transform = parent.transform
        empty = isinstance(transform, Compose) and len(transform) == 0
        # The transforms before this one: their forward pass runs on every inner step (their
        # inverses ran once, before the outer step). None where there are none.
        self._transform = None if empty else transform
        # The ActionRepeats among them ask for the workers' repeat in their inverse pass, which
        # inner steps skip: they are asked before each inner step instead.
        earlier = transform if isinstance(transform, Compose) else [transform]
        self._repeats = [] if empty else [t for t in earlier if isinstance(t, ActionRepeat)]
        self._base = parent.base_env
        # Directly on an env that may have its CPU workers repeat actions themselves (the
        # EnvHooks protocol's request_worker_repeat, which says whether they will): no transform
        # between would see the inner steps.
        self.workers: EnvHooks | None = env_hooks(parent) if empty else None
        self._complete: bool | None = None

    def step(self, td: TensorDictBase) -> TensorDictBase:
        """One inner step of the parent with ``td``, whose inverse transforms were applied:
        what ``parent._step`` does after its inverse pass."""
        base = self._base
        for repeat in self._repeats:
            repeat._begin_step(td)
        out = env_step(base, td)
        complete = self._complete
        if complete is None:  # fill missing done entries as TransformedEnv does, if this env needs it
            keys = set(out.keys(True, True))
            complete = self._complete = all(k in keys for k in base.done_keys)
        if not complete:
            complete_done(base, out)
        transform = self._transform
        return out if transform is None else transform._step(td, out)


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
        >>> from maniskill_torchrl.transforms.action_repeat import merge_step
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
