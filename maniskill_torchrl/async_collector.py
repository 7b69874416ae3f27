"""A TorchRL collector that drives an :class:`~torchrl.envs.AsyncEnvPool` in ready batches.

:class:`AsyncPoolCollector` keeps every env of the pool busy: it waits for the envs that are
done (at least ``min_get``), runs the policy on their next roots and sends their actions back,
then does its bookkeeping while the envs step. The critical path is read, policy, write; no env
waits for the slowest. It is the loop of TorchRL's ``AsyncBatchedCollector`` over a pool given
as is, with the policy in this process: ``AsyncBatchedCollector`` makes its own pool from env
factories and cannot take a :class:`~maniskill_torchrl.ManiSkillAsyncEnvPool`.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.collectors import BaseCollector
from torchrl.data import Bounded, Composite
from torchrl.envs import AsyncEnvPool
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import RandomPolicy

from maniskill_torchrl.envs.async_pool import ManiSkillAsyncEnvPool

__all__ = ["AsyncPoolCollector"]

_TRAJ_IDS = ("collector", "traj_ids")


class AsyncPoolCollector(BaseCollector):
    """Collects transitions from an :class:`~torchrl.envs.AsyncEnvPool` as its envs finish, out of lockstep.

    Args:
        env (AsyncEnvPool): the pool, e.g. a :class:`~maniskill_torchrl.ManiSkillAsyncEnvPool`
            (TorchRL's own pools work too).
        policy (Callable[[TensorDictBase], TensorDictBase], optional): reads the roots of the envs
            received (batch ``[k]``, ``k`` varies) and writes ``"action"``. None, or a TorchRL
            :class:`~torchrl.modules.RandomPolicy` (whose spec may be the pool's batched one):
            random actions from the pool's action spec, one row per env received.

    Keyword Args:
        frames_per_batch (int): transitions per yielded batch.
        total_frames (int): transitions in all, -1 for no end. Defaults to -1.
        min_get (int): the envs to wait for before the policy runs (1: each env is sent its
            next action as soon as it is done; ``num_envs``: lockstep). Defaults to 1.
        exploration_type (ExplorationType): the policy's exploration mode. Defaults to
            ``ExplorationType.RANDOM``.

    Each yielded batch is ``[frames_per_batch]`` transitions (the root, ``"action"``,
    ``"next"``, ``"env_index"``, ``("collector", "traj_ids")`` and ``"step_count"`` /
    ``("next", "step_count")`` as TorchRL's ``StepCounter`` writes them), not ``[N, T]``: the
    envs' steps are out of lockstep, and a batch holds the transitions that finished first.
    Within it each trajectory's transitions lie side by side, in order, sorted by their
    ``("collector", "traj_ids")`` (TorchRL's collectors' key: ``split_trajectories`` and
    ``SliceSampler(traj_key=("collector", "traj_ids"))`` read it). A trajectory ends where
    ``("next", "done")`` is True; the env's next transition starts its next episode (the pool
    resets it at once) with a new id.

    Episodes carry on from one ``iter()`` to the next: the steps under way when an iteration
    stops are received and kept for the next batch, and nothing is dropped. If the pool was
    stepped or reset by another caller in between, every env restarts, and the last kept
    transition of each unfinished episode is marked ``("next", "truncated")``. An exception (in
    the policy, say) leaves the pool open and idle: the collector only closes it in
    :meth:`shutdown`.

    :meth:`cycle_stats` says where the main process spends each cycle (wait, policy, the rest).

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
        self.frames_per_batch = self.requested_frames_per_batch = int(frames_per_batch)
        self.total_frames = int(total_frames)
        self.min_get = int(min_get)
        self.exploration_type = exploration_type
        self.trajs_per_batch = None
        self._frames = 0
        # policy=None or a RandomPolicy: random actions, one row per env received, drawn from the
        # unbatched leaf specs (a Composite's rand builds a TensorDict; the pool's spec is [N, ...]).
        self._actions = None
        if policy is None or isinstance(policy, RandomPolicy):
            spec = env.full_action_spec if policy is None or policy.action_spec is None else policy.action_spec
            one = env.full_action_spec_unbatched
            if isinstance(spec, Composite):
                leaves = [(key, _unbatched(spec[key], one[key])) for key in env.action_keys]
            else:  # a RandomPolicy of one leaf spec writes its action_key
                key = policy.action_key
                leaves = [(key, _unbatched(spec, one[key]))]
            self._actions = [(key, _uniform(leaf)) for key, leaf in leaves]
            policy = None
        self.policy = policy
        n = env.num_envs
        # Per env: its trajectory id and the steps of its episode so far; the next new id.
        self._traj_ids = np.zeros(n, dtype=np.int64)  # set when the episodes start
        self._next_traj = 0
        self._step_count = np.zeros((n, 1), dtype=np.int64)
        self._marks: list[tuple[np.ndarray, np.ndarray]] = []  # per chunk received, not yet set
        # Between iterations: transitions received and not yet yielded, roots not yet acted on,
        # and the pool's count of foreign steps and resets when the episodes were last under way.
        self._kept: list[TensorDictBase] = []
        self._held: list[TensorDictBase] = []
        self._epoch: int | None = None
        self._running = False
        self._stats = {"cycles": 0, "wait": 0.0, "policy": 0.0, "total": 0.0}

    # ------------------------------------------------------------------ the cycle
    def _act(self, roots: TensorDictBase) -> None:
        """The policy's actions for ``roots``, sent to their envs."""
        if self._actions is None:
            with torch.no_grad(), set_exploration_type(self.exploration_type):
                roots = self.policy(roots)
        else:
            for key, draw in self._actions:
                roots.set(key, draw(roots.shape))
        index = roots.get("env_index")
        if not isinstance(self.env, ManiSkillAsyncEnvPool):  # TorchRL's pools take a list
            index = index.tolist()
        self.env.async_step_and_maybe_reset_send(roots, env_index=index)

    def _mark(self, transitions: TensorDictBase) -> TensorDictBase:
        """Trajectory ids and step counts of ``transitions``, then new ids for the envs whose
        episode ended; the entries are set on the whole batch at once (:meth:`_with_marks`)."""
        index = transitions.get("env_index").numpy()
        counts = self._step_count[index]
        self._marks.append((self._traj_ids[index], counts))
        done = transitions.get(("next", "done")).numpy().reshape(-1)
        self._step_count[index] = np.where(done[:, None], 0, counts + 1)
        if done.any():
            ended = index[done]
            self._traj_ids[ended] = np.arange(self._next_traj, self._next_traj + len(ended))
            self._next_traj += len(ended)
        return transitions

    def _split(self, chunks: list[TensorDictBase]) -> tuple[list[TensorDictBase], int, TensorDictBase]:
        """A batch of the first ``frames_per_batch`` transitions of ``chunks``, with their ids and step
        counts, each trajectory's transitions side by side and in order (what ``split_trajectories``
        and ``SliceSampler`` read); and the chunks and count left."""
        frames = self.frames_per_batch
        joined = torch.cat(chunks) if len(chunks) > 1 else chunks[0]
        ids, counts = self._joined_marks(len(chunks))
        rest = joined[frames:]
        if rest.shape[0]:  # its marks go back, set with its own batch
            self._marks.insert(0, (ids[frames:], counts[frames:]))
        out = joined[:frames]
        out.set(_TRAJ_IDS, torch.from_numpy(ids[:frames]))
        out.set("step_count", torch.from_numpy(counts[:frames]))
        out.set(("next", "step_count"), torch.from_numpy(counts[:frames] + 1))
        out = out[torch.argsort(out.get(_TRAJ_IDS), stable=True)]
        return ([rest] if rest.shape[0] else []), rest.shape[0], out

    def _joined_marks(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """The marks of the first ``count`` chunks, as one."""
        marks, self._marks = self._marks[:count], self._marks[count:]
        return np.concatenate([m[0] for m in marks]), np.concatenate([m[1] for m in marks])

    def _start(self) -> None:
        """Every env's episodes start (or go on from the last iteration, when nothing came between)."""
        pool = self.env
        resumed = self._running and getattr(pool, "_epoch", None) == self._epoch
        if not resumed:
            self._truncate_kept()
            self._held = []
            everyone = list(range(pool.num_envs))
            pool.async_reset_send(env_index=everyone)
            self._held = [pool.async_reset_recv(min_get=pool.num_envs)]
            self._step_count[:] = 0
            n = pool.num_envs
            self._traj_ids[:] = np.arange(self._next_traj, self._next_traj + n)
            self._next_traj += n
            self._epoch = getattr(pool, "_epoch", None)
            self._running = True
        if self._held:
            roots = torch.cat(self._held) if len(self._held) > 1 else self._held[0]
            self._held = []
            try:
                self._act(roots)
            except BaseException:
                self._held = [roots]
                raise

    def _truncate_kept(self) -> None:
        """The kept transitions' unfinished episodes end here: their last transition is truncated."""
        if not self._kept:
            return
        kept = torch.cat(self._kept) if len(self._kept) > 1 else self._kept[0]
        merged = self._joined_marks(len(self._kept))
        self._marks.insert(0, merged)
        index = kept["env_index"]
        last = torch.zeros(len(kept), dtype=torch.bool)
        for i in index.unique().tolist():
            last[(index == i).nonzero()[-1]] = True
        cut = last & ~kept["next", "done"].reshape(-1)
        kept["next", "truncated"][cut] = True
        kept["next", "done"][cut] = True
        self._kept = [kept]

    def iterator(self) -> Iterator[TensorDictBase]:
        pool = self.env
        stats = self._stats
        clock = time.perf_counter
        self._start()
        chunks, self._kept = self._kept, []
        held = sum(c.shape[0] for c in chunks)
        try:
            while self.total_frames < 0 or self._frames < self.total_frames:
                t0 = clock()
                transitions, roots = pool.async_step_and_maybe_reset_recv(min_get=self.min_get)
                t1 = clock()
                try:
                    self._act(roots)  # the envs step again while this process does the rest
                except BaseException:
                    self._held.append(roots)
                    raise
                finally:
                    t2 = clock()
                    self._mark(transitions)
                    chunks.append(transitions)
                    held += transitions.shape[0]
                batches = []
                while held >= self.frames_per_batch:
                    chunks, held, out = self._split(chunks)
                    batches.append(out)
                stats["cycles"] += 1
                stats["wait"] += t1 - t0
                stats["policy"] += t2 - t1
                stats["total"] += clock() - t0
                for out in batches:
                    self._frames += out.shape[0]
                    yield out
                    if 0 <= self.total_frames <= self._frames:
                        return
        finally:
            self._kept = chunks
            self._drain()

    def _drain(self) -> None:
        """Receives the steps still under way and keeps them (and their roots) for the next
        iteration, so that the pool is idle: it can reset, step in lockstep, or close."""
        pool = self.env
        pending = getattr(pool, "_current_step_reset", 0)  # TorchRL's pools count them there
        if pending:
            transitions, roots = pool.async_step_and_maybe_reset_recv(min_get=pending)
            self._mark(transitions)
            self._kept.append(transitions)
            self._held.append(roots)
        self._epoch = getattr(pool, "_epoch", None)

    def __iter__(self) -> Iterator[TensorDictBase]:
        # BaseCollector's shuts the collector (and closes the env) on an exception: the pool is the
        # user's, and stays open and idle (the iterator drains it).
        self._iteration_started = True
        yield from self.iterator()

    def cycle_stats(self, reset: bool = False) -> dict[str, float]:
        """Mean seconds per cycle (one receive, the policy, one send and the bookkeeping) in this
        process: ``wait`` (for the envs), ``policy``, ``other`` (the rest: the collector's and the
        pool's own work, the critical path's overhead), and ``cycles``."""
        s = self._stats
        n = max(s["cycles"], 1)
        out = {
            "cycles": s["cycles"],
            "wait": s["wait"] / n,
            "policy": s["policy"] / n,
            "other": (s["total"] - s["wait"] - s["policy"]) / n,
        }
        if reset:
            s.update(cycles=0, wait=0.0, policy=0.0, total=0.0)
        return out

    # ------------------------------------------------------------------ TorchRL's collector API
    def update_policy_weights_(
        self,
        policy_or_weights: TensorDictBase | nn.Module | dict | None = None,
        *,
        weights: TensorDictBase | dict | None = None,
        policy: nn.Module | None = None,
        **kwargs: Any,
    ) -> None:
        """The policy runs in this process and is the trained module itself: nothing to do unless
        other weights are given (a module, a TensorDict of parameters, or a ``state_dict``)."""
        given = next((w for w in (policy_or_weights, weights, policy) if w is not None), None)
        if given is None or given is self.policy:
            return
        if not isinstance(self.policy, nn.Module):
            raise TypeError(f"update_policy_weights_: the policy ({type(self.policy).__name__}) has no weights.")
        if isinstance(given, nn.Module):
            given = TensorDict.from_module(given)
        if isinstance(given, TensorDictBase):
            given.to_module(self.policy)
        else:
            self.policy.load_state_dict(given)

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        self._running = False  # new seeds: new episodes
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


def _uniform(spec: Any) -> Callable[[torch.Size], torch.Tensor]:
    """Draws of ``spec.rand(shape)``: for a continuous box, uniform in its bounds with the bounds kept
    once (``Bounded.rand`` re-derives them on every call, on the collector's critical path)."""
    if isinstance(spec, Bounded) and spec.dtype.is_floating_point:
        low, span = spec.space.low, spec.space.high - spec.space.low
        if torch.isfinite(span).all():
            return lambda shape: torch.rand(*shape, *spec.shape, dtype=spec.dtype).mul_(span).add_(low)
    return spec.rand


def _unbatched(spec: Any, one: Any) -> Any:
    """``spec`` for one env (``one``'s shape): the pool's ``[num_envs, ...]`` specs lose their first dim."""
    return spec if spec.shape == one.shape else spec[0]
