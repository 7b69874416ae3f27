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
import warnings
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
# Seconds the drain after Ctrl-C waits for the steps under way (a step takes milliseconds).
_INTERRUPTED_DRAIN_S = 10.0
_MARKS = (_TRAJ_IDS, "step_count", ("next", "step_count"))  # the collector's own entries


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
    ``shutdown()``. While an iterator is open, the pool's envs have steps under way and the pool
    is busy: exhaust or close the iterator before calling the pool yourself. Any pause between
    two batches is fine (the pool's watchdog counts only its own waits). Ctrl-C raises
    ``KeyboardInterrupt`` as is, after a drain of at most a few seconds: the pool is left idle
    for the user's handler, and the next iteration starts new episodes.

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
        self._step_count = np.zeros(n, dtype=np.int64)
        # The transitions received and not yet yielded, rows [0, cursor) of a buffer made on the first
        # receive; its entries as numpy views, for the pool's and the marks' copies. A receive brings
        # num_envs rows at most: before one, the cursor is below frames_per_batch, or (the drain
        # after a batch) below num_envs.
        self._buffer: TensorDictBase | None = None
        self._buffer_keys: frozenset = frozenset()
        self._arrays: dict = {}
        self._cursor = 0
        # Roots not acted on yet (after a drain, or a failing policy), and the pool's count of
        # foreign steps and resets when the episodes were last under way.
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

    def _receive(self, timeout: float | None = None) -> TensorDictBase:
        """Receives at least ``min_get`` transitions into the buffer at the cursor; returns the
        roots of those envs' next steps (``timeout``: seconds, then a ``TimeoutError``)."""
        pool, start = self.env, self._cursor
        if self._buffer is not None and start + pool.num_envs > len(self._buffer):
            self._grow(start + pool.num_envs)
        fast = getattr(pool, "_into", None) is not None and self._buffer is not None
        if fast:  # one numpy copy per entry, straight from the pool's rows (ManiSkillAsyncEnvPool)
            rows, done, roots = pool._recv_into(start, self.min_get, timeout)
        else:
            transitions, roots = pool.async_step_and_maybe_reset_recv(min_get=self.min_get, timeout=timeout)
            index = transitions.get("env_index")  # TorchRL's pools: python ints
            rows = np.asarray(index.tolist() if not isinstance(index, torch.Tensor) else index.numpy(), np.int64)
            transitions = transitions.exclude(*_MARKS, inplace=False)
            transitions.set("env_index", torch.from_numpy(rows))
            if self._buffer is None or frozenset(transitions.keys(True, True)) != self._buffer_keys:
                self._make_buffer(transitions)
            self._buffer[start : start + len(rows)] = transitions
            done = transitions.get(("next", "done")).numpy().reshape(-1)
        self._cursor = end = start + len(rows)
        self._mark(rows, done, start, end)
        if not fast and isinstance(pool, ManiSkillAsyncEnvPool):
            pool._plan_into({k: v for k, v in self._arrays.items() if k not in _MARKS})
        return roots

    def _make_buffer(self, example: TensorDictBase) -> None:
        """The buffer, laid out as ``example`` (a transition): on the first receive, and when the
        entries of the transitions change (a new policy); the kept transitions move into it."""
        n = self.env.num_envs
        rows = n + max(self.frames_per_batch, n)
        example = example[:1].exclude(*_MARKS, inplace=False)
        self._buffer_keys = frozenset(example.keys(True, True))
        example.set(_TRAJ_IDS, torch.zeros(1, dtype=torch.int64))
        example.set("step_count", torch.zeros(1, 1, dtype=torch.int64))
        example.set(("next", "step_count"), torch.zeros(1, 1, dtype=torch.int64))
        ours, theirs, kept = self._lay_out(example, rows)
        if kept and ours != theirs:
            warnings.warn(
                f"AsyncPoolCollector: the policy's entries changed with {kept} transitions kept from the last "
                f"iteration; in those, {sorted(theirs - ours, key=str)} are dropped and "
                f"{sorted(ours - theirs, key=str)} are zeros.",
                RuntimeWarning,
                stacklevel=5,
            )

    def _grow(self, rows: int) -> None:
        """A buffer of at least ``rows`` rows, the kept transitions moved in: iterations left early
        (a ``break`` after one batch) keep more than they yield, and nothing kept is dropped."""
        self._lay_out(self._buffer[:1], max(rows, 2 * len(self._buffer)))
        if isinstance(self.env, ManiSkillAsyncEnvPool):  # its plan wrote into the old buffer
            self.env._plan_into({k: v for k, v in self._arrays.items() if k not in _MARKS})

    def _lay_out(self, example: TensorDictBase, rows: int) -> tuple[set, set, int]:
        """A new buffer of ``rows`` rows laid out as ``example`` (one row), the kept transitions moved
        in (their entries the new layout has). Returns the new and old entry keys and how many were kept."""
        old, kept = self._buffer, self._cursor
        self._buffer = example.expand(rows).clone()
        self._arrays = {key: self._buffer.get(key).numpy() for key in self._buffer.keys(True, True)}
        ours = set(self._buffer.keys(True, True))
        if old is None or not kept:
            return ours, ours, 0
        theirs = set(old.keys(True, True))
        self._buffer[:kept] = old[:kept].select(*(ours & theirs))
        return ours, theirs, kept

    def _mark(self, rows: np.ndarray, done: np.ndarray, start: int, end: int) -> None:
        """Trajectory ids and step counts of the transitions at ``start:end`` (envs ``rows``), then
        new ids for the envs whose episode ended."""
        arrays, counts = self._arrays, self._step_count[rows]
        arrays[_TRAJ_IDS][start:end] = self._traj_ids[rows]
        arrays["step_count"][start:end, 0] = counts
        arrays[("next", "step_count")][start:end, 0] = counts + 1
        self._step_count[rows] = np.where(done, 0, counts + 1)
        if done.any():
            ended = rows[done]
            self._traj_ids[ended] = np.arange(self._next_traj, self._next_traj + len(ended))
            self._next_traj += len(ended)

    def _batch(self) -> TensorDictBase:
        """The first ``frames_per_batch`` transitions, a copy, each trajectory's transitions side by
        side and in order (what ``split_trajectories`` and ``SliceSampler`` read); the rest move
        to the front of the buffer."""
        frames, cursor = self.frames_per_batch, self._cursor
        ids = self._buffer.get(_TRAJ_IDS)[:frames]
        out = self._buffer[torch.argsort(ids, stable=True)]  # a gather: the buffer is free again
        if cursor > frames:
            for array in self._arrays.values():
                array[: cursor - frames] = array[frames:cursor]
        self._cursor = cursor - frames
        return out

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
            n = pool.num_envs
            self._step_count[:] = 0
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
        if not self._cursor:
            return
        arrays, cursor = self._arrays, self._cursor
        index = arrays["env_index"][:cursor]
        done = arrays[("next", "done")].reshape(len(self._buffer), -1)[:cursor, 0]
        for i in np.unique(index):
            last = np.flatnonzero(index == i)[-1]
            if not done[last]:
                arrays[("next", "truncated")].reshape(len(self._buffer), -1)[last] = True
                arrays[("next", "done")].reshape(len(self._buffer), -1)[last] = True

    def iterator(self) -> Iterator[TensorDictBase]:
        pool, stats, clock = self.env, self._stats, time.perf_counter
        # The time blocked waiting for the envs, where the pool measures it; else the whole receive.
        waited = (lambda: pool.waited) if isinstance(pool, ManiSkillAsyncEnvPool) else clock
        frames = self.frames_per_batch
        self._start()
        try:
            while self.total_frames < 0 or self._frames < self.total_frames:
                if self._cursor >= frames:
                    self._frames += frames
                    yield self._batch()
                    continue
                t0, w0 = clock(), waited()
                roots = self._receive()
                t1, w1 = clock(), waited()
                try:
                    self._act(roots)  # the envs step again while this process does the rest
                except BaseException:
                    self._held.append(roots)
                    raise
                stats["cycles"] += 1
                stats["wait"] += w1 - w0
                stats["policy"] += clock() - t1
                stats["total"] += clock() - t0
        except BaseException as err:  # an error, Ctrl-C, or the iterator closed (GeneratorExit)
            interrupted = isinstance(err, KeyboardInterrupt)
            if interrupted:  # it may have come mid-receive: the episodes start afresh next time
                self._running = False
            try:
                # After Ctrl-C, a bounded wait: the user's handler (a checkpoint) comes first.
                self._drain(timeout=_INTERRUPTED_DRAIN_S if interrupted else None)
            except Exception as drain_error:
                if isinstance(err, GeneratorExit):
                    raise
                # The user's error (or KeyboardInterrupt) is the one raised; the drain's is told.
                err.add_note(f"AsyncPoolCollector: draining the pool then failed too: {drain_error!r}")
            raise
        self._drain()

    def _drain(self, timeout: float | None = None) -> None:
        """Receives the steps still under way into the buffer and keeps their roots for the next
        iteration, so that the pool is idle: it can reset, step in lockstep, or close."""
        pool = self.env
        pending = getattr(pool, "_current_step_reset", 0)  # TorchRL's pools count them there
        if pending:
            min_get, self.min_get = self.min_get, pending
            try:
                self._held.append(self._receive(timeout))
            finally:
                self.min_get = min_get
        self._epoch = getattr(pool, "_epoch", None)

    def __iter__(self) -> Iterator[TensorDictBase]:
        # BaseCollector's shuts the collector (and closes the env) on an exception: the pool is the
        # user's, and stays open and idle (the iterator drains it).
        self._iteration_started = True
        yield from self.iterator()

    def cycle_stats(self, reset: bool = False) -> dict[str, float]:
        """Mean seconds per cycle (one receive, the policy, one send and the bookkeeping) in this
        process: ``wait`` (blocked waiting for the envs; for pools other than
        :class:`~maniskill_torchrl.ManiSkillAsyncEnvPool`, the whole receive), ``policy`` (the
        policy and the send of its actions), ``other`` (the rest: the receive's and the
        collector's own work), and ``cycles``."""
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
