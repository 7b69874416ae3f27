"""The asynchronous path as a TorchRL collector maintainer uses it (issue 51, item 2).

Each test reproduces a finding of the review: mixed step kinds, unseeded pools, a stuck env,
TorchRL's receive rules, per-env receives from one thread per env, ``check_env_specs``,
trajectory ids and step counts, episodes across ``iter()``, ``RandomPolicy``,
``update_policy_weights_`` and a policy error. Workers are paused with SIGSTOP where a test needs
an env that has not answered: then no timing can make it pass by chance.
"""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest
import torch
from torchrl.collectors.utils import split_trajectories
from torchrl.envs.utils import check_env_specs
from torchrl.modules import RandomPolicy

from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool

N, EPISODE = 2, 4
PICK = dict(obs_mode="state", max_episode_steps=EPISODE)


@pytest.fixture(scope="module")
def pool():
    pool = ManiSkillAsyncEnvPool("PickCube-v1", N, **PICK)
    yield pool
    pool.close(raise_if_closed=False)


def _paused(pool, i: int):
    """A context in which env ``i``'s worker is stopped (SIGSTOP), continued on exit."""

    class _Pause:
        def __enter__(self):
            os.kill(pool._engine._pool.processes[i].pid, signal.SIGSTOP)

        def __exit__(self, *exc):
            os.kill(pool._engine._pool.processes[i].pid, signal.SIGCONT)

    return _Pause()


def _chain(data, env: int):
    """Env ``env``'s transitions chain: each root is the previous next unless an episode ended."""
    mine = data[data["env_index"] == env]
    done = mine["next", "done"].reshape(-1)
    linked = ~done[:-1]
    assert torch.equal(mine["next", "observation"][:-1][linked], mine["observation"][1:][linked])
    return mine


def test_without_set_seed_every_env_plays_its_own_episodes(pool):
    """Runs first, on a pool never seeded: the workers fork from one process with one RNG state."""
    first = pool.reset()["observation"]
    again = pool.reset()["observation"]
    assert not torch.equal(first[0], first[1]), "two envs started the same episode"
    assert not torch.equal(first, again), "a second reset repeated the first"


def test_mixed_step_kinds_are_received_by_their_own_call(pool):
    pool.set_seed(0)
    roots = pool.reset()
    roots["action"] = torch.zeros(N, 8)
    with _paused(pool, 1):
        pool.async_step_send(roots[0], env_index=0)
        pool.async_step_and_maybe_reset_send(roots[1:], env_index=[1])
        assert (pool._current_step, pool._current_step_reset) == (1, 1)
        # env 0's plain step is done, but it is not a step_and_maybe_reset: none of those is done
        with pytest.raises(TimeoutError):
            pool.async_step_and_maybe_reset_recv(min_get=1, timeout=0.3)
        plain = pool.async_step_recv(min_get=1)
        assert plain["env_index"].tolist() == [0] and pool._current_step == 0
    transitions, next_roots = pool.async_step_and_maybe_reset_recv(min_get=1)
    assert transitions["env_index"].tolist() == [1] and next_roots["env_index"].tolist() == [1]
    assert (pool._current_step, pool._current_step_reset) == (0, 0)
    assert pool.rollout(2)["next", "observation"].shape == (N, 2, 42), "nothing left under way"


def test_receive_rules_are_torchrls(pool):
    pool.set_seed(0)
    roots = pool.reset()
    roots["action"] = torch.zeros(N, 8)
    pool.async_step_send(roots, env_index=[0, 1])
    for kwargs, match in (
        (dict(min_get=0), "min_get must be positive"),
        (dict(min_get=2, max_get=1), "max_get must be greater"),
        (dict(min_get=1, timeout=-1.0), "timeout must be non-negative"),
        (dict(min_get=3), "Cannot await 3"),
    ):
        with pytest.raises((ValueError, RuntimeError), match=match):
            pool.async_step_recv(**kwargs)
    pool.async_step_recv(min_get=2)
    # Once min_get is met, a timeout keeps gathering until its deadline: env 1 answers 0.3 s late.
    with _paused(pool, 1):
        pool.async_step_send(roots, env_index=[0, 1])
        threading.Timer(0.3, os.kill, (pool._engine._pool.processes[1].pid, signal.SIGCONT)).start()
        out = pool.async_step_recv(min_get=1, timeout=20.0)
    assert out["env_index"].tolist() == [0, 1]


def test_per_env_loops_in_threads_as_torchrls_async_collector_runs_them(pool):
    """TorchRL's ``_env_loop``: one thread per env, int env indices, unbatched results."""
    pool.set_seed(3)
    results: dict[int, list] = {i: [] for i in range(N)}
    errors: list[BaseException] = []

    def loop(i: int) -> None:
        try:
            pool.async_reset_send(env_index=i)
            obs = pool.async_reset_recv(env_index=i)
            assert obs.batch_size == () and obs["env_index"].item() == i
            for _ in range(2 * EPISODE):
                obs["action"] = torch.rand(8) * 2 - 1
                pool.async_step_and_maybe_reset_send(obs, env_index=i)
                transition, obs = pool.async_step_and_maybe_reset_recv(env_index=i)
                assert transition.batch_size == () and obs.batch_size == ()
                results[i].append(transition)
        except BaseException as err:
            errors.append(err)

    threads = [threading.Thread(target=loop, args=(i,)) for i in range(N)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors, errors
    for i in range(N):
        data = torch.stack(results[i])
        assert (data["env_index"] == i).all()
        _chain(data, i)
        assert data["next", "done"].sum() == 2, "two episodes of EPISODE steps"


def test_check_env_specs(pool):
    check_env_specs(pool)


def test_trajectory_ids_and_step_counts_slice_episodes(pool):
    pool.set_seed(5)
    collector = AsyncPoolCollector(pool, frames_per_batch=4 * N)
    batches = []
    for batch in collector:  # until each env has started its second episode (one may lag on a busy machine)
        batches.append(batch)
        if (torch.cat(batches)["env_index"].bincount(minlength=N) > EPISODE).all() or len(batches) == 30:
            break
    data = torch.cat(batches)  # each env's transitions in order
    ids, steps = data["collector", "traj_ids"], data["step_count"].reshape(-1)
    assert torch.equal(data["next", "step_count"].reshape(-1), steps + 1)
    for i in range(N):
        mine = _chain(data, i)
        mine_ids, mine_steps = mine["collector", "traj_ids"], mine["step_count"].reshape(-1)
        assert mine_steps[:EPISODE].tolist() == list(range(EPISODE)) and mine_steps[EPISODE] == 0
        assert (mine_ids[:EPISODE] == i).all() and mine_ids[EPISODE] >= N, "a new id after the episode ended"
        ends = mine["next", "done"].reshape(-1)
        new_id = mine_ids[1:] != mine_ids[:-1]
        assert torch.equal(new_id, ends[:-1]), "an env's id changes exactly where its episode ended"
    assert len(set(ids.tolist())) == len(set(zip(data["env_index"].tolist(), ids.tolist()))), "ids are global"
    split = split_trajectories(batches[0])  # TorchRL's own, on ("collector", "traj_ids")
    assert split["collector", "mask"].sum() == len(batches[0])
    mask = split["collector", "mask"]
    assert (split["next", "done"].squeeze(-1) & mask).sum(-1).le(1).all(), "one episode per trajectory"
    env = split["env_index"]
    assert (env == env[:, :1])[mask].all(), "one env per trajectory"


def test_episodes_carry_on_across_iterations(pool):
    pool.set_seed(9)
    collector = AsyncPoolCollector(pool, frames_per_batch=3, total_frames=-1)
    batches = []
    for k in range(20):  # at least 3 iterations, and until an episode is under way at the end of one
        for batch in collector:  # one batch per iteration: each iter() stops with steps under way
            batches.append(batch)
            break
        assert pool._current_step_reset == 0, "the pool is idle between iterations"
        kept = collector._buffer[: collector._cursor]
        last = [(kept["env_index"] == i).nonzero().reshape(-1) for i in range(N)]
        if k >= 2 and any(len(j) and not kept["next", "done"][j[-1]].all() for j in last):
            break
    data = torch.cat(batches)
    assert len(data) == 3 * len(batches)
    for i in range(N):
        mine = _chain(data, i)
        steps = mine["step_count"].reshape(-1)
        assert (steps[1:] == torch.where(mine["next", "done"].reshape(-1)[:-1], 0, steps[:-1] + 1)).all()
    # A reset by another caller between iterations: the kept, unfinished episodes end truncated.
    kept = collector._buffer[: collector._cursor].clone()  # received, not yet yielded
    kept_ids = kept["collector", "traj_ids"]
    pool.reset()
    batches, got = iter(collector), []
    for batch in batches:  # the kept transitions, then each env's new episodes (one may lag on a busy machine)
        got.append(batch)
        seen = torch.cat(got)
        fresh = seen[seen["collector", "traj_ids"] > int(kept_ids.max())]
        if len(got) == 30 or len(fresh["env_index"].unique()) == N:
            break
    batches.close()
    nxt = torch.cat(got)
    cut = 0
    for i in range(N):
        mine = (kept["env_index"] == i).nonzero().reshape(-1)
        if not len(mine) or kept["next", "done"][mine[-1]].all():
            continue
        old = nxt[nxt["collector", "traj_ids"] == int(kept_ids[mine[-1]])]
        assert old["next", "truncated"][-1].all() and old["next", "done"][-1].all(), f"env {i}'s episode was cut"
        assert not old["next", "done"][:-1].any()
        cut += 1
    assert cut, "an episode was under way when the pool was reset"
    fresh = nxt[nxt["collector", "traj_ids"] >= int(kept_ids.max()) + 1]
    for i in range(N):
        assert fresh[fresh["env_index"] == i]["step_count"].reshape(-1)[0] == 0, "every env restarted"


def test_random_policy_and_weight_updates_as_torchrls_collectors_take_them(pool):
    collector = AsyncPoolCollector(pool, RandomPolicy(pool.action_spec), frames_per_batch=4, total_frames=4)
    (data,) = list(collector)
    assert data["action"].shape == (4, 8) and data["action"].abs().le(1).all()
    collector.update_policy_weights_()  # no policy weights to move: nothing to do

    torch.manual_seed(0)
    net = torch.nn.Linear(42, 8)
    from tensordict.nn import TensorDictModule

    policy = TensorDictModule(net, in_keys=["observation"], out_keys=["action"])
    collector = AsyncPoolCollector(pool, policy, frames_per_batch=4, total_frames=4)
    collector.update_policy_weights_()
    trained = TensorDictModule(torch.nn.Linear(42, 8), in_keys=["observation"], out_keys=["action"])
    collector.update_policy_weights_(trained)
    assert torch.equal(net.weight, trained.module.weight)
    list(collector)


def test_a_policy_error_leaves_the_users_pool_open_and_idle(pool):
    calls = {"n": 0}

    def flaky(td):
        calls["n"] += 1
        if calls["n"] == 3:
            raise ValueError("policy bug")
        td["action"] = torch.zeros(*td.shape, 8)
        return td

    collector = AsyncPoolCollector(pool, flaky, frames_per_batch=100, total_frames=200)
    with pytest.raises(ValueError, match="policy bug"):
        list(collector)
    assert not pool.is_closed and pool._current_step_reset == 0
    batch = next(iter(collector))  # the collector goes on where it stopped
    assert batch.shape == (100,)


def test_the_collector_copies_straight_from_the_pool_and_drives_torchrls_pools_too(pool):
    """Its cycle writes each entry from the pool's rows into its buffer (planned once); a pool of
    TorchRL's own, through the public calls, gives batches of the same layout."""
    import functools

    from torchrl.envs import AsyncEnvPool

    from maniskill_torchrl import ManiSkillEnv

    pool.set_seed(1)
    ours = next(iter(AsyncPoolCollector(pool, frames_per_batch=8, total_frames=8)))
    assert pool._into is not None, "the planned copies are in use"
    make = functools.partial(ManiSkillEnv, "PickCube-v1", batch_size=[], **PICK)
    theirs_pool = AsyncEnvPool([make] * N, backend="threading")
    try:
        collector = AsyncPoolCollector(theirs_pool, frames_per_batch=8, total_frames=16)
        batches = list(collector)
    finally:
        theirs_pool.close()
    assert [b.shape for b in batches] == [(8,), (8,)]
    theirs = torch.cat(batches)
    assert set(theirs.keys(True, True)) == set(ours.keys(True, True))
    for i in range(N):
        _chain(theirs, i)


def test_a_stuck_env_is_a_warning_then_an_error_never_a_hang(pool):
    """Last: the pool is closed by the error. Env 1 stops a second into collection; env 0 goes on."""
    pool._engine.warn_after, pool._engine.fail_after = 0.5, 2.0
    collector = AsyncPoolCollector(pool, frames_per_batch=10**6)
    processes = list(pool._engine._pool.processes)
    stop = threading.Timer(1.0, os.kill, (processes[1].pid, signal.SIGSTOP))
    start = time.monotonic()
    stop.start()
    with pytest.warns(RuntimeWarning, match=r"sub-env\(s\) \[1\] have not answered"):
        with pytest.raises(RuntimeError, match=r"sub-env\(s\) \[1\].*did not answer"):
            for _ in collector:  # never yields: frames_per_batch is never reached
                pass
    assert time.monotonic() - start < 60
    assert pool._engine.closed
    for process in processes:
        process.join(10)
        assert not process.is_alive(), "the stuck worker was ended"
