"""A TorchRL collector that drives an :class:`~torchrl.envs.AsyncEnvPool` in ready batches.

:class:`AsyncPoolCollector` keeps every env of the pool busy: it waits for the envs that are
done (at least ``min_get``), runs the policy on their next roots and sends their actions back,
then does its bookkeeping while the envs step. The critical path is read, policy, write; no env
waits for the slowest. It is the loop of TorchRL's ``AsyncBatchedCollector`` over a pool given
as is, with the policy in this process: ``AsyncBatchedCollector`` makes its own pool from env
factories and cannot take a :class:`~maniskill_torchrl.ManiSkillAsyncEnvPool`.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.collectors import BaseCollector
from torchrl.envs import AsyncEnvPool
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["AsyncPoolCollector"]


class AsyncPoolCollector(BaseCollector):
    """Collects transitions from an :class:`~torchrl.envs.AsyncEnvPool` as its envs finish, out of lockstep.

    Args:
        env (AsyncEnvPool): the pool, e.g. a :class:`~maniskill_torchrl.ManiSkillAsyncEnvPool`
            (TorchRL's own pools work too).
        policy (Callable[[TensorDictBase], TensorDictBase], optional): reads the roots of the envs
            received (batch ``[k]``, ``k`` varies) and writes ``"action"``. None: random actions
            from the pool's action spec.

    Keyword Args:
        frames_per_batch (int): transitions per yielded batch.
        total_frames (int): transitions in all, -1 for no end. Defaults to -1.
        min_get (int): the envs to wait for before the policy runs (1: each env is sent its
            next action as soon as it is done; ``num_envs``: lockstep). Defaults to 1.
        exploration_type (ExplorationType): the policy's exploration mode. Defaults to
            ``ExplorationType.RANDOM``.

    Each yielded batch is ``[frames_per_batch]`` transitions (the root, ``"action"``,
    ``"next"`` and ``"env_index"``) in the order they finished, not ``[N, T]``: the envs'
    steps are out of lockstep. The transitions of one env keep their order; select them with
    ``batch[batch["env_index"] == i]``. A trajectory ends where ``("next", "done")`` is True;
    the env's next transition starts its next episode (the pool resets it at once).

    Examples:
        >>> from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool
        >>> pool = ManiSkillAsyncEnvPool("PickCube-v1", 2, obs_mode="state")
        >>> collector = AsyncPoolCollector(pool, frames_per_batch=20, total_frames=40)
        >>> [batch.shape for batch in collector]
        [torch.Size([20]), torch.Size([20])]
        >>> collector.shutdown()
    """

    def __init__(
        self,
        env: AsyncEnvPool,
        policy: Callable[[TensorDictBase], TensorDictBase] | None = None,
        *,
        frames_per_batch: int,
        total_frames: int = -1,
        min_get: int = 1,
        exploration_type: ExplorationType = ExplorationType.RANDOM,
    ) -> None:
        super().__init__()
        if not isinstance(env, AsyncEnvPool):
            raise TypeError(
                f"AsyncPoolCollector drives an AsyncEnvPool (e.g. ManiSkillAsyncEnvPool), got {type(env).__name__}: "
                "for a lockstep env use torchrl.collectors.Collector."
            )
        if frames_per_batch < 1:
            raise ValueError(f"frames_per_batch must be a positive int, got {frames_per_batch!r}.")
        if not 1 <= min_get <= env.num_envs:
            raise ValueError(f"min_get must be in [1, num_envs={env.num_envs}], got {min_get!r}.")
        self.env = env
        self.policy = policy
        self.frames_per_batch = self.requested_frames_per_batch = int(frames_per_batch)
        self.total_frames = int(total_frames)
        self.min_get = int(min_get)
        self.exploration_type = exploration_type
        self.trajs_per_batch = None
        self._frames = 0
        # policy=None: random actions, drawn from the leaf spec (a Composite's rand builds a TensorDict)
        self._actions = None
        if policy is None:
            self._actions = [(key, env.full_action_spec_unbatched[key]) for key in env.action_keys]

    def _act(self, roots: TensorDictBase) -> None:
        """The policy's actions for ``roots``, sent to their envs."""
        if self._actions is None:
            with torch.no_grad(), set_exploration_type(self.exploration_type):
                roots = self.policy(roots)
        else:
            for key, spec in self._actions:
                roots.set(key, spec.rand(roots.shape))
        self.env.async_step_and_maybe_reset_send(roots, env_index=roots["env_index"].tolist())

    def iterator(self) -> Iterator[TensorDictBase]:
        pool = self.env
        everyone = list(range(pool.num_envs))
        pool.async_reset_send(env_index=everyone)
        self._act(pool.async_reset_recv(min_get=pool.num_envs))
        chunks: list[TensorDictBase] = []
        held = 0
        try:
            while self.total_frames < 0 or self._frames < self.total_frames:
                transitions, roots = pool.async_step_and_maybe_reset_recv(min_get=self.min_get)
                self._act(roots)  # the envs step again while this process does the rest
                chunks.append(transitions)
                held += transitions.shape[0]
                while held >= self.frames_per_batch:
                    batch = torch.cat(chunks) if len(chunks) > 1 else chunks[0]
                    out, rest = batch[: self.frames_per_batch], batch[self.frames_per_batch :]
                    chunks, held = ([rest] if rest.shape[0] else []), rest.shape[0]
                    self._frames += out.shape[0]
                    yield out
                    if 0 <= self.total_frames <= self._frames:
                        return
        finally:
            self._drain()

    def _drain(self) -> None:
        """Receives the steps still under way, so that the pool can reset or step in lockstep."""
        pool = self.env
        pending = getattr(pool, "_current_step_reset", 0)  # TorchRL's pools count them there
        if pending:
            pool.async_step_and_maybe_reset_recv(min_get=pending)

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        return self.env.set_seed(seed, static_seed=static_seed)

    def state_dict(self) -> OrderedDict:
        return OrderedDict(frames=self._frames)

    def load_state_dict(self, state_dict: OrderedDict) -> None:
        self._frames = int(state_dict.get("frames", 0))

    def shutdown(self, timeout: float | None = None, close_env: bool = True, raise_on_error: bool = True) -> None:
        if close_env:
            self.env.close(raise_if_closed=False)

    def __repr__(self) -> str:
        return (
            f"AsyncPoolCollector({self.env!r}, frames_per_batch={self.frames_per_batch}, "
            f"total_frames={self.total_frames}, min_get={self.min_get})"
        )

    def __getstate__(self) -> Any:
        raise TypeError("AsyncPoolCollector drives live worker processes and cannot be pickled.")
