"""ManiSkill CPU-sim envs as TorchRL's :class:`~torchrl.envs.AsyncEnvPool`, on the split-phase engine.

:class:`ManiSkillAsyncEnvPool` answers TorchRL's asynchronous-env interface
(``async_step_send`` / ``async_step_recv``, ``async_step_and_maybe_reset_send`` / ``_recv``,
``async_reset_send`` / ``_recv``, the ``"env_index"`` convention) over one
:class:`~maniskill_torchrl.CPUVectorEnv` made with ``split_phase=True``: the actions of some envs
go into their rows of the shared block, and the envs that are done come back, whichever they
are. The workers stay lean (ManiSkill, the gym shim's repeat, numpy; no TorchRL), and a step
that ends an episode resets at once in its worker. Each output is a TensorDict of the envs
received, laid out as :class:`~maniskill_torchrl.ManiSkillEnv` lays out a step, with
``"env_index"``.
"""

from __future__ import annotations

import functools
import threading
import warnings
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Unbounded
from torchrl.envs import AsyncEnvPool, EnvBase

from maniskill_torchrl._internal.mp import entropy_seed
from maniskill_torchrl._internal.rows import RowStore
from maniskill_torchrl._private import new_tensordict
from maniskill_torchrl.engines._interrupts import HELD
from maniskill_torchrl.engines._worker import INFO, OBS, REWARD, TERMINATED, TRUNCATED
from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv
from maniskill_torchrl.envs.engine_env import ManiSkillEnv, ManiSkillWrapper

__all__ = ["ManiSkillAsyncEnvPool"]


def _put(tree: dict, key: Any, value: Any) -> None:
    """``value`` at ``key`` (a name or a tuple of names) of nested dicts."""
    if isinstance(key, str):
        tree[key] = value
        return
    for name in key[:-1]:
        tree = tree.setdefault(name, {})
    tree[key[-1]] = value


def _read(store: RowStore | TensorDictBase, rows: np.ndarray) -> TensorDictBase:
    """Rows ``rows`` of the sent rows ``store``, a fresh ``[k]`` TensorDict."""
    return store.read(rows) if isinstance(store, RowStore) else store[torch.from_numpy(rows)]


class ManiSkillAsyncEnvPool(AsyncEnvPool):
    """``num_envs`` ManiSkill CPU-sim envs, one worker process each, as TorchRL's :class:`~torchrl.envs.AsyncEnvPool`.

    Args:
        env_name (str): a registered ManiSkill task, e.g. ``"PickCube-v1"``.
        num_envs (int): the envs of the pool, one worker process each.

    Keyword Args:
        repeat (int): each step applies its action up to ``repeat`` times in the env's worker,
            with ManiSkill's ``ActionRepeatWrapper`` semantics (rewards summed, flags OR'ed, the
            last real step's observation; what :class:`~maniskill_torchrl.transforms.ActionRepeat`
            gives). Defaults to 1.
        info_keys (list of str, optional): as in :class:`~maniskill_torchrl.ManiSkillEnv`.
        warn_after (float, optional): seconds a receive may wait for one env's call before a
            warning. Only waiting counts: the caller's own time between two calls (a learner's
            update) does not. Defaults to 30. None: never.
        fail_after (float, optional): seconds a receive may wait for one env's call before the
            call raises an error naming it, its worker is killed and the pool closed (a stuck
            worker). Defaults to 300. None: never.
        **kwargs: ManiSkill's ``gym.make`` arguments (``obs_mode``, ``control_mode``,
            ``max_episode_steps``...), given to every env.

    Each env of the pool is the env ``ManiSkillEnv(env_name, batch_size=[], **kwargs)`` would
    make, with the same keys, specs and values: the pool's batch is ``[num_envs]`` and
    ``env_makers`` holds those factories. Seeding: after ``set_seed(s)``, env ``i``'s first
    reset uses seed ``s + i`` and its later resets the draws of ``numpy.random.RandomState(s +
    i)``, in order, however the envs' steps interleave; each env therefore equals a lone
    ManiSkill env (``CPUGymWrapper``) reset with those seeds and given the same actions, bit for
    bit. Without ``set_seed`` (or after ``set_seed(None)``), ``s`` is drawn from the operating
    system's entropy: every env plays its own episodes, as in gym's ``AsyncVectorEnv`` (the
    workers fork from one process, and ManiSkill's unseeded resets would repeat one another).

    The sync calls (``reset``, ``step``, ``rollout``, a TorchRL ``Collector``) step every env
    together, as TorchRL's pools do; a reset with TorchRL's ``"_reset"`` mask (what
    ``TransformedEnv`` and the collectors send when some episodes end) resets only the envs it
    asks, and TorchRL keeps the others' roots. Each transition holds the entries its step was
    sent with, nothing left from an earlier send (a policy that wrote other entries). The
    asynchronous calls step some and return whichever are
    done: ``async_step_and_maybe_reset_recv`` returns the transitions and the roots of the next
    steps, an env whose episode ended already reset there. Each env has one call under way at
    most: ``async_step_recv`` returns the envs sent ``async_step_send`` only, and
    ``async_step_and_maybe_reset_recv`` those sent ``async_step_and_maybe_reset_send``.
    ``min_get``, ``max_get``, ``timeout`` and ``env_index`` follow TorchRL's pools: an ``int``
    ``env_index`` gives that env's unbatched result, the results of several envs come in env
    order (whatever the order of an ``env_index`` list), each with its ``"env_index"``, and the
    per-env calls may come from one thread per env (TorchRL's ``AsyncBatchedCollector`` env
    loops). A worker that fails makes
    the call raise a ``RuntimeError`` naming its env, and closes the pool; an env that does not
    answer for ``warn_after`` seconds is warned about, and after ``fail_after`` seconds the call
    raises and closes the pool (never a hang). CPU only (``device="cpu"``); pictures come with
    ``obs_mode="rgb"`` (no ``from_pixels``).

    Examples:
        >>> import torch
        >>> from maniskill_torchrl import ManiSkillAsyncEnvPool
        >>> pool = ManiSkillAsyncEnvPool("PickCube-v1", 2, obs_mode="state")
        >>> _ = pool.set_seed(0)
        >>> pool.async_reset_send(env_index=[0, 1])
        >>> roots = pool.async_reset_recv(min_get=2)
        >>> roots["action"] = torch.zeros(2, 8)
        >>> pool.async_step_and_maybe_reset_send(roots, env_index=[0, 1])
        >>> transitions, next_roots = pool.async_step_and_maybe_reset_recv(min_get=1)
        >>> transitions["next", "reward"].shape[-1], transitions["env_index"].dtype
        (1, torch.int64)
        >>> pool.close()
    """

    def __init__(
        self,
        env_name: str,
        num_envs: int,
        *,
        repeat: int = 1,
        info_keys: list[str] | None = None,
        warn_after: float | None = 30.0,
        fail_after: float | None = 300.0,
        **kwargs: Any,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"ManiSkillAsyncEnvPool: num_envs must be a positive int, got {num_envs!r}.")
        for key, why in (
            ("from_pixels", "render with obs_mode='rgb' (pictures in the observation)"),
            ("device", "the pool is on the CPU: move its outputs with a transform or the collector's device"),
            ("num_workers", "each env of the pool has its worker already"),
            ("batch_size", "the pool's batch is [num_envs]"),
        ):
            if key in kwargs:
                raise TypeError(f"ManiSkillAsyncEnvPool does not take {key}=: {why}.")
        names = ("env_name", "repeat", "info_keys", "warn_after", "fail_after", "kwargs")
        self._maniskill = dict(zip(names, (env_name, repeat, info_keys, warn_after, fail_after, kwargs)))
        # The batched env whose specs and layout the pool has: in __dict__, not a submodule.
        self.__dict__["_inner"] = None
        single = functools.partial(ManiSkillEnv, env_name, batch_size=[], info_keys=info_keys, **kwargs)
        super().__init__([single] * int(num_envs), backend="threading", stack="dense")
        # The env indices are an int64 tensor here (TorchRL's pools stack python ints): declared so,
        # check_env_specs compares them as the other entries.
        self.__dict__["_input_spec"]["full_state_spec"].set(
            self._env_idx_key, Unbounded(shape=(self.num_envs,), dtype=torch.int64)
        )

    # ------------------------------------------------------------------ set-up
    def _setup(self) -> tuple:
        from maniskill_torchrl._internal.repeat import check_repeat

        settings = self._maniskill
        repeat = check_repeat(settings["repeat"])
        engine = CPUVectorEnv(settings["env_name"], self.num_envs, split_phase=True, **settings["kwargs"])
        try:
            if repeat != 1:
                engine.set_repeat(repeat)
            self.__dict__["_inner"] = ManiSkillWrapper(engine, info_keys=settings["info_keys"])
        except BaseException:
            engine.close()
            raise
        engine.warn_after, engine.fail_after = settings["warn_after"], settings["fail_after"]
        self._engine = engine
        # One thread at a time in the engine's bookkeeping (TorchRL's env loops run one thread per env).
        self._pool_lock = threading.RLock()
        self._next_seed = np.zeros(self.num_envs, dtype=np.int64)
        self._rngs: list[np.random.RandomState] = []
        self._set_seed(None)
        # What each env was sent to step, kept for its transition: one row per env, one indexed write
        # per send and one indexed read per receive (made on the first send; a TensorDict where the
        # rows hold something numpy cannot). When the entries sent change (a new policy), new rows
        # are made; the envs whose step is under way keep theirs in the older rows until received
        # (``_older``: (rows, the envs whose row is there)).
        self._sent: RowStore | TensorDictBase | None = None
        self._older: list[tuple[RowStore | TensorDictBase, np.ndarray]] = []
        self._into: tuple | None = None  # a collector's plan (_plan_into)
        self._fresh: tuple | None = None  # the last roots of _recv_into, and their entries
        # Counts the plain steps and resets sent: a collector resumes its episodes only if none came between.
        self._epoch = 0
        return self._inner.output_spec.clone(), self._inner.input_spec.clone()

    # The pool's specs are the batched env's own ([num_envs]); AsyncEnvPool would stack its
    # children's, which this pool does not have.
    full_action_spec = EnvBase.full_action_spec
    full_observation_spec = EnvBase.full_observation_spec
    full_reward_spec = EnvBase.full_reward_spec
    full_done_spec = EnvBase.full_done_spec
    full_state_spec = EnvBase.full_state_spec

    @property
    def env_batch_sizes(self) -> list[torch.Size]:
        return [torch.Size([])] * self.num_envs

    def _get_child_specs(self) -> list:
        return [{"input_spec": self.input_spec[i], "output_spec": self.output_spec[i]} for i in range(self.num_envs)]

    @property
    def waited(self) -> float:
        """Seconds this process has spent waiting for the workers' answers (the rest of a receive is
        its own work)."""
        return self._engine._pool.waited

    @property
    def is_closed(self) -> bool:
        """Whether the pool is closed (by ``close()``, or after a worker failed or got stuck)."""
        engine = self.__dict__.get("_engine")
        return self.__dict__.get("_inner") is None or engine is None or engine.closed

    @is_closed.setter
    def is_closed(self, value: bool) -> None:  # EnvBase sets it; here it is the engine's state
        pass

    # TorchRL's pools count the calls under way here; the engine keeps one per env, and these
    # are derived from it (none once closed, or after a worker failed).
    def _count(self, kind: str) -> int:
        if self._inner is None or self._engine.closed:
            return 0
        return self._engine.count_pending(kind)

    @property
    def _current_step(self) -> int:
        return self._count("step")

    @property
    def _current_step_reset(self) -> int:
        return self._count("step_reset")

    @property
    def _current_reset(self) -> int:
        return self._count("reset")

    # ------------------------------------------------------------------ seeds
    def _set_seed(self, seed: int | None) -> None:
        if seed is None:  # every env its own episodes, as gym's AsyncVectorEnv gives
            seed = entropy_seed()
        self._next_seed[:] = int(seed) + np.arange(self.num_envs)
        self._rngs = [np.random.RandomState((int(seed) + i) % 2**32) for i in range(self.num_envs)]

    def _seeds(self, env_idx: np.ndarray) -> np.ndarray:
        """The next reset seed of each env of ``env_idx``, not yet used up."""
        return self._next_seed[env_idx]

    def _used_seeds(self, env_idx: np.ndarray) -> None:
        """The envs of ``env_idx`` have reset: their next reset takes their stream's next draw."""
        for i in env_idx.tolist():
            self._next_seed[i] = self._rngs[i].randint(2**31)

    # ------------------------------------------------------------------ asynchronous calls
    def _indexed(self, tensordict: TensorDictBase, env_index: Any) -> tuple[TensorDictBase, np.ndarray]:
        """``tensordict`` as ``[k]`` rows and the env index of each (TorchRL's convention: the
        ``env_index`` argument, else the ``"env_index"`` entry)."""
        if env_index is None:
            env_index = tensordict.get(self._env_idx_key, None)
            if env_index is None:
                raise KeyError(f"{self!r}: say which envs these rows are for: env_index=[...] or an 'env_index' entry.")
            if not isinstance(env_index, torch.Tensor):
                env_index = env_index.tolist()
        if isinstance(env_index, int) or (isinstance(env_index, torch.Tensor) and env_index.ndim == 0):
            if tensordict.ndim == 0:
                tensordict = tensordict.unsqueeze(0)
        if isinstance(env_index, torch.Tensor) and env_index.ndim == 1 and env_index.device.type == "cpu":
            env_idx = env_index.numpy().astype(np.int64, copy=False)
        else:
            env_idx = np.asarray(torch.as_tensor(env_index, device="cpu").reshape(-1), dtype=np.int64)
        if tensordict.shape[:1] != (len(env_idx),):
            raise ValueError(
                f"{self!r}: {len(env_idx)} env indices for a tensordict of batch {tuple(tensordict.shape)}."
            )
        return tensordict, env_idx

    def _send_steps(self, tensordict: TensorDictBase, env_index: Any, autoreset: bool) -> None:
        tensordict, env_idx = self._indexed(tensordict, env_index)
        action = tensordict.get("action", None)
        if action is None:
            raise KeyError(
                f"{self!r}: no 'action' entry in the tensordict sent to step ({sorted(tensordict.keys())}): set "
                "td['action'] (the policy's output) first."
            )
        # Ctrl-C after the send but before its rows are written would leave a step whose transition holds the
        # rows of the env's step before: held till the rows are written (engines/_interrupts.py), never over
        # the lock's wait.
        with self._pool_lock, HELD:
            seeds = self._seeds(env_idx) if autoreset else None
            self._engine.step_send(action, env_idx, autoreset=autoreset, reset_seeds=seeds)
            self.__dict__["_epoch"] += 1  # not EnvBase's (nn.Module's) __setattr__: on the hot path
            sent = self._sent
            if sent is None or not (
                sent.fits(tensordict)
                if isinstance(sent, RowStore)
                else set(sent.keys(True, True)) == set(tensordict.keys(True, True))
            ):
                sent = self._new_rows(tensordict, env_idx)
            if isinstance(sent, RowStore):
                # Roots just made by _recv_into and sent back as they are: only the entries the
                # policy wrote (or replaced) are new to the rows.
                fresh = self._fresh
                self.__dict__["_fresh"] = None
                sent.write(env_idx, tensordict, same=fresh[1] if fresh is not None and fresh[0] is tensordict else None)
            else:
                sent[torch.from_numpy(env_idx)] = tensordict

    def _new_rows(self, tensordict: TensorDictBase, env_idx: np.ndarray) -> RowStore | TensorDictBase:
        """Rows laid out as ``tensordict`` (the first send, or other entries than before: a new
        policy), so that a transition holds what its send held and nothing older."""
        old = self._sent
        if old is not None:
            waiting = self._engine.stepping()
            waiting[env_idx] = False  # just sent: their rows are the new ones
            for _, mask in self._older:  # their rows are in older ones still
                waiting &= ~mask
            if waiting.any():
                self._older.append((old, waiting))
        if RowStore.supports(tensordict):
            rows = RowStore(tensordict, self.num_envs)
        else:
            rows = tensordict[:1].expand(self.num_envs).clone()
        self._sent = rows
        self._into = None
        return rows

    def _read_sent(self, rows: np.ndarray) -> TensorDictBase:
        """What the envs ``rows`` were sent to step, from the rows each was written in."""
        if not self._older:
            return _read(self._sent, rows)
        with self._pool_lock:
            parts, left = [], np.ones(len(rows), dtype=bool)
            for store, mask in [*self._older, (self._sent, None)]:
                mine = left.copy() if mask is None else mask[rows] & left
                if mine.any():
                    parts.append((np.flatnonzero(mine), _read(store, rows[mine])))
                    if mask is not None:
                        mask[rows[mine]] = False
                    left &= ~mine
            self._older = [(store, mask) for store, mask in self._older if mask.any()]
        if len(parts) == 1:
            return parts[0][1]
        keys = [set(part.keys(True, True)) - {self._env_idx_key} for _, part in parts]  # set for all below
        common = set.intersection(*keys)
        if common != set.union(*keys):
            warnings.warn(
                f"{self!r}: the envs received together were sent different entries (a policy changed while "
                f"steps were under way); their transitions hold the common entries, without "
                f"{sorted(set.union(*keys) - common, key=str)}. Receive such envs apart (env_index=...) to keep "
                "them.",
                RuntimeWarning,
                stacklevel=4,
            )
        out = torch.cat([part.select(*common) for _, part in parts])
        order = np.argsort(np.concatenate([where for where, _ in parts]), kind="stable")
        return out[torch.from_numpy(order)]

    def _wait_for(self, env_index: int) -> None:
        """Waits, without holding the pool's lock, until env ``env_index`` has answered (the
        per-env calls of TorchRL's env loops, one thread per env)."""
        engine = self._engine
        while True:
            with self._pool_lock:
                if engine.answered(env_index):
                    return
            engine.wait_readable(env_index, 0.05)

    def _receive(
        self, autoreset: bool, min_get: int | None, env_index: Any, max_get: int | None, timeout: float | None
    ) -> tuple[np.ndarray, tuple, tuple | None]:
        engine = self._engine
        if env_index is None:
            min_get = self.min_get if min_get is None else min_get
            with self._pool_lock:  # the engine checks the arguments (TorchRL's rules) and what is under way
                return engine.step_recv(min_get, max_get=max_get, timeout=timeout, autoreset=autoreset)
        only = np.asarray(torch.as_tensor(env_index, device="cpu").reshape(-1), dtype=np.int64)
        if only.size == 1:
            self._wait_for(int(only[0]))
        with self._pool_lock:
            return engine.step_recv(env_idx=only, autoreset=autoreset)

    def _transitions(self, rows: np.ndarray, step: tuple) -> tuple[TensorDictBase, torch.Tensor]:
        index = torch.from_numpy(rows)
        transitions = self._read_sent(rows)
        transitions.set(self._env_idx_key, index)
        transitions.set("next", self._next_rows(step))
        return transitions, index

    @staticmethod
    def _one(out: TensorDictBase, env_index: Any) -> TensorDictBase:
        """An ``int`` env index gets its env's unbatched result, as TorchRL's pools give it."""
        return out[0] if isinstance(env_index, (int, np.integer)) else out

    def async_step_send(self, tensordict: TensorDictBase, env_index: int | list[int] | None = None) -> None:
        self._send_steps(tensordict, env_index, autoreset=False)

    def async_step_recv(
        self,
        min_get: int | None = None,
        env_index: int | list[int] | None = None,
        *,
        max_get: int | None = None,
        timeout: float | None = None,
    ) -> TensorDictBase:
        rows, step, _ = self._receive(False, min_get, env_index, max_get, timeout)
        return self._one(self._transitions(rows, step)[0], env_index)

    def async_step_and_maybe_reset_send(
        self, tensordict: TensorDictBase, env_index: int | list[int] | None = None
    ) -> None:
        self._send_steps(tensordict, env_index, autoreset=True)

    def async_step_and_maybe_reset_recv(
        self,
        min_get: int | None = None,
        env_index: int | list[int] | None = None,
        *,
        max_get: int | None = None,
        timeout: float | None = None,
    ) -> tuple[TensorDictBase, TensorDictBase]:
        rows, step, (done, obs, info) = self._receive(True, min_get, env_index, max_get, timeout)
        transitions, index = self._transitions(rows, step)
        # TorchRL's step_mdp, for this pool's entries: "next" but the reward, the action and env index kept.
        roots = transitions.get("next").exclude(*self.reward_keys)
        for key in self.action_keys:
            roots.set(key, transitions.get(key))
        roots.set(self._env_idx_key, index)
        if done.any():
            with self._pool_lock:
                self._used_seeds(rows[done.numpy()])
            restarted = self._restarts(obs, info, int(done.sum()))
            roots = roots.clone()  # step_mdp's entries are the transitions' "next" ones
            roots[done] = restarted
        return self._one(transitions, env_index), self._one(roots, env_index)

    # ------------------------------------------------------------------ the collector's cycle
    def _plan_into(self, arrays: dict) -> bool:
        """Plans :meth:`_recv_into` for a collector's buffer: ``arrays`` maps each leaf of a
        transition (``"env_index"``, the sent entries, the ``"next"`` ones; others are the
        collector's) to a numpy array ``[capacity, ...]``. Each entry comes straight from where it
        lies: the sent rows, or the shared block's (found as the memory the batched env's own
        step and reset entries are views of). Returns whether every entry could be planned so."""
        self._into = None
        sent, inner = self._sent, self._inner
        if not isinstance(sent, RowStore) or self._older:
            return False
        block, n = self._engine.block, self.num_envs
        results = block.results

        # Where each entry of a step lies in the block: the observation's leaves under OBS (one
        # Box: "observation"), the declared infos under INFO, the reward and the two flags.
        by_path = dict(zip(block.layout.result_paths, results))
        infos = {(td_key,): key for key, td_key in inner.info_entries.items()}

        def source(key: Any, td: TensorDictBase) -> np.ndarray | None:
            path = (key,) if isinstance(key, str) else tuple(key)
            special = {("reward",): (REWARD,), ("terminated",): (TERMINATED,), ("truncated",): (TRUNCATED,)}
            if path in special:
                where = special[path]
            elif (OBS,) in by_path:
                where = (OBS,) if path == ("observation",) else None
            else:
                where = (OBS, *path)
            if path[:1] in infos:
                where = (INFO, infos[path[:1]], *path[1:])
            array = by_path.get(where)
            value = td.get(key)
            if array is None or array.dtype != value.numpy().dtype or array[:n].size != value.numel():
                return None
            return array

        def located(td: TensorDictBase) -> dict:
            return {key: source(key, td) for key in td.keys(True, True)}

        views = block.views(0, n)
        nxt = self._next_rows((views[OBS], views[REWARD], views[TERMINATED], views[TRUNCATED], views[INFO]))
        again = block.views(n, 2 * n)
        restart = self._reset_rows(again[OBS], again[INFO], n)
        in_step, in_reset = located(nxt), located(restart)
        flags = set(self.done_keys)
        copies, done_dst = [], None
        for key, dst in arrays.items():
            path = (key,) if isinstance(key, str) else tuple(key)
            if path == (self._env_idx_key,):
                continue
            if path[0] == "next":
                sub = path[1] if len(path) == 2 else path[1:]
                src = in_step.get(sub)
                if src is None and sub == "done":
                    done_dst = dst.reshape(-1)
                    continue
            else:
                src = sent.array(key)
            if src is None:
                return False
            copies.append((src, dst.reshape(dst.shape[0], *src.shape[1:])))
        roots = []  # (key, step rows, reset rows or None: a done flag, False at a start, leaf shape)
        for key in nxt.keys(True, True):
            if key in self.reward_keys:
                continue
            src = in_step.get(key)
            if key == "done" or src is None:
                if key != "done":
                    return False
                src = None
            reset = in_reset.get(key)
            if reset is None and key not in flags:
                return False
            store = sent.array(key)
            if store is None:
                return False
            roots.append((key, src, reset, tuple(nxt.get(key).shape[1:]), store))
        terminated, truncated = in_step["terminated"], in_step["truncated"]
        if done_dst is None or terminated is None or truncated is None:
            return False
        actions = [(key, sent.array(key)) for key in self.action_keys]
        env_store = sent.array(self._env_idx_key)
        if any(a is None for _, a in actions) or env_store is None:
            return False
        self._into = (copies, done_dst, arrays[self._env_idx_key], roots, actions, terminated, truncated, env_store)
        return True

    def _recv_into(
        self, cursor: int, min_get: int, timeout: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, TensorDictBase]:
        """The collector's receive (after :meth:`_plan_into`): the transitions of the envs whose
        step is done written into the planned arrays at rows ``cursor:cursor + k``, one numpy
        copy per entry, and the roots of their next steps (a reset's, for the envs that ended).
        Returns the envs, their done flags and the roots."""
        copies, done_dst, env_dst, roots_plan, actions, terminated, truncated, env_store = self._into
        with self._pool_lock:
            rows = self._engine.step_recv_rows(min_get, timeout=timeout, autoreset=True)
        k = len(rows)
        end = cursor + k
        for src, dst in copies:
            src.take(rows, axis=0, out=dst[cursor:end])
        done = terminated[rows] | truncated[rows]
        done_dst[cursor:end] = done
        env_dst[cursor:end] = rows
        ended = done.any()
        restarted = rows[done] + self.num_envs if ended else None
        tree: dict = {}
        # The roots, also written into the sent rows: what the next send leaves as it is, it skips.
        for key, src, reset, shape, store in roots_plan:
            value = (done.copy() if src is None else src[rows]).reshape(k, *shape)  # src None: "done"
            if ended:
                value[done] = False if reset is None else reset[restarted].reshape(-1, *shape)
            store[rows] = value
            _put(tree, key, torch.from_numpy(value))
        for key, src in actions:
            _put(tree, key, torch.from_numpy(src[rows]))
        env_store[rows] = rows
        tree[self._env_idx_key] = torch.from_numpy(rows)
        if ended:
            with self._pool_lock:
                self._used_seeds(rows[done])
        roots = new_tensordict(tree, batch_size=torch.Size([k]))
        self.__dict__["_fresh"] = (roots, tree)
        return rows, done, roots

    def _next_rows(self, step: tuple) -> TensorDictBase:
        """The ``"next"`` entries of some envs' steps, ``(obs, reward, terminated, truncated, info)``
        rows, as the env's step makes them (the engine's outputs are fresh: nothing to copy)."""
        obs, reward, terminated, truncated, info = step
        inner = self._inner
        source = inner._to_source(obs, info, reward, terminated, truncated)
        return new_tensordict(source, batch_size=reward.shape[:1], device=inner.device)

    def _reset_rows(self, obs: Any, info: Any, count: int) -> TensorDictBase:
        """The reset entries of ``count`` envs, as the env's reset makes them."""
        inner = self._inner
        return new_tensordict(inner._to_source(obs, info), batch_size=torch.Size([count]), device=inner.device)

    def _restarts(self, obs: Any, info: Any, count: int) -> TensorDictBase:
        """The roots of ``count`` episodes' starts: the reset's entries, every done flag False."""
        out = self._reset_rows(obs, info, count)
        for key in ("done", "terminated", "truncated"):
            out.set(key, torch.zeros(count, 1, dtype=torch.bool))
        return out

    def async_reset_send(
        self,
        tensordict: TensorDictBase | None = None,
        env_index: int | list[int] | None = None,
    ) -> None:
        tensordict, env_idx = self._maybe_make_tensordict(tensordict, env_index, True)
        env_idx = np.asarray(env_idx, dtype=np.int64).reshape(-1)
        with self._pool_lock:
            self._engine.reset_send(env_idx, self._seeds(env_idx))
            self._used_seeds(env_idx)
            self.__dict__["_epoch"] += 1

    def async_reset_recv(
        self,
        min_get: int | None = None,
        env_index: int | list[int] | None = None,
        *,
        max_get: int | None = None,
        timeout: float | None = None,
    ) -> TensorDictBase:
        engine = self._engine
        if env_index is None:
            min_get = self.min_get if min_get is None else min_get
            with self._pool_lock:
                rows, obs, info = engine.reset_recv(min_get, max_get=max_get, timeout=timeout)
        else:
            only = np.asarray(torch.as_tensor(env_index, device="cpu").reshape(-1), dtype=np.int64)
            if only.size == 1:
                self._wait_for(int(only[0]))
            with self._pool_lock:
                rows, obs, info = engine.reset_recv(env_idx=only)
        out = self._restarts(obs, info, len(rows))
        out.set(self._env_idx_key, torch.from_numpy(rows))
        return self._one(out, env_index)

    # ------------------------------------------------------------------ sync calls
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        # TorchRL's partial reset: only the envs of the "_reset" mask; TorchRL keeps the others' roots
        # (their rows here are zeros, which its update_during_reset does not read).
        n = self.num_envs
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            env_idx = np.arange(n)
        else:
            env_idx = np.flatnonzero(mask.reshape(n, -1).any(-1).cpu().numpy())
        if len(env_idx) == n:
            self.async_reset_send(env_index=env_idx.tolist())
            return self.async_reset_recv(min_get=n)
        out = self.full_observation_spec.zero().update(self.full_done_spec.zero())
        out.set(self._env_idx_key, torch.arange(n))
        if len(env_idx):
            self.async_reset_send(env_index=env_idx.tolist())
            out[torch.from_numpy(env_idx)] = self.async_reset_recv(min_get=len(env_idx))
        return out

    def reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        """Resets every env, or the envs of TorchRL's ``"_reset"`` mask in ``tensordict`` (the others
        keep their roots), as :meth:`~torchrl.envs.EnvBase.reset` does: TorchRL's ``AsyncEnvPool``
        resets every env whatever the mask."""
        return EnvBase.reset(self, tensordict, **kwargs)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.async_step_send(tensordict, env_index=list(range(self.num_envs)))
        return self.async_step_recv(min_get=self.num_envs)["next"]

    # ------------------------------------------------------------------ the end
    def shutdown(self) -> None:
        if self._inner is not None:
            self._inner.close(raise_if_closed=False)
            self.__dict__["_inner"] = None

    def __reduce__(self) -> Any:
        raise TypeError(
            "ManiSkillAsyncEnvPool holds worker processes and cannot be pickled: pickle "
            "functools.partial(ManiSkillAsyncEnvPool, 'PickCube-v1', num_envs, ...) instead."
        )

    def __repr__(self) -> str:
        settings = self._maniskill
        repeat = f", repeat={settings['repeat']}" if settings["repeat"] != 1 else ""
        return f"ManiSkillAsyncEnvPool({settings['env_name']!r}, num_envs={self.num_envs}{repeat})"
