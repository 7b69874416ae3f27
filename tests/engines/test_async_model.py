"""A model-based test of the asynchronous path (issue 59, item 2): random sequences of TorchRL's calls on one
:class:`~maniskill_torchrl.ManiSkillAsyncEnvPool`, every returned entry compared bit for bit with a model.

The model of each env is a lone ManiSkill env (``CPUGymWrapper``, over ``ActionRepeatWrapper`` for a
repeat), reset with the pool's seeds (first ``s + i``, then the draws of ``numpy.random.RandomState(s +
i)``, in order) and stepped with the actions the pool was sent. Hypothesis' ``RuleBasedStateMachine``
drives the pool with the calls TorchRL's consumers make: step and step-and-maybe-reset sends and
receives by ``env_index`` (an int, a list, a tensor, or the ``"env_index"`` entry), ``min_get``,
``max_get`` and ``timeout``; asynchronous and sync resets, partial resets through TorchRL's ``"_reset"``
mask (``pool.reset`` and ``TransformedEnv(pool, StepCounter(), RewardSum())``'s
``step_and_maybe_reset``); policies that change the entries they write or edit a root in place;
:class:`~maniskill_torchrl.AsyncPoolCollector` iterations of random ``frames_per_batch`` and ``min_get``,
left open, resumed, or cut by another caller; and pauses longer than the watchdog's (lowered) limits
between two calls. Preconditions keep to the pool's rules (one call under way per env, receive only
what is under way); the misuse rules assert the pool's error and that nothing changed.

Checked after every call: each transition is what its send held (the entries that send held, no
others), with ``"env_index"`` and the lone env's ``"next"``; the roots of the next steps are the lone
env's; ``StepCounter`` / ``RewardSum`` / the collector's step counts and ``elapsed_steps`` are the
episode's; nothing is lost or duplicated (TorchRL's counts of the calls under way are the model's, and
at the end of a sequence everything under way is received and checked); the collector's trajectory
ids change exactly at episode ends and belong to one env.

Profiles: the default run fits ``make test`` (the same sequences every run); ``MANISKILL_TORCHRL_MODEL_RUNS=long``
explores more, and new sequences each run (``MANISKILL_TORCHRL_MODEL_EXAMPLES`` / ``_STEPS`` override both).

What hypothesis draws never depends on timing, so that a failure replays and shrinks (else: hypothesis'
FlakyStrategyDefinition, a failure it cannot replay). Which envs a ``min_get`` receive or a collector's batch gets
is the machine's; so the rules choose among the envs with nothing under way (a step to an env whose episode ended
resets it first), and a receive that takes the answers as they come (the long profile's unsettled sequences) then
receives the rest of that kind by ``env_index``. A failure's note lists the envs as the machine gave them.
To look at one finding: ``_RULES`` (the rules that act), ``_POLICIES``, ``_FRESH=1`` (a new pool per
sequence), ``_VERBOSE=1`` (every step). Each test appends what it explored (sequences, rules, pool calls,
transitions checked) to ``outputs/async_model.txt``.

The pool's state (its sent rows, a collector's plan) carries from one sequence to the next, as it does for a
user who changes policy; a shrunk failure that needs what came before says so when replayed with ``_FRESH=1``.
"""

from __future__ import annotations

import collections
import functools
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, Verbosity, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
    run_state_machine_as_test,
)
from mani_skill.utils.wrappers import ActionRepeatWrapper, CPUGymWrapper
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import Compose, RewardSum, StepCounter, TransformedEnv

from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool
from maniskill_torchrl.testing import assert_tensordict_equal
from support.helpers import close_envs, make_gym_env

# ----------------------------------------------------------------------------- profiles
LONG = os.environ.get("MANISKILL_TORCHRL_MODEL_RUNS", "") == "long"
EXAMPLES = int(os.environ.get("MANISKILL_TORCHRL_MODEL_EXAMPLES", 40 if LONG else 6))
STEPS = int(os.environ.get("MANISKILL_TORCHRL_MODEL_STEPS", 50 if LONG else 20))
SETTINGS = settings(
    max_examples=EXAMPLES,
    stateful_step_count=STEPS,
    deadline=None,
    database=None,
    derandomize=not LONG,  # the default run explores the same sequences every time
    print_blob=True,
    suppress_health_check=list(HealthCheck),
    verbosity=Verbosity.debug if os.environ.get("MANISKILL_TORCHRL_MODEL_VERBOSE") else Verbosity.normal,
)
SUMMARY = Path(__file__).resolve().parents[2] / "outputs" / "async_model.txt"

# The watchdog's limits: generous in general (a real hang fails in seconds, not minutes), lowered around
# a pause (longer than fail_after, so that a watchdog counting from the send fails).
LIMITS = (10.0, 20.0)
PAUSE_LIMITS, PAUSE_S = (0.2, 0.4), 0.45
# Pauses per sequence (each costs PAUSE_S). The default run receives every answer in env order before a
# receive (``_settle``): the same sequence gives the same data, so that hypothesis can shrink a failure;
# the long one also receives as the answers come (which envs a min_get receive returns is the machine's).
MAX_PAUSES = 3 if LONG else 1
# A new pool for every sequence (seconds each): a failing sequence then reproduces alone, whatever ran before.
FRESH = os.environ.get("MANISKILL_TORCHRL_MODEL_FRESH", "") == "1"
# Only these rules act (the others do nothing), e.g. "step_send,receive": to look at one finding at a time.
ONLY = {name for name in os.environ.get("MANISKILL_TORCHRL_MODEL_RULES", "").split(",") if name}

DONE_KEYS = ("done", "terminated", "truncated")
MARKS = (("collector", "traj_ids"),)


def _copy(td: TensorDictBase) -> TensorDictBase:
    """A copy to the bit. Not ``TensorDict.clone()``: on a TensorDict with a device, tensordict 0.14.3 clones
    its float leaves as ``torch._foreach_add(leaves, 0)``, which turns ``-0.0`` into ``0.0``."""
    return td.apply(torch.clone)


# ----------------------------------------------------------------------------- policies
# Deterministic, elementwise, exactly rounded (a multiply, an add, a clamp): the model computes the
# action a collector's policy chose from the root alone, to the bit, whatever the batch.
def _action(obs: torch.Tensor) -> torch.Tensor:
    return (obs[..., :8] * 3.0 + 0.25).clamp(-1.0, 1.0)


def plain(td: TensorDictBase) -> TensorDictBase:
    """Writes ``"action"`` only."""
    td.set("action", _action(td.get("observation")))
    return td


def with_log_prob(td: TensorDictBase) -> TensorDictBase:
    """Writes ``"action"`` and an extra root entry, ``"action_log_prob"`` (a stochastic policy's)."""
    obs = td.get("observation")
    td.set("action", _action(obs))
    td.set("action_log_prob", obs[..., 0] * 0.5 - 7.0)
    return td


def editing(td: TensorDictBase) -> TensorDictBase:
    """Writes ``"action"``, then edits the root's observation in place (a normalizing policy)."""
    td.set("action", _action(td.get("observation")))
    td.get("observation").add_(1.0)
    return td


POLICIES = {"plain": plain, "log_prob": with_log_prob, "editing": editing}
if os.environ.get("MANISKILL_TORCHRL_MODEL_POLICIES"):  # e.g. "plain": one finding at a time
    POLICIES = {name: POLICIES[name] for name in os.environ["MANISKILL_TORCHRL_MODEL_POLICIES"].split(",")}


# ----------------------------------------------------------------------------- the pools and lone envs
class Seeds:
    """The reset seeds of one env of the pool after ``set_seed(s)``: ``s + i``, then ``RandomState(s + i)``'s draws."""

    def __init__(self, first: int) -> None:
        self.first, self.rng, self.used = first, np.random.RandomState(first % 2**32), False

    def next(self) -> int:
        if not self.used:
            self.used = True
            return self.first
        return int(self.rng.randint(2**31))


class World:
    """One pool (rebuilt only if a failure closed it), its ``TransformedEnv``, and one lone env per env index
    (built on first use, reused by every sequence while the pool is, rebuilt with it).

    A seeded reset of ManiSkill's CPU sim does not undo everything of the episode before: PhysX keeps the
    contacts of the last step until the next one (PickCube's ``is_grasped`` after a reset is the old
    episode's). A lone env and the pool's env it models give the same data only from the same history: every
    step of one is a step of the other (:meth:`PoolMachine.teardown` catches the lone envs up with what a
    collector kept), and both are built anew together."""

    def __init__(self, num_envs: int, repeat: int, episode: int) -> None:
        self.num_envs, self.repeat, self.episode = num_envs, repeat, episode
        self.pool: ManiSkillAsyncEnvPool | None = None
        self.tenv: TransformedEnv | None = None
        self.refs: list = [None] * num_envs
        self.stats = collections.Counter()
        self.times, self.counts = collections.Counter(), collections.Counter()  # seconds and calls per rule
        self.started = time.monotonic()

    def get_pool(self) -> ManiSkillAsyncEnvPool:
        if self.pool is None or self.pool.is_closed or FRESH:
            if self.pool is not None:
                self.pool.close(raise_if_closed=False)
            close_envs([r for r in self.refs if r is not None])
            self.refs = [None] * self.num_envs
            self.pool = ManiSkillAsyncEnvPool(
                "PickCube-v1", self.num_envs, repeat=self.repeat, obs_mode="state", max_episode_steps=self.episode
            )
            self.tenv = TransformedEnv(self.pool, Compose(StepCounter(), RewardSum()))
            self.stats["pools built"] += 1
        self.pool._engine.warn_after, self.pool._engine.fail_after = LIMITS
        return self.pool

    def ref(self, i: int):
        if self.refs[i] is None:
            env = make_gym_env("PickCube-v1", obs_mode="state", max_episode_steps=self.episode)
            self.refs[i] = CPUGymWrapper(ActionRepeatWrapper(env, self.repeat) if self.repeat > 1 else env)
        return self.refs[i]

    def close(self) -> None:
        if self.pool is not None:
            self.pool.close(raise_if_closed=False)
        close_envs([r for r in self.refs if r is not None])


# ----------------------------------------------------------------------------- the model of each env
UNKNOWN, READY, DONE = "unknown", "ready", "done"  # no episode known / a root to step / ended, to reset
STEP, STEP_RESET, RESET = "step", "step_reset", "reset"  # what is under way
OWNED = "collector"  # the collector's: its lone env is behind by the transitions it has not yielded


@dataclass
class Pending:
    kind: str
    sent: TensorDictBase | None = None  # what the send held for this env (a clone, taken before the call)
    next: TensorDictBase | None = None  # the lone env's "next"
    root: TensorDictBase | None = None  # the root after: the reset's (a reset, or an episode's end), else "next"'s
    done: bool = False


@dataclass
class EnvModel:
    seeds: Seeds
    status: str = UNKNOWN
    root: TensorDictBase | None = None  # the root entries of its current state (what the pool gave last)
    pending: Pending | None = None
    steps: int = 0  # steps of the current episode (StepCounter's, the collector's step_count)
    reward: torch.Tensor = field(default_factory=lambda: torch.zeros(1))  # RewardSum's episode_reward
    queue: collections.deque = field(default_factory=collections.deque)  # collector transitions to come


@dataclass
class CollectorModel:
    collector: AsyncPoolCollector
    policy: str
    frames_per_batch: int
    min_get: int
    iterator: Any = None  # an iterator held open (after a yield: steps under way)
    running: bool = False  # episodes under way (a next iter() resumes them unless another caller came)
    owns: bool = False  # drained, with transitions received that it has not yielded (the lone envs lag)
    restart: bool = False  # another caller used the pool since its last drain: its next iter() restarts
    traj_env: dict = field(default_factory=dict)  # trajectory id -> env
    traj_of: dict = field(default_factory=dict)  # env -> its current trajectory id (once seen)


def _rule(fn):
    """A rule's body; a sequence whose rule failed is not drained at teardown (its pool is rebuilt)."""

    @functools.wraps(fn)
    def wrapped(self, *args, **kwargs):
        if ONLY and fn.__name__ not in ONLY:
            return None
        self.broken = True
        self.world.stats["rules"] += 1
        start = time.perf_counter()
        try:
            out = fn(self, *args, **kwargs)
        except BaseException as err:
            if self.arrivals:  # what timing decided, to replay a failure that needs it
                err.add_note("Envs as the machine gave them in this sequence: " + "; ".join(self.arrivals[-30:]))
            raise
        self.world.times[fn.__name__] += time.perf_counter() - start
        self.world.counts[fn.__name__] += 1
        self.broken = False
        return out

    return wrapped


class PoolMachine(RuleBasedStateMachine):
    world: World  # set by the test, per pool configuration

    def __init__(self) -> None:
        super().__init__()
        self.broken = False
        self.world.stats["sequences"] += 1
        self.pool = self.world.get_pool()
        self.n = self.world.num_envs
        spec = self.pool.full_observation_spec
        self.info_specs = {key: spec[key] for key in spec.keys() if key != "observation"}
        self.envs: list[EnvModel] = []
        self.coll: CollectorModel | None = None
        self.session: TensorDictBase | None = None  # the TransformedEnv's roots, while no other call came
        self.lowered = False  # the watchdog's limits are lowered (a pause), until the next receive
        self.pauses = 0
        self.settled = True  # _settle before each receive (see MAX_PAUSES)
        self.arrivals: list[str] = []  # which envs the calls that take the first to arrive got, in order

    # ------------------------------------------------------------------ the lone envs
    def _root_td(self, obs: np.ndarray, info: dict) -> TensorDictBase:
        """The root entries of a state of a lone env, laid out as the pool's."""
        td = {"observation": torch.as_tensor(np.array(obs))}
        for key, spec in self.info_specs.items():
            td[key] = torch.as_tensor(np.asarray(info[key])).to(spec.dtype).reshape(spec.shape[1:])
        for key in DONE_KEYS:
            td[key] = torch.zeros(1, dtype=torch.bool)
        return TensorDict(td, [])

    def _ref_reset(self, i: int) -> TensorDictBase:
        env = self.envs[i]
        obs, info = self.world.ref(i).reset(seed=env.seeds.next())
        env.root, env.steps, env.reward = self._root_td(obs, info), 0, torch.zeros(1)
        self.world.stats["episodes"] += 1
        return env.root

    def _ref_step(self, i: int, action: torch.Tensor) -> tuple[TensorDictBase, bool]:
        """The lone env's step: its ``"next"`` entries and whether the episode ended."""
        obs, reward, terminated, truncated, info = self.world.ref(i).step(action.numpy())
        nxt = self._root_td(obs, info)
        nxt.set("reward", torch.tensor([reward], dtype=torch.float32))
        nxt.set("terminated", torch.tensor([bool(terminated)]))
        nxt.set("truncated", torch.tensor([bool(truncated)]))
        done = bool(terminated or truncated)
        nxt.set("done", torch.tensor([done]))
        env = self.envs[i]
        env.steps += 1
        env.reward = env.reward + nxt["reward"]
        env.root = nxt.exclude("reward")
        self.world.stats["transitions"] += 1
        return nxt, done

    # ------------------------------------------------------------------ calls into the pool
    def _call(self, fn, *args, receive: bool = False, **kwargs):
        """A call into the pool. After a pause, the watchdog's limits stay lowered until a receive returns,
        and no watchdog warning may come (nothing was stuck: the pool was not waited on)."""
        self.world.stats["pool calls"] += 1
        if not self.lowered:
            return fn(*args, **kwargs)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = fn(*args, **kwargs)
        if receive:
            self.lowered = False
            self.pool._engine.warn_after, self.pool._engine.fail_after = LIMITS
        late = [w for w in caught if "have not answered" in str(w.message)]
        assert not late, f"a watchdog warning after a pause, with every env answered: {late[0].message}"
        for w in caught:
            if "have not answered" not in str(w.message):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return out

    def _foreign(self, restart: bool = True) -> None:
        """Another caller than the collector is about to use the pool (``restart``: to step or reset it): the
        lone envs catch up with what the collector received and has not yielded (in the queues, to compare
        when it yields them), and its next iter() restarts every env."""
        self.session = None
        coll = self.coll
        if coll is None or not coll.running:
            return
        if coll.owns:
            collector = coll.collector
            cursor = collector._cursor
            kept = [] if not cursor else collector._buffer.get("env_index")[:cursor].tolist()
            for i in range(self.n):
                env = self.envs[i]
                # the oldest of env i's kept transitions may be in its queue already (a restart before)
                assert kept.count(i) >= len(env.queue), f"env {i}: kept transitions lost"
                for _ in range(kept.count(i) - len(env.queue)):
                    env.queue.append(self._collector_step(i, coll))
                if env.status == OWNED:
                    env.status = READY
            coll.owns = False
        coll.restart = coll.restart or restart

    def _idle(self) -> bool:
        return all(env.pending is None for env in self.envs) and (self.coll is None or self.coll.iterator is None)

    def _pending(self, kind: str) -> list[int]:
        return [i for i, env in enumerate(self.envs) if env.pending is not None and env.pending.kind == kind]

    def _free(self) -> list[int]:
        """The envs with nothing under way. Which of them ended an episode is not known before a rule: how many
        steps each env took depends on which envs a collector (or a receive) got first, and what hypothesis
        draws may not depend on timing (else a failure would not replay: FlakyStrategyDefinition)."""
        return [i for i, env in enumerate(self.envs) if env.pending is None]

    def _reset_ended(self, envs: list[int]) -> None:
        """The envs of ``envs`` whose episode ended (their last call an ``async_step_send``) reset, through
        ``async_reset_send`` / ``async_reset_recv(env_index=...)``: they can step again."""
        ended = [i for i in envs if self.envs[i].status == DONE]
        if not ended:
            return
        self._call(self.pool.async_reset_send, env_index=ended)
        out = self._call(self.pool.async_reset_recv, env_index=ended, receive=True)
        # the rows come in env order, whatever the order asked (TorchRL's pools sort their results)
        assert out.get("env_index").tolist() == sorted(ended), f"asked for {ended}, rows {out['env_index'].tolist()}"
        for j, i in enumerate(sorted(ended)):
            expected = _copy(self._ref_reset(i)).set("env_index", torch.tensor(i))
            self.envs[i].status = READY
            assert_tensordict_equal(out[j], expected, msg=f"env {i}'s reset (its episode ended)")

    def _choose_envs(self, data, among: list[int], label: str) -> list[int]:
        chosen = data.draw(st.lists(st.sampled_from(among), min_size=1, unique=True), label=label)
        return sorted(chosen) if data.draw(st.booleans(), label="in env order") else chosen

    @staticmethod
    def _index(form: str, envs: list[int]):
        if form == "int":
            return envs[0]
        if form == "tensor":
            return torch.tensor(envs)
        return list(envs)

    # ------------------------------------------------------------------ the sequence's start and end
    @initialize(seed=st.integers(0, 2**20), settled=st.booleans() if LONG else st.just(True))
    def start(self, seed: int, settled: bool) -> None:
        """``set_seed``, then every env reset (``pool.reset()``)."""
        self.settled = settled
        self.pool.set_seed(seed)
        self.envs = [EnvModel(Seeds(seed + i)) for i in range(self.n)]
        out = self._call(self.pool.reset)
        for i in range(self.n):
            expected = _copy(self._ref_reset(i)).set("env_index", torch.tensor(i))
            self.envs[i].status = READY
            assert_tensordict_equal(out[i], expected, msg=f"env {i}'s first reset")

    def teardown(self) -> None:
        """Receives (and checks) everything still under way. After a failure, the pool is closed, and rebuilt
        by the next sequence."""
        pool = self.pool
        if not pool.is_closed:
            pool._engine.warn_after, pool._engine.fail_after = LIMITS
        if self.broken:
            self._recover()
            return
        try:
            if self.coll is not None and self.coll.iterator is not None:
                self._call(self.coll.iterator.close)
                self.coll.iterator, self.coll.owns = None, True
            for kind in (STEP, STEP_RESET, RESET):
                envs = self._pending(kind)
                if envs:
                    self._receive(kind, dict(min_get=len(envs)), envs)
            # the pool's envs stepped what the collector kept: the lone envs too (the next sequence's resets
            # then start from the same history, see World)
            self._foreign(restart=False)
            assert pool._current_step == pool._current_step_reset == pool._current_reset == 0, "left under way"
        except BaseException:
            self._recover()
            raise

    def _recover(self) -> None:
        """After a failure: the pool is closed (the next sequence builds a new one, and new lone envs). What
        was under way is never received unchecked: the pool's envs would have stepped what the lone envs
        did not (see World)."""
        try:
            if self.coll is not None and self.coll.iterator is not None:
                self.coll.iterator, iterator = None, self.coll.iterator
                iterator.close()
        except Exception:  # noqa: BLE001 - the failure is the sequence's, already raised
            pass
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.pool.close(raise_if_closed=False)

    @invariant()
    def nothing_lost_or_duplicated(self) -> None:
        """TorchRL's counts of the calls under way are the model's."""
        if not self.envs or self.broken:
            return
        self.broken = True
        pool = self.pool
        counts = (pool._current_step, pool._current_step_reset, pool._current_reset)
        if self.coll is not None and self.coll.iterator is not None:
            assert counts[0] == counts[2] == 0 and counts[1] <= self.n
            self.broken = False
            return
        assert counts == tuple(len(self._pending(kind)) for kind in (STEP, STEP_RESET, RESET)), counts
        self.broken = False

    # ------------------------------------------------------------------ asynchronous steps
    @precondition(lambda self: self._free() and (self.coll is None or self.coll.iterator is None))
    @rule(data=st.data())
    @_rule
    def step_send(self, data) -> None:
        """``async_step_send`` / ``async_step_and_maybe_reset_send`` of some envs with nothing under way; those
        whose episode ended (an ``async_step_send``'s last step) are reset first (``async_reset_send``)."""
        self._foreign()
        envs = self._choose_envs(data, self._free(), "envs sent")
        self._reset_ended(envs)
        kind = data.draw(st.sampled_from([STEP, STEP_RESET]), label="kind")
        form = data.draw(st.sampled_from(["list", "tensor", "entry"] + (["int"] if len(envs) == 1 else [])))
        policy = data.draw(st.sampled_from(sorted(POLICIES)), label="policy")
        roots = data.draw(st.sampled_from(["full", "observation"]), label="root entries")
        td = torch.stack([self.envs[i].root for i in envs])
        if roots == "observation":
            td = td.select("observation")
        td = POLICIES[policy](td)
        if form == "entry":
            td.set("env_index", torch.tensor(envs))
        sent = _copy(td)
        if form == "int":
            td = td[0]
        send = self.pool.async_step_send if kind == STEP else self.pool.async_step_and_maybe_reset_send
        self._call(send, td, None if form == "entry" else self._index(form, envs))
        for j, i in enumerate(envs):
            row = sent[j]
            nxt, done = self._ref_step(i, row["action"])
            root = self._ref_reset(i) if kind == STEP_RESET and done else self.envs[i].root
            self.envs[i].pending = Pending(kind, row, nxt, root, done)
            self.envs[i].status = DONE if kind == STEP and done else READY

    @precondition(lambda self: self._pending(STEP) or self._pending(STEP_RESET) or self._pending(RESET))
    @rule(data=st.data())
    @_rule
    def receive(self, data) -> None:
        """A receive of what is under way: by ``min_get`` (with ``max_get``, ``timeout``) or by ``env_index``."""
        if self.settled:
            self._settle()
        kinds = [kind for kind in (STEP, STEP_RESET, RESET) if self._pending(kind)]
        kind = data.draw(st.sampled_from(kinds), label="kind")
        under_way = self._pending(kind)
        if data.draw(st.booleans(), label="by env_index"):
            envs = self._choose_envs(data, under_way, "envs received")
            form = data.draw(st.sampled_from(["list", "tensor"] + (["int"] if len(envs) == 1 else [])))
            self._receive(kind, dict(env_index=self._index(form, envs)), envs)
        else:
            args = {}
            if data.draw(st.booleans(), label="min_get given"):
                args["min_get"] = data.draw(st.integers(1, len(under_way)), label="min_get")
            low = args.get("min_get", self.pool.min_get)
            if data.draw(st.booleans(), label="max_get given"):
                args["max_get"] = data.draw(st.integers(low, len(under_way)), label="max_get")
            if data.draw(st.booleans(), label="timeout given"):
                args["timeout"] = data.draw(st.sampled_from([0.0, 0.01, 0.2]), label="timeout")
            self._receive(kind, args, None)
        if not self.settled and self._pending(kind):
            # Which envs came is the machine's: the rest of this kind are received too (by env_index), so that
            # what is under way after this rule, and so what hypothesis draws next, does not depend on timing.
            rest = self._pending(kind)
            self._receive(kind, dict(env_index=rest), rest)

    def _settle(self) -> None:
        """Waits for the answers of every call under way and reads them in env order, so that a receive
        returns the same envs whatever the timing (min_get / max_get take the first to arrive)."""
        engine = self.pool._engine
        for i, env in enumerate(self.envs):
            if env.pending is not None:
                while not engine.answered(i):
                    engine.wait_readable(i, 0.05)

    def _receive(self, kind: str, args: dict, envs: list[int] | None) -> None:
        pool = self.pool
        call = {STEP: pool.async_step_recv, STEP_RESET: pool.async_step_and_maybe_reset_recv}.get(
            kind, pool.async_reset_recv
        )
        under_way = self._pending(kind)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                out = self._call(call, receive=True, **args)
            except TimeoutError:
                assert "timeout" in args, "a TimeoutError without a timeout"
                self.arrivals.append(f"{kind}_recv({args}): TimeoutError")
                return  # what arrived is kept for the next call: the next receives check it
        one = isinstance(args.get("env_index"), int)
        if kind == STEP_RESET:
            transitions, roots = out
        else:
            transitions, roots = (out, None) if kind == STEP else (None, out)
        if one:
            transitions = None if transitions is None else transitions.unsqueeze(0)
            roots = None if roots is None else roots.unsqueeze(0)
        got = (transitions if transitions is not None else roots).get("env_index").tolist()
        if envs is None:
            self.arrivals.append(f"{kind}_recv({args}): {got}")
        assert got == sorted(set(got)), f"rows not in env order, or an env received twice: {got}"
        assert set(got) <= set(under_way), f"received {got}, of which only {under_way} had a {kind} under way"
        if envs is not None:
            assert sorted(got) == sorted(envs), f"asked for {envs}, received {got}"
        else:
            low, high = args.get("min_get", pool.min_get), args.get("max_get", len(under_way))
            assert low <= len(got) <= high, f"{len(got)} received for min_get={low}, max_get={high}"
        mixed = False
        if transitions is not None:
            keys = [set(self.envs[i].pending.sent.keys(True, True)) for i in got]
            common = set.intersection(*keys)
            # the pool's warning leaves "env_index" out: a send by the "env_index" entry and one by argument
            # are the same data (the pool sets the entry on every transition)
            mixed = any(k - {"env_index"} != common - {"env_index"} for k in keys)
            for j, i in enumerate(got):
                self.world.stats["checked"] += 1
                p = self.envs[i].pending
                # the sent entries ("env_index" among them where it was one), with the env's index
                expected = p.sent.select(*common).set("env_index", torch.tensor(i)).set("next", p.next)
                assert_tensordict_equal(transitions[j], expected, msg=f"env {i}'s transition ({kind})")
        if roots is not None:
            for j, i in enumerate(got):
                p = self.envs[i].pending
                expected = _copy(p.root).set("env_index", torch.tensor(i))
                if kind == STEP_RESET:
                    expected.set("action", p.sent["action"])
                assert_tensordict_equal(roots[j], expected, msg=f"env {i}'s next root ({kind})")
        told = [w for w in caught if "sent different entries" in str(w.message)]
        assert bool(told) == mixed, f"mixed entries {mixed}, warned {[str(w.message) for w in told]}"
        for i in got:
            self.envs[i].pending = None

    # ------------------------------------------------------------------ resets
    @precondition(lambda self: self.coll is None or self.coll.iterator is None)
    @rule(data=st.data())
    @_rule
    def reset_send(self, data) -> None:
        """``async_reset_send`` of some envs with nothing under way."""
        idle = [i for i, env in enumerate(self.envs) if env.pending is None]
        if not idle:
            return
        envs = self._choose_envs(data, idle, "envs reset")
        form = data.draw(st.sampled_from(["list", "tensor", "entry"] + (["int"] if len(envs) == 1 else [])))
        self._foreign()
        if form == "entry":
            self._call(self.pool.async_reset_send, TensorDict({"env_index": torch.tensor(envs)}, [len(envs)]))
        else:
            self._call(self.pool.async_reset_send, env_index=self._index(form, envs))
        for i in envs:
            self.envs[i].pending = Pending(RESET, root=self._ref_reset(i))
            self.envs[i].status = READY

    @precondition(lambda self: self._idle())
    @rule(data=st.data())
    @_rule
    def sync_reset(self, data) -> None:
        """``pool.reset()``, or ``pool.reset(TensorDict({"_reset": mask}))``: the envs of the mask only."""
        mask = data.draw(st.lists(st.booleans(), min_size=self.n, max_size=self.n), label="_reset mask")
        if data.draw(st.booleans(), label="whole reset"):
            mask = [True] * self.n
        self._foreign(restart=any(mask))  # a mask of no env resets none: not another caller's use
        if all(mask):
            out = self._call(self.pool.reset, receive=True)
        else:
            reset = TensorDict({"_reset": torch.tensor(mask).reshape(self.n, 1)}, [self.n])
            out = self._call(self.pool.reset, reset, receive=True)
        assert out.batch_size == (self.n,)
        for i in range(self.n):
            if mask[i]:
                expected = _copy(self._ref_reset(i)).set("env_index", torch.tensor(i))
                self.envs[i].status = READY
                assert_tensordict_equal(out[i], expected, msg=f"env {i}'s reset")

    # ------------------------------------------------------------------ sync steps
    @precondition(lambda self: self._idle() and self.envs)
    @rule(data=st.data())
    @_rule
    def sync_step(self, data) -> None:
        """``pool.step(td)`` or ``pool.step_and_maybe_reset(td)``: every env together (those whose episode
        ended reset first)."""
        autoreset = data.draw(st.booleans(), label="step_and_maybe_reset")
        policy = data.draw(st.sampled_from(sorted(POLICIES)), label="policy")
        self._foreign()
        self._reset_ended(list(range(self.n)))
        td = POLICIES[policy](torch.stack([env.root for env in self.envs]))
        sent = _copy(td)
        if autoreset:
            transitions, roots = self._call(self.pool.step_and_maybe_reset, td, receive=True)
        else:
            transitions, roots = self._call(self.pool.step, td, receive=True), None
        assert transitions.get("env_index").tolist() == list(range(self.n)), "a sync step's rows are in env order"
        for i in range(self.n):
            nxt, done = self._ref_step(i, sent[i]["action"])
            self.envs[i].status = DONE if done and not autoreset else READY
            self.world.stats["checked"] += 1
            expected = _copy(sent[i]).set("env_index", torch.tensor(i)).set("next", nxt)
            assert_tensordict_equal(transitions[i], expected, msg=f"env {i}'s transition (sync)")
            if autoreset:
                root = self._ref_reset(i) if done else self.envs[i].root
                expected = _copy(root).set("env_index", torch.tensor(i)).set("action", sent[i]["action"])
                assert_tensordict_equal(roots[i], expected, msg=f"env {i}'s next root (sync)")

    # ------------------------------------------------------------------ TorchRL's TransformedEnv
    def _transformed_reset(self) -> None:
        """``TransformedEnv(pool, Compose(StepCounter(), RewardSum())).reset()``."""
        td = self._call(self.world.tenv.reset, receive=True)
        for i in range(self.n):
            expected = _copy(self._ref_reset(i)).set("env_index", torch.tensor(i))
            self.envs[i].status = READY
            expected.set("step_count", torch.zeros(1, dtype=torch.int64)).set("episode_reward", torch.zeros(1))
            assert_tensordict_equal(td[i], expected, msg=f"env {i}'s reset (TransformedEnv)")
        self.session = td

    def _transformed_partial_reset(self, mask: list[bool]) -> None:
        """``tenv.reset(roots)`` with a ``"_reset"`` mask: TorchRL keeps the other envs' roots."""
        td = _copy(self.session).set("_reset", torch.tensor(mask).reshape(self.n, 1))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # TorchRL's set_state transition warning
            out = self._call(self.world.tenv.reset, td, receive=True)
        for i in range(self.n):
            env = self.envs[i]
            if mask[i]:
                self._ref_reset(i)
            root = _copy(env.root).set("step_count", torch.tensor([env.steps])).set("episode_reward", env.reward)
            got = out[i].select(*root.keys(True, True))
            assert_tensordict_equal(got, root, msg=f"env {i}'s root after a partial reset (TransformedEnv)")
        self.session = out.exclude("_reset")

    @precondition(lambda self: self._idle() and self.envs)
    @rule(data=st.data())
    @_rule
    def transformed(self, data) -> None:
        """``TransformedEnv(pool, Compose(StepCounter(), RewardSum()))``: a reset (unless its session goes on),
        maybe a partial reset through ``"_reset"`` (so that the envs' episodes end apart), then some of its
        ``step_and_maybe_reset``: an env whose episode ends is reset through TorchRL's partial ``"_reset"``,
        the others go on (their StepCounter and RewardSum too)."""
        if self.session is None or data.draw(st.booleans(), label="reset first"):
            self._foreign()
            self._transformed_reset()
        mask = data.draw(st.lists(st.booleans(), min_size=self.n, max_size=self.n), label="partial reset mask")
        if any(mask):
            self._transformed_partial_reset(mask)
        for _ in range(data.draw(st.integers(1, 6), label="steps")):
            self._transformed_step(data.draw(st.sampled_from(sorted(POLICIES)), label="policy"))

    def _transformed_step(self, policy: str) -> None:
        td = POLICIES[policy](self.session)
        sent = _copy(td)
        out, nxt = self._call(self.world.tenv.step_and_maybe_reset, td, receive=True)
        for i in range(self.n):
            env = self.envs[i]
            steps = env.steps
            step, done = self._ref_step(i, sent[i]["action"])
            self.world.stats["checked"] += 1
            step.set("step_count", torch.tensor([steps + 1])).set("episode_reward", env.reward)
            expected = _copy(sent[i]).set("next", step)
            assert_tensordict_equal(out[i], expected, msg=f"env {i}'s transition (TransformedEnv)")
            env.status = READY
            root = _copy(self._ref_reset(i) if done else env.root)
            root.set("step_count", torch.tensor([env.steps])).set("episode_reward", env.reward)
            got = nxt[i].select(*root.keys(True, True))
            assert_tensordict_equal(got, root, msg=f"env {i}'s next root (TransformedEnv)")
        self.session = nxt

    # ------------------------------------------------------------------ the collector
    def _collector_step(self, i: int, coll: CollectorModel) -> TensorDictBase:
        """Env ``i``'s next transition under the collector's policy, from its lone env."""
        env = self.envs[i]
        steps = env.steps
        td = _copy(env.root).set("env_index", torch.tensor(i))
        td = POLICIES[coll.policy](td.unsqueeze(0))[0]
        td.set("step_count", torch.tensor([steps]))
        nxt, done = self._ref_step(i, td["action"])
        nxt.set("step_count", torch.tensor([steps + 1]))
        td.set("next", nxt)
        if done:
            self._ref_reset(i)
        return td

    @precondition(lambda self: self.envs and all(env.pending is None for env in self.envs))
    @rule(data=st.data())
    @_rule
    def collect(self, data) -> None:
        """An iteration of an AsyncPoolCollector (a new one, or the last one again): some batches, then the
        iterator closed (the collector drains the pool) or held open (steps under way)."""
        coll = self.coll
        if coll is not None and coll.iterator is not None:
            if data.draw(st.booleans(), label="close the iterator"):
                self._call(coll.iterator.close, receive=True)
                coll.iterator, coll.owns = None, True
                return
            self._batch(coll, self._call(next, coll.iterator, receive=True))
            return
        if coll is None or data.draw(st.booleans(), label="a new collector"):
            self._foreign()  # the old one's transitions not yielded are the lone envs' still
            fpb = data.draw(st.sampled_from([1, 2, 3, 5, 8, 13]), label="frames_per_batch")
            min_get = data.draw(st.integers(1, self.n), label="min_get")
            policy = data.draw(st.sampled_from(sorted(POLICIES)), label="policy")
            if coll is not None:
                for env in self.envs:
                    env.queue.clear()  # the old collector's, never yielded
            collector = AsyncPoolCollector(self.pool, POLICIES[policy], frames_per_batch=fpb, min_get=min_get)
            self.coll = coll = CollectorModel(collector, policy, fpb, min_get)
        if not coll.running or coll.restart:  # every env starts an episode: its lone env resets
            for i in range(self.n):
                queue = self.envs[i].queue
                if queue and not queue[-1]["next", "done"].item():
                    # the restart cuts this episode: its last kept transition is marked truncated
                    queue[-1].set(("next", "truncated"), torch.tensor([True]))
                    queue[-1].set(("next", "done"), torch.tensor([True]))
                self._ref_reset(i)
                if not queue:  # else its kept transitions come first, in their trajectory
                    coll.traj_of.pop(i, None)
            coll.running, coll.restart = True, False
        for env in self.envs:
            env.status = OWNED
        self.session = None
        coll.iterator = iter(coll.collector)
        for _ in range(data.draw(st.integers(1, 3), label="batches")):
            self._batch(coll, self._call(next, coll.iterator, receive=True))
        if data.draw(st.booleans(), label="hold the iterator open"):
            return
        self._call(coll.iterator.close, receive=True)
        coll.iterator, coll.owns = None, True

    def _batch(self, coll: CollectorModel, batch: TensorDictBase) -> None:
        assert batch.batch_size == (coll.frames_per_batch,)
        ids = batch.get(("collector", "traj_ids"))
        self.arrivals.append(f"collector batch: {batch.get('env_index').tolist()}")
        assert (ids[1:] >= ids[:-1]).all(), f"trajectory ids not sorted: {ids.tolist()}"
        for t in range(coll.frames_per_batch):
            row = batch[t]
            i = int(row["env_index"])
            env = self.envs[i]
            expected = env.queue.popleft() if env.queue else self._collector_step(i, coll)
            assert_tensordict_equal(
                row.exclude(*MARKS), expected, msg=f"env {i}'s transition (collector, row {t} of the batch)"
            )
            self.world.stats["checked"] += 1
            # An env's trajectory id stays the same through its episode; its next episode has a new one.
            traj = int(ids[t])
            if i in coll.traj_of:
                assert traj == coll.traj_of[i], f"env {i}: trajectory id {traj} mid-episode ({coll.traj_of[i]} before)"
            else:
                assert traj not in coll.traj_env, f"env {i}: a new episode with the used trajectory id {traj}"
            coll.traj_env[traj] = i
            coll.traj_of[i] = traj
            if expected["next", "done"].item():
                del coll.traj_of[i]

    # ------------------------------------------------------------------ pauses
    @precondition(
        lambda self: (
            self.pauses < MAX_PAUSES
            and (
                any(env.pending is not None for env in self.envs)
                or (self.coll is not None and self.coll.iterator is not None)
            )
        )
    )
    @rule(data=st.data())
    @_rule
    def pause(self, data) -> None:
        """A pause longer than the watchdog's (lowered) fail_after with calls under way (a learner's update
        between two batches), then a receive (the collector's next batch, or every env of a kind): it must
        neither warn nor fail, since the pool was not waited on."""
        self.pauses += 1
        self.world.stats["pauses"] += 1
        self.pool._engine.warn_after, self.pool._engine.fail_after = PAUSE_LIMITS
        self.lowered = True
        time.sleep(PAUSE_S)
        if self.coll is not None and self.coll.iterator is not None:
            self._batch(self.coll, self._call(next, self.coll.iterator, receive=True))
            return
        kind = data.draw(st.sampled_from([k for k in (STEP, STEP_RESET, RESET) if self._pending(k)]), label="kind")
        under_way = self._pending(kind)
        if self.settled:  # the other kinds' answers are read here too, in env order (their arrival order)
            self._call(self._settle)
        self._receive(kind, dict(min_get=len(under_way)), under_way)

    # ------------------------------------------------------------------ misuse: a clear error, nothing changed
    @precondition(lambda self: any(env.pending is not None for env in self.envs))
    @rule(data=st.data())
    @_rule
    def misuse(self, data) -> None:
        """A send to an env with a call under way, a receive of more than is under way, or of an env with
        nothing of that kind under way: TorchRL's error, and the pool as it was (the next calls check)."""
        busy = [i for i, env in enumerate(self.envs) if env.pending is not None]
        what = data.draw(st.sampled_from(["send to a busy env", "min_get too large", "receive an env not sent"]))
        pool = self.pool
        calls = {
            STEP: pool.async_step_recv,
            STEP_RESET: pool.async_step_and_maybe_reset_recv,
            RESET: pool.async_reset_recv,
        }
        if what == "send to a busy env":
            i = data.draw(st.sampled_from(busy), label="env")
            td = plain(_copy(self.envs[i].root).unsqueeze(0)) if self.envs[i].root is not None else None
            if td is None:
                return
            with pytest.raises(RuntimeError, match="under way"):
                self._call(pool.async_step_and_maybe_reset_send, td, [i])
        elif what == "min_get too large":
            kind = data.draw(st.sampled_from([STEP, STEP_RESET, RESET]), label="kind")
            count = len(self._pending(kind))
            with pytest.raises(RuntimeError, match="Cannot await|no .* under way"):
                self._call(calls[kind], min_get=count + 1)
        else:
            kind = data.draw(st.sampled_from([STEP, STEP_RESET, RESET]), label="kind")
            others = [i for i in range(self.n) if i not in self._pending(kind)]
            if not others:
                return
            i = data.draw(st.sampled_from(others), label="env")
            with pytest.raises(RuntimeError, match="under way"):
                self._call(calls[kind], env_index=[i])


# ----------------------------------------------------------------------------- the tests
CONFIGS = {"N3-repeat1": (3, 1, 4), "N2-repeat2": (2, 2, 5)}


@pytest.fixture(scope="module")
def worlds():
    made: dict[str, World] = {}
    yield made
    for world in made.values():
        world.close()


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_random_sequences_of_torchrls_calls_match_lone_envs(worlds, config):
    world = worlds.setdefault(config, World(*CONFIGS[config]))
    machine = type(f"PoolMachine_{config.replace('-', '_')}", (PoolMachine,), {"world": world})
    start = time.monotonic()
    try:
        run_state_machine_as_test(machine, settings=SETTINGS)
    finally:
        s = world.stats
        line = (
            f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {config} profile={'long' if LONG else 'default'} "
            f"max_examples={EXAMPLES} steps={STEPS}: {s['sequences']} sequences, {s['rules']} rules, "
            f"{s['pool calls']} pool calls, {s['checked']} transitions checked, {s['episodes']} episodes, "
            f"{s['pauses']} pauses, {s['pools built']} pools built, {time.monotonic() - start:.1f} s"
        )
        SUMMARY.parent.mkdir(exist_ok=True)
        with SUMMARY.open("a") as f:
            f.write(line + "\n")
        print(line)
        print({k: (world.counts[k], round(v, 2)) for k, v in world.times.items()})
