"""The split-phase engine as TorchRL's AsyncEnvPool, and the collector that drives it out of lockstep.

The oracle is ManiSkill's own ``CPUGymWrapper`` (over its ``ActionRepeatWrapper`` for a repeat),
one lone env per env index, reset with the pool's seeds (``s + i``, then the draws of
``numpy.random.RandomState(s + i)``) and given the actions the pool's transitions of that
index recorded, in their order. Episodes of 5 steps, so that every env ends and restarts
several times while the others are mid-episode.
"""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
import torch
from mani_skill.utils.wrappers import ActionRepeatWrapper, CPUGymWrapper
from torchrl.envs import AsyncEnvPool

from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool, ManiSkillEnv
from maniskill_torchrl.engines.cpu_vector import in_process_default
from support.helpers import make_gym_env

N, SEED = 2, 7
PICK = dict(obs_mode="state", max_episode_steps=5)


@pytest.fixture(scope="module", params=[1, 2], ids=["repeat1", "repeat2"])
def repeat(request):
    return request.param


@pytest.fixture(scope="module")
def pool(repeat):
    pool = ManiSkillAsyncEnvPool("PickCube-v1", N, repeat=repeat, **PICK)
    yield pool
    pool.close(raise_if_closed=False)


def _reference(repeat: int):
    env = make_gym_env("PickCube-v1", **PICK)
    return CPUGymWrapper(ActionRepeatWrapper(env, repeat) if repeat > 1 else env)


def _bits(x) -> bytes:
    return np.ascontiguousarray(np.asarray(x)).tobytes()


def test_is_torchrls_async_env_pool(pool):
    assert isinstance(pool, AsyncEnvPool)
    assert pool.batch_size == (N,)
    assert pool.full_action_spec["action"].shape == (N, 8)
    assert "env_index" in pool.full_state_spec.keys()


def test_each_env_is_maniskills_cpu_gym_wrapper_bit_for_bit(pool, repeat):
    """Out of lockstep, per env index: the transitions of env i are a lone ManiSkill env's."""
    pool.set_seed(SEED)
    torch.manual_seed(0)
    collector = AsyncPoolCollector(pool, frames_per_batch=16, total_frames=32)
    data = torch.cat(list(collector))
    assert data.shape == (32,)
    ends = 0
    for i in range(N):
        mine = data[data["env_index"] == i]
        assert mine.shape[0] >= 8, "each env steps"
        ref = _reference(repeat)
        rng = np.random.RandomState(SEED + i)
        obs, _ = ref.reset(seed=SEED + i)
        for t in range(mine.shape[0]):
            step = mine[t]
            assert _bits(step["observation"].numpy()) == _bits(obs), f"env {i}, transition {t}: root observation"
            obs, reward, terminated, truncated, info = ref.step(step["action"].numpy())
            nxt = step["next"]
            assert _bits(nxt["observation"].numpy()) == _bits(obs), f"env {i}, transition {t}: next observation"
            assert _bits(nxt["reward"].numpy()) == _bits(np.float32([reward])), f"env {i}, transition {t}: reward"
            assert bool(nxt["terminated"]) == bool(terminated) and bool(nxt["truncated"]) == bool(truncated)
            assert bool(nxt["success"]) == bool(info["success"])
            if terminated or truncated:
                ends += 1
                obs, _ = ref.reset(seed=int(rng.randint(2**31)))
        ref.close()
    assert ends >= N, "every env ended an episode and restarted with its next seed"


def test_sync_calls_are_the_lockstep_env(pool, repeat):
    """reset / rollout through TorchRL's sync AsyncEnvPool calls: the batched env's own values."""
    if repeat > 1:
        pytest.skip("one repeat is enough here: the per-env oracle above covers the repeat")
    pool.set_seed(SEED)
    got = pool.rollout(3, break_when_any_done=False)
    env = ManiSkillEnv("PickCube-v1", num_envs=N, in_process=False, sim_backend="cpu", **PICK)
    try:
        env.set_seed(SEED)
        td = env.reset()
        for t in range(3):
            td["action"] = got["action"][:, t]
            td = env.step(td)
            assert _bits(td["next", "observation"].numpy()) == _bits(got["next", "observation"][:, t].numpy())
            assert _bits(td["next", "reward"].numpy()) == _bits(got["next", "reward"][:, t].numpy())
            td = td["next"].exclude("reward")
    finally:
        env.close()
    assert (got["env_index"] == torch.arange(N).unsqueeze(-1)).all()


def test_torchrls_collector_drives_it_in_lockstep():
    from torchrl.collectors import Collector

    pool = ManiSkillAsyncEnvPool("PickCube-v1", N, **PICK)  # its own: the Collector's shutdown closes its env
    pool.set_seed(SEED)
    collector = Collector(pool, None, frames_per_batch=6 * N, total_frames=12 * N)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
        pool.close(raise_if_closed=False)
    assert [b.shape for b in batches] == [(N, 6), (N, 6)]
    assert batches[0]["next", "done"].any(), "5-step episodes end inside a batch of 6"


def test_receives_whichever_envs_are_done_and_keeps_them_on_timeout(pool):
    pool.set_seed(SEED)
    roots = pool.reset()
    roots["action"] = torch.zeros(N, 8)
    # Env 0's worker is stopped until the timeout has been seen: its step (milliseconds) cannot
    # finish before the checks below, however slow they run.
    worker = pool._engine._pool.processes[0]
    os.kill(worker.pid, signal.SIGSTOP)
    try:
        pool.async_step_send(roots[:1], env_index=[0])
        with pytest.raises(RuntimeError, match="Cannot await 2"):
            pool.async_step_recv(min_get=2)
        with pytest.raises(RuntimeError, match="still have a step under way"):
            pool.async_step_send(roots[:1], env_index=[0])
        with pytest.raises(RuntimeError, match=r"reset_send: sub-envs \[0\] still have a step under way"):
            pool.rollout(1)  # its reset, as TorchRL's pools refuse it
        with pytest.raises(RuntimeError, match="split-phase call pending"):  # the engine's, under it
            pool._engine.step(torch.zeros(N, 8))
        with pytest.raises(TimeoutError, match="kept for the next call"):
            pool.async_step_recv(min_get=1, timeout=0.0)
    finally:
        os.kill(worker.pid, signal.SIGCONT)
    out = pool.async_step_recv(min_get=1)
    assert out["env_index"].tolist() == [0]
    assert out["next", "observation"].shape == (1, 42)
    pool.async_step_send(roots, env_index=[0, 1])
    first = pool.async_step_recv(env_index=1)
    assert first.batch_size == () and first["env_index"].item() == 1, "an int env index: its unbatched result"
    second = pool.async_step_recv(min_get=1)
    assert second["env_index"].tolist() == [0]


def test_a_missing_action_says_what_to_set(pool):
    pool.set_seed(SEED)
    roots = pool.reset()
    with pytest.raises(KeyError, match="no 'action' entry"):
        pool.async_step_send(roots, env_index=[0, 1])


def test_a_dead_worker_is_an_error_and_a_closed_pool_never_a_hang():
    pool = ManiSkillAsyncEnvPool("PickCube-v1", N, **PICK)
    engine = pool._engine
    segment = engine._block.name
    processes = list(engine._pool.processes)
    pool.set_seed(SEED)
    roots = pool.reset()
    roots["action"] = torch.zeros(N, 8)
    os.kill(processes[1].pid, signal.SIGKILL)
    processes[1].join(10)
    with pytest.raises(RuntimeError, match=r"sub-env\(s\) \[1\] died"):
        pool.async_step_and_maybe_reset_send(roots, env_index=[0, 1])
        pool.async_step_and_maybe_reset_recv(min_get=N)
    assert engine._closed
    for process in processes:
        process.join(10)
        assert not process.is_alive()
    assert not os.path.exists(f"/dev/shm/{segment}"), "the shared block is unlinked"
    pool.close(raise_if_closed=False)


def test_bad_arguments_say_what_to_do():
    with pytest.raises(TypeError, match="obs_mode='rgb'"):
        ManiSkillAsyncEnvPool("PickCube-v1", N, from_pixels=True)
    with pytest.raises(ValueError, match="positive int"):
        ManiSkillAsyncEnvPool("PickCube-v1", 0)
    with pytest.raises(TypeError, match="drives an AsyncEnvPool"):
        AsyncPoolCollector(object(), frames_per_batch=4)


@pytest.mark.parametrize(
    ("cores", "num_envs", "expected"),
    [(2, 2, True), (2, 4, True), (16, 15, False), (16, 8, False), (16, 16, True), (1, 2, True), (16, 1, True)],
)
def test_in_process_is_decided_by_the_cores(monkeypatch, cores, num_envs, expected):
    """Sub-env 0 in the main process for one sub-env, else unless this process may use more cores than there
    are sub-envs."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)), raising=False)
    assert in_process_default(num_envs) is expected


def test_a_collector_left_mid_batch_then_closed_leaves_no_process_or_segment():
    pool = ManiSkillAsyncEnvPool("PickCube-v1", N, **PICK)
    engine = pool._engine
    segment, processes = engine._block.name, list(engine._pool.processes)
    collector = AsyncPoolCollector(pool, frames_per_batch=4)
    for _ in collector:
        break  # leaves steps under way: the collector receives them
    assert engine.pending == {}
    assert pool.rollout(2)["next", "observation"].shape == (N, 2, 42), "the pool steps in lockstep again"
    collector.shutdown()
    for process in processes:
        process.join(10)
        assert not process.is_alive()
    assert not os.path.exists(f"/dev/shm/{segment}")
