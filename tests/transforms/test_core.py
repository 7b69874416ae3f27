"""The shared core on its own (masked_merge, episode_stats, numpy_sum): episode returns bit for
bit in both summations, masked merge.

The references here are numpy itself (``np.sum`` over a python list of float32 rewards, as
ManiSkill's CPUGymWrapper computes the return), a float32 running sum (ManiSkillVectorEnv's) and
plain per-env python bookkeeping.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from maniskill_torchrl._internal.episode_stats import EpisodeStats
from maniskill_torchrl.transforms.action_repeat import any_done, merge_step
from support.helpers import bits
from support.toy_env import ToyEnv


@pytest.mark.parametrize(
    "batch, summation",
    [
        ((), "numpy"),  # a single CPU env (what the gym shim and CPUUnbatch-ed envs use)
        ((3,), "numpy"),
        ((20,), "numpy"),
        ((4, 6), "numpy"),
        ((20,), "running"),  # the GPU sim's default, ManiSkillVectorEnv's float32 running sum
        ((4, 6), "running"),
    ],
)
def test_episode_return_bit_exact_with_resets(batch, summation):
    rng = np.random.default_rng(7)
    stats = EpisodeStats(batch, "cpu", has_success=True, has_fail=True, summation=summation)
    n_envs = int(np.prod(batch)) if batch else 1
    rewards: list[list[np.ndarray]] = [[] for _ in range(n_envs)]
    running = np.zeros(n_envs, np.float32)
    success_once = np.zeros(n_envs, bool)
    fail_once = np.zeros(n_envs, bool)
    ep = None
    lengths = []
    for step in range(600):
        if step % 250 == 249:
            ep = None
            rewards = [[] for _ in range(n_envs)]
            running[:] = 0
            success_once[:] = False
            fail_once[:] = False
        mask = rng.random(n_envs) < 0.004
        if mask.any() and ep is not None:
            ep = stats.restart(ep, torch.from_numpy(mask).reshape(batch))
            for i in np.flatnonzero(mask):
                rewards[i] = []
                running[i] = 0
                success_once[i] = fail_once[i] = False
        r = (rng.standard_normal(n_envs) * rng.uniform(0, 5, n_envs)).astype(np.float32)
        succ = rng.random(n_envs) < 0.05
        fail = rng.random(n_envs) < 0.05
        ep = stats.update(
            ep,
            torch.from_numpy(r).reshape(batch),
            success=torch.from_numpy(succ).reshape(batch),
            fail=torch.from_numpy(fail).reshape(batch),
        )
        flat = ep.reshape(-1)
        for i in range(n_envs):
            rewards[i].append(np.array([r[i]], dtype=np.float32))
            running[i] = running[i] + r[i]
            success_once[i] |= succ[i]
            fail_once[i] |= fail[i]
            ref = np.sum(rewards[i]) if summation == "numpy" else running[i]
            assert bits(flat["return"][i].numpy(), np.float32) == bits(ref, np.float32), (step, i, len(rewards[i]))
            assert flat["episode_len"][i].item() == len(rewards[i])
            assert bits(flat["reward"][i].numpy(), np.float32) == bits(ref / len(rewards[i]), np.float32)
            assert flat["success_once"][i].item() == success_once[i]
            assert flat["fail_once"][i].item() == fail_once[i]
            assert flat["success_at_end"][i].item() == succ[i]
            assert flat["fail_at_end"][i].item() == fail[i]
            lengths.append(len(rewards[i]))
    assert max(lengths) > 128  # numpy's recursion above 128 rewards is covered


def test_numpy_and_running_sums_differ_past_8_steps():
    """The two summations are two anchors: this test fails if they became one."""
    x = torch.tensor([0.1, 1e4, -0.3, 7.7, 1e-3, 3.3, -2e3, 0.7, 0.9, 1.1] * 3, dtype=torch.float32)
    out = {}
    for summation in ("numpy", "running"):
        stats = EpisodeStats((), has_success=False, has_fail=False, summation=summation)
        ep = None
        for r in x:
            ep = stats.update(ep, r)
        out[summation] = ep["return"].item()
    assert out["numpy"] == float(np.sum(x.numpy()))
    assert out["numpy"] != out["running"]


def test_episode_outputs_not_written_by_restart_or_update():
    stats = EpisodeStats((2,), "cpu", has_success=False, has_fail=False)
    ep = stats.update(None, torch.tensor([1.5, 2.5]))
    kept = ep.clone()
    restarted = stats.restart(ep, torch.tensor([True, False]))
    stats.update(restarted, torch.tensor([1.0, 1.0]))
    assert (ep == kept).all()
    assert restarted["episode_len"].tolist() == [0, 1]


def test_summation_is_checked():
    with pytest.raises(ValueError, match="summation='pairwise'"):
        EpisodeStats((2,), summation="pairwise")


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


class _HookedToy(ToyEnv):
    """A toy env implementing the transforms' env protocol (``maniskill_torchrl.envs.hooks``):
    it records the repeats asked and never repeats in workers."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.requests: list[int] = []

    def request_worker_repeat(self, repeat: int) -> bool:
        self.requests.append(repeat)
        return False

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        return None

    def request_reset_states(self, states, obs=None) -> bool:
        return False


def test_the_transforms_talk_to_envs_through_the_hooks_protocol():
    """ActionRepeat asks any env implementing ``EnvHooks`` for the workers' repeat (only when
    directly on it), EpisodeMetrics for host values; a plain env is not asked anything."""
    from torchrl.envs import Compose, StepCounter, TransformedEnv

    from maniskill_torchrl import ActionRepeat, EpisodeMetrics
    from maniskill_torchrl.envs.hooks import env_hooks

    env = TransformedEnv(_HookedToy([5, 5]), Compose(ActionRepeat(3), EpisodeMetrics(summation="numpy")))
    assert env_hooks(env) is env.base_env
    nxt = env.step(env.reset().set("action", torch.zeros(2, 2)))["next"]
    assert env.base_env.requests == [3]
    # The numpy summation reads host values through the hook (it asks on an accelerator only).
    assert env.transform[1]._host_value == env.base_env.host_value
    assert nxt["elapsed_steps"].tolist() == [3, 3] and nxt["episode", "episode_len"].tolist() == [1, 1]
    # A transform in between would miss the inner steps: no request then.
    env = TransformedEnv(_HookedToy([5, 5]), Compose(StepCounter(), ActionRepeat(3)))
    env.step(env.reset().set("action", torch.zeros(2, 2)))
    assert env.base_env.requests == []
    assert env_hooks(TransformedEnv(ToyEnv([5]))) is None
