"""The asynchronous path at its edges, as TorchRL's own consumers reach them (issue 59, item 1).

Each test reproduces a finding of the review and failed before its fix: partial resets through
TorchRL's ``"_reset"`` mask, entries left from an earlier policy, a user's pause between two
batches taken for stuck workers, the error of a stuck worker late by a SIGTERM it cannot act on,
``frames_per_batch`` below ``num_envs - 1``, a policy that edits a root entry in place, and foreign
steps between two iterations. Ctrl-C, a subprocess each, is in ``tests/examples/test_engine_interrupts.py``
(``make test-examples``).
"""

from __future__ import annotations

import os
import signal
import time
import warnings
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import StepCounter, TransformedEnv

from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool
from support.helpers import ENGINE_FILES, ctrl_c_after_a_length, ctrl_c_at_line, no_hang

N, EPISODE = 3, 4
PICK = dict(obs_mode="state", max_episode_steps=EPISODE)
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def pool():
    pool = ManiSkillAsyncEnvPool("PickCube-v1", N, **PICK)
    yield pool
    pool.close(raise_if_closed=False)


def _zeros(tensordict):
    """Zero actions (``tensordict``: the name TorchRL's rollout passes a plain callable's input by)."""
    tensordict.set("action", torch.zeros(tensordict.shape[0], 8))
    return tensordict


def _chained(data, env: int) -> None:
    """Env ``env``'s transitions chain (each root the previous next, unless an episode ended), and
    their step counts are ManiSkill's own ``elapsed_steps``: nothing is lost, doubled or reset unseen."""
    mine = data[data["env_index"] == env]
    assert mine.shape[0] > 0
    done = mine["next", "done"].reshape(-1)
    linked = ~done[:-1]
    assert torch.equal(mine["next", "observation"][:-1][linked], mine["observation"][1:][linked])
    assert torch.equal(mine["next", "step_count"].reshape(-1), mine["next", "elapsed_steps"].reshape(-1).long())


def test_a_partial_reset_resets_only_the_envs_asked(pool):
    """Env 1 restarts two steps after env 0, so their episodes end apart: TorchRL resets one with a
    partial mask and keeps the other's roots. Before the fix the pool reset every env: env 0's
    StepCounter read 3..6 while its sim had restarted (elapsed_steps 1, 2)."""
    pool.set_seed(3)
    env = TransformedEnv(pool, StepCounter())
    td = env.reset()
    for _ in range(2):
        _, td = env.step_and_maybe_reset(_zeros(td))
    td["_reset"] = torch.tensor([[False], [True], [False]])
    td = env.reset(td)
    assert td["step_count"].reshape(-1).tolist() == [2, 0, 2]
    assert td["elapsed_steps"].reshape(-1).tolist() == [2, 0, 2], "the envs not asked were not reset"
    rollout = env.rollout(3 * EPISODE, _zeros, auto_reset=False, tensordict=td, break_when_any_done=False)
    counts, elapsed = rollout["next", "step_count"].squeeze(-1), rollout["next", "elapsed_steps"].long()
    assert torch.equal(counts, elapsed), (counts, elapsed)
    assert counts[1].tolist() == [1, 2, 3, 4] * 3 and counts[0].tolist()[:3] == [3, 4, 1]


def test_the_pools_own_reset_takes_the_mask_too(pool):
    pool.set_seed(4)
    first = pool.reset()
    pool.step(_zeros(first))
    pool.reset(TensorDict({"_reset": torch.zeros(N, 1, dtype=torch.bool)}, [N]))
    again = pool.step(_zeros(pool.reset(TensorDict({"_reset": torch.tensor([[True], [False], [False]])}, [N]))))
    assert again["next", "elapsed_steps"].reshape(-1).tolist() == [1, 2, 2]


def test_only_the_entries_sent_come_back(pool):
    """Policy A writes ``action_log_prob``; policy B on the same pool writes only ``action``: B's
    transitions hold no ``action_log_prob`` (before: A's -7, raw calls and collectors alike)."""
    pool.set_seed(0)
    pool.async_reset_send(env_index=list(range(N)))
    roots = pool.async_reset_recv(min_get=N)
    _zeros(roots).set("action_log_prob", torch.full((N,), -7.0))
    pool.async_step_and_maybe_reset_send(roots, env_index=roots["env_index"])
    transitions, roots = pool.async_step_and_maybe_reset_recv(min_get=N)
    assert (transitions["action_log_prob"] == -7).all()
    pool.async_step_and_maybe_reset_send(_zeros(roots.exclude("action_log_prob")), env_index=roots["env_index"])
    transitions, _ = pool.async_step_and_maybe_reset_recv(min_get=N)
    assert "action_log_prob" not in transitions.keys()

    def policy_a(td):
        return _zeros(td).set("action_log_prob", torch.full((td.shape[0],), -7.0))

    first = AsyncPoolCollector(pool, policy_a, frames_per_batch=8, total_frames=8)
    assert all((batch["action_log_prob"] == -7).all() for batch in first)
    second = AsyncPoolCollector(pool, _zeros, frames_per_batch=8, total_frames=16)
    for batch in second:
        assert "action_log_prob" not in batch.keys()


def test_envs_sent_different_entries_and_received_together_keep_the_common_ones(pool):
    pool.set_seed(1)
    pool.async_reset_send(env_index=list(range(N)))
    roots = pool.async_reset_recv(min_get=N)
    pool.async_step_send(_zeros(roots[:1]).set("extra", torch.ones(1)), env_index=[0])
    pool.async_step_send(_zeros(roots[1:2]), env_index=[1])
    pool.async_step_send(_zeros(roots[2:]).set("extra", torch.ones(1)), env_index=[2])
    alone = pool.async_step_recv(env_index=2)
    assert alone["extra"] == 1  # received apart: what it was sent
    with pytest.warns(RuntimeWarning, match=r"different entries.*\['extra'\]"):
        together = pool.async_step_recv(min_get=2)
    assert together["env_index"].tolist() == [0, 1] and "extra" not in together.keys()
    assert torch.equal(together["observation"], roots["observation"][:2])


def test_a_pause_between_batches_is_never_stuck(pool):
    """The collector leaves every env's step under way at each yield; a learner's update longer
    than ``fail_after`` between two batches must neither warn nor close the pool."""
    engine = pool._engine
    limits = engine.warn_after, engine.fail_after
    engine.warn_after, engine.fail_after = 0.3, 0.6
    try:
        collector = AsyncPoolCollector(pool, _zeros, frames_per_batch=6, total_frames=18)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            for batch in collector:
                time.sleep(1.0)  # the learner
                assert batch.shape == (6,)
        assert not engine.closed
    finally:
        engine.warn_after, engine.fail_after = limits


def test_a_stuck_worker_fails_at_fail_after_not_later(monkeypatch):
    """A stopped worker cannot act on SIGTERM: the watchdog SIGKILLs it when the error is raised (before,
    ``close()`` sent it SIGTERM and waited 5 s more). Checked by what the pool does, not by the clock: the
    stuck worker's position goes to ``WorkerPool.kill`` before anything closes the pool."""
    from maniskill_torchrl.engines._pool import WorkerPool

    calls: list = []
    kill, close = WorkerPool.kill, WorkerPool.close
    monkeypatch.setattr(
        WorkerPool, "kill", lambda self, positions: (calls.append(("kill", list(positions))), kill(self, positions))[1]
    )
    monkeypatch.setattr(WorkerPool, "close", lambda self, *a, **k: (calls.append(("close",)), close(self, *a, **k))[1])
    pool = ManiSkillAsyncEnvPool("PickCube-v1", 2, fail_after=1.0, **PICK)
    try:
        pool.set_seed(0)
        pool.async_reset_send(env_index=[0, 1])
        roots = pool.async_reset_recv(min_get=2)
        position = pool._engine._pool.indices.index(1)
        worker = pool._engine._pool.processes[position]
        os.kill(worker.pid, signal.SIGSTOP)
        pool.async_step_send(_zeros(roots), env_index=[0, 1])
        with pytest.raises(RuntimeError, match=r"sub-env\(s\) \[1\].*did not answer for 1 s"):
            pool.async_step_recv(min_get=2)
        assert calls and calls[0] == ("kill", [position]), f"the pool's calls: {calls}"
        worker.join(30)
        assert worker.exitcode == -signal.SIGKILL
    finally:
        pool.close(raise_if_closed=False)


@pytest.mark.parametrize("min_get", [1, N])
def test_any_frames_per_batch_drains_without_loss(pool, min_get):
    """``frames_per_batch=1`` with ``N=3``, left after each first batch: the transitions kept and
    the three steps under way outnumbered the buffer's room (before: ``ValueError`` from
    ``ndarray.take`` with ``min_get=N``, now and then with ``min_get=1``; the drained transitions
    lost). Every kept transition comes out later, in its episode's order."""
    pool.set_seed(2)
    collector = AsyncPoolCollector(pool, _zeros, frames_per_batch=1, min_get=min_get)
    first = []
    for _ in range(4):  # each iteration keeps more than it yields (the third overflowed, found by the model)
        iterator = iter(collector)
        first.append(next(iterator))
        iterator.close()  # its steps under way drained and kept
    kept = collector._cursor
    assert kept > N
    collector.total_frames = 4 + 8 + kept
    second = list(collector)
    assert len(second) == 8 + kept
    data = torch.cat(first + second)
    for i in range(N):
        _chained(data, i)


def test_a_policy_that_edits_a_root_in_place_is_stored_edited(pool):
    """TorchRL stores the policy's output tensordict: a root entry the policy edits in place is
    stored edited, every transition (before: only on the collector's first, slow receives)."""
    pool.set_seed(5)

    def policy(td):
        td.get("observation").add_(1000.0)
        return _zeros(td)

    data = torch.cat(list(AsyncPoolCollector(pool, policy, frames_per_batch=12, total_frames=24)))
    for i in range(N):
        mine = data[data["env_index"] == i]
        linked = ~mine["next", "done"].reshape(-1)[:-1]
        assert torch.equal(mine["next", "observation"][:-1][linked] + 1000.0, mine["observation"][1:][linked])


def test_foreign_steps_between_iterations_restart_the_episodes(pool):
    """``async_step_and_maybe_reset_send`` by another caller between two iterations counts as
    foreign use, as the other calls do: each env's kept transition ends truncated and its
    episode restarts (step count 0), instead of going on from roots the envs have left."""
    pool.set_seed(6)
    collector = AsyncPoolCollector(pool, _zeros, frames_per_batch=2 * N, total_frames=2 * N, min_get=N)
    list(collector)
    assert collector._cursor == N, "one kept transition per env (the drain)"
    roots = collector._held[0]  # the pool is idle, its envs ready for their next step
    pool.async_step_and_maybe_reset_send(_zeros(roots.clone()), env_index=roots["env_index"])
    pool.async_step_and_maybe_reset_recv(min_get=N)
    collector.total_frames = 4 * N
    (batch,) = list(collector)
    for i in range(N):
        mine = batch[batch["env_index"] == i]
        assert mine["next", "truncated"][0].item() and mine["step_count"][1].item() == 0


def test_ctrl_c_inside_the_read_of_an_answer_leaves_the_pipe_whole(pool, monkeypatch):
    """A Ctrl-C inside ``recv_bytes``, between a worker's answer's 4-byte length and its body, comes once the
    answer is read and noted. Before the fix the KeyboardInterrupt left the body in the pipe; the next read
    (the collector's drain after Ctrl-C) took it for a length and waited forever for bytes no worker sends:
    the likeliest cause of the one hang of the Ctrl-C example test (tests/examples/test_engine_interrupts.py)."""
    pool.set_seed(0)
    roots = pool.reset()
    pool.async_step_and_maybe_reset_send(_zeros(roots), env_index=[0, 1, 2])
    engine = pool._engine
    pipe = engine._pool.pipes[engine._pool.indices.index(1)]
    with ctrl_c_after_a_length(pipe, monkeypatch) as reads:
        with pytest.raises(KeyboardInterrupt):
            pool.async_step_and_maybe_reset_recv(env_index=[1])
        transitions, _ = pool.async_step_and_maybe_reset_recv(min_get=N)  # the drain: before the fix, a hang
    assert reads[:2] == [4, 1], reads  # the KeyboardInterrupt came after the body, not between
    assert transitions["env_index"].tolist() == [0, 1, 2]
    assert pool._current_step_reset == 0 and not pipe.poll(0)


def test_ctrl_c_at_any_line_of_a_cycle_leaves_the_pool_whole(pool):
    """A Ctrl-C at each line, in turn, of a send and a receive of every env (the pool's lines, the engine's,
    ``multiprocessing``'s pipe reads): afterwards the drain a collector makes returns, nothing is under way and
    no answer is left in a pipe. Before the fix, one between an answer's length and its body left the body in
    the pipe and the drain hung (cut here by SIGALRM); one between a read and its bookkeeping left an answer
    read but not noted, which a drain waits for forever."""
    engine = pool._engine
    files = (*ENGINE_FILES, "maniskill_torchrl/envs/async_pool.py")
    sent = TensorDict({"action": torch.zeros(N, 8)}, [N])
    pool.set_seed(0)
    pool.reset()

    def cycle() -> None:
        pool.async_step_and_maybe_reset_send(sent.clone(), env_index=list(range(N)))
        pool.async_step_and_maybe_reset_recv(min_get=N)

    cycle()  # the first send makes the pool's rows
    with ctrl_c_at_line(0, files) as counted:
        cycle()
    lines, interrupted = counted[0], 0
    for line in range(1, lines + 1):
        with no_hang(10.0):
            with ctrl_c_at_line(line, files):
                try:
                    cycle()
                except KeyboardInterrupt:
                    interrupted += 1
            if pool._current_step_reset:  # AsyncPoolCollector's drain after Ctrl-C
                pool.async_step_and_maybe_reset_recv(min_get=pool._current_step_reset)
        left = [i for i, pipe in enumerate(engine._pool.pipes) if pipe.poll(0)]
        assert not engine.pending and not left, f"a Ctrl-C at line {line} of {lines}: {engine.pending}, pipes {left}"
    assert interrupted >= lines - 50, (interrupted, lines)  # a cycle's lines vary a little (what select finds)
    cycle()
