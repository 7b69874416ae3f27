"""The CPU workers' action repeat of :class:`~maniskill_torchrl.ManiSkillWrapper`: the fast path of
:class:`~maniskill_torchrl.transforms.ActionRepeat` on a :class:`~maniskill_torchrl.CPUVectorEnv`,
whose sub-envs then repeat each action in their own processes (one round trip per outer step, no
step after an episode's end).

ManiSkill steps all of its envs together (the GPU sim, and the sub-envs of a ``CPUVectorEnv``,
which it steps all at once), so the wrapper does not honour a ``"_step"`` mask. Placed directly on
a ``CPUVectorEnv`` one, ``ActionRepeat`` instead has the sub-envs repeat each action themselves
(:meth:`ManiSkillWrapper.request_worker_repeat <maniskill_torchrl.ManiSkillWrapper.request_worker_repeat>`,
then :meth:`CPUVectorEnv.set_repeat <maniskill_torchrl.CPUVectorEnv.set_repeat>`): one round trip
per step, and a sub-env whose episode ends mid-repeat is not stepped further.

No engine is imported: an engine that can repeat declares ``repeats_actions = True``.
"""

from __future__ import annotations

from typing import Any

__all__ = ["WorkerRepeat"]


class WorkerRepeat:
    """The wrapper's side of the workers' repeat (mixed into it): a request for the next step, and
    the repeat each step runs with. Only an engine that declares ``repeats_actions`` (a
    :class:`~maniskill_torchrl.CPUVectorEnv`), wrapped as is, has workers."""

    def _init_worker_repeat(self, env: Any, base: Any) -> None:
        # Each step runs with the repeat asked for it, else with the one the env had when wrapped.
        self._workers = base if env is base and getattr(base, "repeats_actions", False) else None
        self._plain_repeat = base.repeat if self._workers is not None else 1
        self._next_repeat = 0  # 0: no request for the next step

    def request_worker_repeat(self, repeat: int) -> bool:
        """Has the next step apply its action up to ``repeat`` times inside the CPU sub-envs.

        :class:`~maniskill_torchrl.transforms.ActionRepeat`'s fast path. Only a
        :class:`~maniskill_torchrl.CPUVectorEnv` wrapped as is (with no repeat of its own) can:
        returns whether it will, False otherwise. The request holds for the next step only; any
        step asked for without one runs with the env's own repeat again, so a removed transform
        leaves plain steps.
        """
        if self._workers is None or self._plain_repeat != 1:
            return False
        self._next_repeat = repeat
        return True

    def _set_worker_repeat(self) -> None:
        """Before a step on the workers: the repeat asked for this step, else the env's own."""
        repeat = self._next_repeat
        if repeat:  # taken first, so that a failing step leaves no request behind
            self._next_repeat = 0
        else:  # no write: an nn.Module attribute write costs more than the rest of this block
            repeat = self._plain_repeat
        if self._workers.repeat != repeat:  # a round trip, only when the repeat changes
            self._workers.set_repeat(repeat)
