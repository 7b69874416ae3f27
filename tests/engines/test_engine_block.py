"""The CPU engine's shared-memory block and pipes (``engines/_shared.py``, ``engines/_pool.py``).

What the engine's other tests (``test_cpu_vector.py``: bit-exact against raw ManiSkill envs,
partial resets, seeding, saved states, failures) cannot see: that a step crosses each pipe as
one byte each way, that outputs are fresh copies of the block, that the block's layout holds
any space ManiSkill gives (nested dicts, every dtype), that a worker's make error is raised as
itself, and that no shared-memory segment outlives the env.
"""

from __future__ import annotations

import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from maniskill_torchrl import CPUVectorEnv
from maniskill_torchrl.engines._shared import Layout, SharedBlock
from maniskill_torchrl.engines._worker import DONE, STEP

SHM = Path("/dev/shm")


class _Recorder:
    """A worker's pipe, recording what the parent sends and receives on it."""

    def __init__(self, pipe, log: list) -> None:
        self._pipe, self._log = pipe, log

    def send_bytes(self, data: bytes) -> None:
        self._log.append(("send", bytes(data)))
        self._pipe.send_bytes(data)

    def recv_bytes(self) -> bytes:
        data = self._pipe.recv_bytes()
        self._log.append(("recv", data))
        return data

    def __getattr__(self, name: str):
        return getattr(self._pipe, name)


@pytest.fixture(scope="module")
def pick():
    env = CPUVectorEnv("PickCube-v1", 3, obs_mode="state_dict", max_episode_steps=20)
    yield env
    env.close()


def test_a_step_is_one_byte_each_way(pick):
    pick.reset(seed=0)
    log: list = []
    pipes = pick._pool.pipes
    pick._pool.pipes = [_Recorder(p, log) for p in pipes]
    try:
        for _ in range(3):
            pick.step(torch.zeros(3, 8))
    finally:
        pick._pool.pipes = pipes
    assert log.count(("send", STEP)) == 3 * 2 and log.count(("recv", DONE)) == 3 * 2
    assert len(log) == 12, log


def test_outputs_are_fresh_copies(pick):
    """What a step returned is not rewritten by the next one (it is not a view of the block)."""
    pick.reset(seed=1)
    gen = torch.Generator().manual_seed(0)
    first = pick.step(torch.rand(3, 8, generator=gen) * 2 - 1)
    kept = (first[0]["agent"]["qpos"].clone(), first[1].clone(), first[4]["elapsed_steps"].clone())
    pick.step(torch.rand(3, 8, generator=gen) * 2 - 1)
    assert torch.equal(first[0]["agent"]["qpos"], kept[0])
    assert torch.equal(first[1], kept[1]) and torch.equal(first[4]["elapsed_steps"], kept[2])
    block = pick._block.tensor
    lo, hi = block.data_ptr(), block.data_ptr() + block.numel()
    assert not lo <= first[1].data_ptr() < hi, "the reward is a view of the shared block"


def test_a_wrong_action_shape_is_refused(pick):
    pick.reset(seed=0)
    with pytest.raises(ValueError, match=r"action of shape \(1, 8\), expected \(3, 8\)"):
        pick.step(torch.zeros(1, 8))  # numpy would broadcast it to every sub-env
    assert pick.step(torch.zeros(3, 8))[1].shape == (3,)


SPACES = {
    "box": (
        gym.spaces.Box(-1, 1, (3,), np.float32),
        gym.spaces.Dict(
            {
                "obs": gym.spaces.Dict(
                    {
                        "qpos": gym.spaces.Box(-1, 1, (9,), np.float32),
                        "rgb": gym.spaces.Box(0, 255, (4, 5, 3), np.uint8),
                        "depth": gym.spaces.Box(0, 10, (4, 5, 1), np.int16),
                    }
                ),
                "info": gym.spaces.Dict(
                    {"elapsed": gym.spaces.Box(0, 9, (), np.int32), "x": gym.spaces.Box(0, 1, (), np.float64)}
                ),
                "reward": gym.spaces.Box(-1, 1, (), np.float32),
                "terminated": gym.spaces.Box(0, 1, (), np.bool_),
            }
        ),
    ),
    "dict-actions": (
        gym.spaces.Dict(
            {"a-0": gym.spaces.Box(-1, 1, (8,), np.float32), "a-1": gym.spaces.Box(-1, 1, (7,), np.float64)}
        ),
        gym.spaces.Dict({"obs": gym.spaces.Box(-1, 1, (5,), np.float32), "flag": gym.spaces.Box(0, 1, (2,), np.bool_)}),
    ),
}


@pytest.mark.parametrize("name", sorted(SPACES))
@pytest.mark.parametrize("n", [1, 3])
def test_block_round_trip(name, n):
    """Rows written by sub-env ``i`` (any dtype, nested) come back at row ``i`` of the batch read;
    actions written for the batch come back per row, each leaf at its own dtype."""
    action_space, result_space = SPACES[name]
    parent = SharedBlock(Layout(result_space, action_space, n))
    worker = SharedBlock(parent.layout, parent.name)  # as a worker attaches it
    try:
        result_space.seed(0)
        action_space.seed(1)
        rows = [result_space.sample() for _ in range(n)]
        for i, row in enumerate(rows):
            worker.write_row(i, row)
        batch = parent.read()
        actions = [action_space.sample() for _ in range(n)]
        stacked = (
            {k: np.stack([a[k] for a in actions]) for k in actions[0]}
            if isinstance(action_space, gym.spaces.Dict)
            else np.stack(actions)
        )
        parent.write_actions(stacked)

        def check(got, want_rows, path=()):
            if isinstance(want_rows[0], dict):
                assert set(got) == set(want_rows[0]), path
                for k in want_rows[0]:
                    check(got[k], [r[k] for r in want_rows], (*path, k))
                return
            want = torch.from_numpy(np.stack([np.asarray(r) for r in want_rows]))
            assert got.dtype == want.dtype and got.shape == want.shape, path
            assert torch.equal(got, want), path

        check(batch, rows)
        for i, action in enumerate(actions):
            got = worker.action_row(i)
            if isinstance(action, dict):
                assert all(got[k].dtype == action[k].dtype and np.array_equal(got[k], action[k]) for k in action)
            else:
                assert got.dtype == action.dtype and np.array_equal(got, action)
    finally:
        worker.close()
        parent.close()


def test_a_worker_make_error_is_raised_as_itself():
    """With every sub-env in a worker, ManiSkill's own error reaches the caller as it would from
    ``gym.make`` here (not a generic one)."""
    with pytest.raises(AssertionError, match="Invalid texture type 'nonsense'"):
        CPUVectorEnv("PickCube-v1", 2, in_process=False, obs_mode="nonsense")


@pytest.mark.skipif(not SHM.is_dir(), reason="shared-memory segments are listed in /dev/shm on Linux only")
def test_no_segment_outlives_the_env():
    """Closing the env (and a worker's failure, which closes it) unlinks its shared block."""
    env = CPUVectorEnv("PickCube-v1", 2, obs_mode="state", trace_steps=4)
    # the env's own segments only: under pytest-xdist other tests make and unlink theirs meanwhile
    own = {env._block.name.lstrip("/"), env._trace._shm.name.lstrip("/")}
    assert own <= set(os.listdir(SHM))
    env.reset(seed=0)
    with pytest.raises(RuntimeError, match=r"worker\(s\) of sub-env\(s\) \[1\] raised AttributeError"):
        env.call("no_such_method")
    env.close()
    assert not (own & set(os.listdir(SHM)))
