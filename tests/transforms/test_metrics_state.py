"""EpisodeMetrics' ``summation="numpy"`` (the CPU sim's default) continues the episode state in
the input tensordict, whatever ran in between.

numpy's pairwise order needs the episode's rewards, which only the transform's own history
holds. A state that is not the continuation of that history (a step kept from an earlier
episode, passed back after another episode ran) goes on from the tensordict's return with a
running float32 sum. The oracles: TorchRL's ``RewardSum`` and ``StepCounter`` on a real task, a
float32 running sum and ``numpy.sum`` itself on the core.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs import Compose, RewardSum, StepCounter, TransformedEnv

from maniskill_torchrl import CPUUnbatch, EpisodeMetrics, ManiSkillEnv
from maniskill_torchrl._internal.episode_stats import EpisodeStats
from support.helpers import bits, close_envs, random_actions


class Scripted:
    """A policy that plays a fixed list of actions."""

    def __init__(self, actions: list[torch.Tensor]) -> None:
        self.actions = iter(actions)

    def __call__(self, td):
        return td.set("action", next(self.actions))


@pytest.fixture(scope="module")
def pick():
    env = TransformedEnv(
        ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=50),
        Compose(CPUUnbatch(), StepCounter(), RewardSum(), EpisodeMetrics()),
    )
    yield env
    close_envs([env])


@pytest.mark.parametrize("other_steps", [1, 6])  # an episode in between, shorter or longer than the kept one
def test_return_continues_a_kept_step_after_another_episode(pick, other_steps):
    env = pick
    assert env.transform[-1]._make_stats().summation == "numpy"
    actions = random_actions(env.base_env.unwrapped.action_space, 3 + other_steps + 12, seed=other_steps)
    kept = env.rollout(3, Scripted(actions[:3]), tensordict=env.reset(seed=11), auto_reset=False)
    root = kept[-1]["next"].clone()
    env.rollout(other_steps, Scripted(actions[3 : 3 + other_steps]), tensordict=env.reset(seed=12), auto_reset=False)
    out = env.rollout(12, Scripted(actions[3 + other_steps :]), tensordict=root, auto_reset=False)
    nxt = out["next"]
    assert not nxt["done"].any()
    assert torch.equal(nxt["episode", "episode_len"], nxt["step_count"].squeeze(-1))
    assert nxt["episode", "episode_len"][0] == 4
    # RewardSum: the root's return plus each reward, in float32, as the fallback sums.
    assert bits(nxt["episode", "return"].numpy()) == bits(nxt["episode_reward"].squeeze(-1).numpy())
    mean = nxt["episode_reward"].squeeze(-1) / nxt["step_count"].squeeze(-1)
    assert bits(nxt["episode", "reward"].numpy()) == bits(mean.numpy())


def _run(stats: EpisodeStats, ep, rewards: np.ndarray):
    """``ep`` after one update per row of ``rewards`` ([T, B] float32); the states on the way."""
    states = []
    for r in rewards:
        ep = stats.update(ep, torch.from_numpy(r))
        states.append(ep)
    return ep, states


def test_core_foreign_state_runs_on_then_numpy_again_after_reset():
    """Per env: an env passed a state the history does not hold goes on with a running sum from
    that state; an env that continues the history keeps numpy.sum's bits; after a reset, numpy's
    bits again (past 8 steps, where a running sum differs)."""
    rng = np.random.default_rng(3)
    stats = EpisodeStats((3,), "cpu", has_success=False, has_fail=False, summation="numpy")
    first = rng.standard_normal((12, 3)).astype(np.float32)
    _, states = _run(stats, None, first)
    kept = states[4]  # after 5 steps
    second = rng.standard_normal((2, 3)).astype(np.float32)
    latest, _ = _run(stats, stats.restart(states[-1], torch.ones(3, dtype=torch.bool)), second)
    # Env 0 carries on the latest episode; envs 1 and 2 get the kept (overwritten) one's state.
    mixed = kept.clone()
    mixed[0] = latest[0]
    more = rng.standard_normal((14, 3)).astype(np.float32)
    ep, states = _run(stats, mixed, more)
    running = kept["return"].numpy().copy()
    for t, state in enumerate(states):
        running = running + more[t]
        expected = np.array([np.sum(np.concatenate([second[:, 0], more[: t + 1, 0]])), *running[1:]], np.float32)
        assert bits(state["return"].numpy()) == bits(expected), t
        assert state["episode_len"].tolist() == [3 + t, 6 + t, 6 + t]
    # A reset of env 1 only: numpy's sum again there; env 2 still runs on.
    ep = stats.restart(ep, torch.tensor([False, True, False]))
    last = rng.standard_normal((12, 3)).astype(np.float32)
    _, states = _run(stats, ep, last)
    for t, state in enumerate(states):
        running[2] = running[2] + last[t, 2]
        assert bits(state["return"][1].numpy()) == bits(np.sum(last[: t + 1, 1]))
        assert bits(state["return"][2].numpy()) == bits(running[2])
