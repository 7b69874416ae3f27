"""TorchRL's ``AsyncBatchedCollector`` over unbatched ``ManiSkillEnv`` workers: the way past
lockstep that docs/guides/cpu_performance.md ("Past lockstep") offers.

Each env is stepped as soon as its own action is ready, so transitions arrive out of env order;
per env they must still chain (the next observation of a step is the observation of that env's
next step, unless the episode ended) and episodes must end where ManiSkill's time limit says.
"""

from __future__ import annotations

import functools

import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.collectors import AsyncBatchedCollector

from maniskill_torchrl import ManiSkillEnv

EPISODE = 6


def make_env():
    return ManiSkillEnv("PickCube-v1", batch_size=[], sim_backend="cpu", obs_mode="state", max_episode_steps=EPISODE)


def make_policy(obs_dim: int, act_dim: int):
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(obs_dim, act_dim), torch.nn.Tanh())
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


@pytest.mark.slow
def test_transitions_chain_per_env():
    """Batches until each env has made two episodes' worth of transitions (one env may start
    seconds after the other on a loaded machine: the collector does not wait for it)."""
    collector = AsyncBatchedCollector(
        create_env_fn=[make_env] * 2,
        policy_factory=functools.partial(make_policy, 42, 8),
        transport="auto",
        env_backend="multiprocessing",
        frames_per_batch=30,
        total_frames=-1,
        transition_chunk_size=1,
    )
    batches = []
    try:
        for batch in collector:
            batches.append(batch.to_tensordict())
            counts = torch.cat([b["env_index"] for b in batches]).bincount(minlength=2)
            if (counts >= 2 * EPISODE).all() or len(batches) == 40:
                break
    finally:
        collector.shutdown()
    data = torch.cat(batches)
    env_index = data["env_index"]
    for i in (0, 1):
        mine = data[env_index == i]
        assert len(mine) >= 2 * EPISODE, f"env {i} made {len(mine)} of {len(data)} transitions"
        done = mine["next", "done"].squeeze(-1)
        steps = mine["next", "elapsed_steps"]
        # ManiSkill's time limit ends every episode at EPISODE steps (random actions do not succeed)
        assert torch.equal(done, steps == EPISODE), (done, steps)
        assert bool((mine["action"].abs() <= 1).all())
        chained = ~done[:-1]
        assert torch.equal(mine["next", "observation"][:-1][chained], mine["observation"][1:][chained])
        assert torch.equal(steps[1:][chained], steps[:-1][chained] + 1)
