"""Masked action repeat as a TorchRL transform."""

from __future__ import annotations

from tensordict import TensorDictBase
from torchrl.envs import Compose, EnvBase, Transform, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase

from maniskill_torchrl._private import complete_done, env_step
from maniskill_torchrl.masked_merge import any_done, check_repeat, merge_step

__all__ = ["ActionRepeat"]


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
    on a :class:`~torchrl.envs.SerialEnv` / :class:`~torchrl.envs.ParallelEnv`
    the extra inner steps carry TorchRL's ``"_step"`` partial-step mask, so a
    ``ParallelEnv`` of CPU ManiSkill envs spends no physics on finished envs.
    One batch-locked simulator (:class:`~maniskill_torchrl.ManiSkillWrapper`,
    ManiSkill's GPU sim) steps all its envs together; the results of the
    finished ones are discarded, as ManiSkill's ``ActionRepeatWrapper`` does.
    Placed inside each worker instead (``ParallelEnv(n, lambda:
    TransformedEnv(ManiSkillEnv(...), Compose(CPUUnbatch(), ActionRepeat(k))))``)
    every worker stops on its own.

    Specs are unchanged. Transforms placed before this one act on every inner
    step (a :class:`~torchrl.envs.StepCounter` there counts inner steps: state
    entries of the parent's ``full_state_spec`` are carried from one inner step
    to the next); transforms placed after it see one outer step.

    Unlike :class:`~torchrl.envs.FrameSkipTransform`, this transform neither
    adds rewards from after an episode's end nor loses a termination that
    happens mid-repeat, and it steps the parent with the input as this
    transform sees it (the parent's own inverse transforms are applied once).

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
        self._stash: TensorDictBase | None = None
        self._cache: _ParentInfo | None = None

    # ------------------------------------------------------------- internals
    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Why: the ``tensordict`` handed to ``_step`` has been through the inverse of
        # every transform, the parent's own included; stepping the parent with it
        # would apply those a second time. Compose runs inverses last to first, so
        # here only the later transforms' inverses were applied: keep this view (a
        # shallow copy, as the earlier inverses set entries on the same object).
        if self.repeat > 1:
            self._stash = tensordict.exclude("next")
        return tensordict

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
        td, self._stash = self._stash, None
        if td is None:  # _step called without the TransformedEnv's inverse pass
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

    __slots__ = ("parent", "reward_keys", "done_keys", "stop_keys", "state_keys", "partial", "_base", "_complete")

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
        # Why: with no transform before this one, parent._step is base_env._step wrapped in an
        # identity inverse (a clone) and an identity forward pass: call the base env directly.
        self._base = parent.base_env if empty else None
        self._complete: bool | None = None

    def step(self, td: TensorDictBase) -> TensorDictBase:
        base = self._base
        if base is None:
            return env_step(self.parent, td)
        out = env_step(base, td)
        complete = self._complete
        if complete is None:  # fill missing done entries as TransformedEnv does, if this env needs it
            keys = set(out.keys(True, True))
            complete = self._complete = all(k in keys for k in self.done_keys)
        if not complete:
            complete_done(base, out)
        return out
