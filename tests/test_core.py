"""The shared core on its own (masked_merge, episode_stats, numpy_sum): numpy-exact episode
return on every code path, masked merge.

The reference here is numpy itself (``np.sum`` over a python list of float32 rewards, as
ManiSkill's CPUGymWrapper computes the return) and plain per-env python bookkeeping.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from helpers import bits
from maniskill_torchrl.episode_stats import EpisodeStats
from maniskill_torchrl.masked_merge import any_done, merge_step
from maniskill_torchrl.numpy_sum import pairwise_sum


@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 15, 16, 127, 128, 129, 130, 255, 256, 300, 1001])
def test_pairwise_sum_matches_numpy(n):
    x = torch.randn(3, n) * torch.rand(3, 1) * 10
    ours = pairwise_sum(x)
    for row in range(3):
        assert bits(ours[row].numpy(), np.float32) == bits(np.sum(x[row].numpy()), np.float32)


@pytest.mark.parametrize(
    "batch, device_path",
    [
        ((), "numpy"),  # a single CPU env (what the gym shim and CPUUnbatch-ed envs use)
        ((3,), "numpy"),
        ((20,), "torch"),  # a large batch takes the incremental torch path (as on the GPU sim)
        ((4, 6), "torch"),
    ],
)
def test_episode_return_bit_exact_with_resets(batch, device_path):
    rng = np.random.default_rng(7)
    stats = EpisodeStats(batch, "cpu", has_success=True, has_fail=True)
    assert stats._sum.uses_numpy == (device_path == "numpy")
    n_envs = int(np.prod(batch)) if batch else 1
    rewards: list[list[np.ndarray]] = [[] for _ in range(n_envs)]
    success_once = np.zeros(n_envs, bool)
    fail_once = np.zeros(n_envs, bool)
    for step in range(420):
        if step % 97 == 96:
            stats.reset()
            rewards = [[] for _ in range(n_envs)]
            success_once[:] = False
            fail_once[:] = False
        mask = rng.random(n_envs) < 0.01
        if mask.any():
            stats.reset(torch.from_numpy(mask).reshape(batch))
            for i in np.flatnonzero(mask):
                rewards[i] = []
                success_once[i] = fail_once[i] = False
        r = (rng.standard_normal(n_envs) * rng.uniform(0, 5, n_envs)).astype(np.float32)
        succ = rng.random(n_envs) < 0.05
        fail = rng.random(n_envs) < 0.05
        ep = stats.update(
            torch.from_numpy(r).reshape(batch),
            success=torch.from_numpy(succ).reshape(batch),
            fail=torch.from_numpy(fail).reshape(batch),
        )
        ep = ep.reshape(-1)
        for i in range(n_envs):
            rewards[i].append(np.array([r[i]], dtype=np.float32))
            success_once[i] |= succ[i]
            fail_once[i] |= fail[i]
            ref = np.sum(rewards[i])
            assert bits(ep["return"][i].numpy(), np.float32) == bits(ref, np.float32), (step, i, len(rewards[i]))
            assert ep["episode_len"][i].item() == len(rewards[i])
            assert bits(ep["reward"][i].numpy(), np.float32) == bits(ref / len(rewards[i]), np.float32)
            assert ep["success_once"][i].item() == success_once[i]
            assert ep["fail_once"][i].item() == fail_once[i]
            assert ep["success_at_end"][i].item() == succ[i]
            assert ep["fail_at_end"][i].item() == fail[i]


def test_episode_outputs_not_aliased_by_reset():
    stats = EpisodeStats((2,), "cpu", has_success=False, has_fail=False)
    ep = stats.update(torch.tensor([1.5, 2.5]))
    kept = ep.clone()
    stats.reset(torch.tensor([True, False]))
    stats.update(torch.tensor([1.0, 1.0]))
    assert (ep == kept).all()


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.booleans(), min_size=1, max_size=6),
    st.lists(st.booleans(), min_size=1, max_size=6),
    st.integers(0, 2**16),
)
def test_merge_step_against_per_env_reference(done_before, done_new, seed):
    b = min(len(done_before), len(done_new))
    done_before, done_new = done_before[:b], done_new[:b]
    g = torch.Generator().manual_seed(seed)

    def td(done):
        return TensorDict(
            {
                "reward": torch.randn(b, 1, generator=g),
                "done": torch.tensor(done).view(b, 1),
                "obs": torch.randn(b, 3, generator=g),
                ("nested", "img"): torch.randint(0, 255, (b, 2, 2), generator=g, dtype=torch.uint8),
                ("agents", "reward"): torch.randn(b, 2, 1, generator=g),
            },
            batch_size=[b],
        )

    acc, new = td(done_before), td(done_new)
    # Expected values come from copies taken before the call: an in-place merge into `acc`
    # (or `new`) must not make the reference alias the output.
    acc0, new0 = acc.clone(), new.clone()
    running = ~any_done(acc, ["done"])
    out = merge_step(acc, new, running, ["reward", ("agents", "reward")], ["done"])
    for i in range(b):
        if running[i]:
            assert torch.equal(out["reward"][i], acc0["reward"][i] + new0["reward"][i])
            assert torch.equal(out["agents", "reward"][i], acc0["agents", "reward"][i] + new0["agents", "reward"][i])
            assert out["done"][i].item() == (done_before[i] or done_new[i])
            assert torch.equal(out["obs"][i], new0["obs"][i])
            assert torch.equal(out["nested", "img"][i], new0["nested", "img"][i])
        else:
            assert (out[i] == acc0[i]).all()
    # the inputs are left untouched
    assert torch.equal(acc["done"].view(-1), torch.tensor(done_before))
    assert (acc == acc0).all() and (new == new0).all()
