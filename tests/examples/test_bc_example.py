"""Behaviour cloning from demonstrations (``examples/bc_torchrl.py``), on a demonstration file that
ManiSkill's ``RecordEpisode`` writes here from the library's scripted PickCube-v1 policy:

- the training pairs (observation history, action chunk) are padded at episode edges as
  ManiSkill's Diffusion Policy baseline pads them, checked against the ``.h5`` read directly;
- the env side (``InitTracker`` + ``CatFrames``) hands the policy the same history layout;
- both policies' losses fall on the demonstrations, and the example runs end to end: evaluation
  through ``EpisodeMetrics``, a checkpoint that reloads to the same actions.

Success rates are a benchmark (benchmarks/RESULTS.md, "Behaviour cloning")."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch
from mani_skill.utils.wrappers import RecordEpisode

import bc_torchrl
from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.cli.scripted_policy import PickCubeScriptedPolicy
from maniskill_torchrl.data import ManiSkillExperienceReplay
from support.helpers import make_gym_env

TASK = "PickCube-v1"
STEPS = 30
SEEDS = list(range(6))
KW = {"control_mode": "pd_ee_delta_pos", "max_episode_steps": STEPS}


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    """6 scripted episodes (state obs, pd_ee_delta_pos): the scripted policy reads the state_dict
    observation, so its actions are found on a state_dict env and recorded on a state env, same seeds."""
    out = tmp_path_factory.mktemp("bc-demos")
    source = make_gym_env(TASK, obs_mode="state_dict", **KW)
    policy = PickCubeScriptedPolicy(noise=0.05, seed=0)
    episodes = []
    for seed in SEEDS:
        obs, _ = source.reset(seed=seed)
        actions = []
        for _ in range(STEPS):
            extra = obs["extra"]
            a = policy(extra["tcp_to_obj_pos"], extra["obj_to_goal_pos"], extra["is_grasped"])
            actions.append(a)
            obs, *_ = source.step(a)
        episodes.append(actions)
    source.close()
    env = RecordEpisode(
        make_gym_env(TASK, obs_mode="state", **KW), output_dir=str(out), trajectory_name="demo", save_video=False
    )
    for seed, actions in zip(SEEDS, episodes):
        env.reset(seed=seed)
        for a in actions:
            env.step(a)
    env.close()
    return out / "demo.h5"


def test_training_pairs_pad_as_the_baseline(demos, tmp_path):
    rb = ManiSkillExperienceReplay(demos, 8, root=tmp_path)
    data = bc_torchrl.ChunkDataset(rb, obs_horizon=2, pred_horizon=4)
    obs, act = data.observation[data.obs_index], data.action[data.act_index]
    expected_obs, expected_act = [], []
    with h5py.File(demos) as f:
        for i in range(len(SEEDS)):
            o = np.asarray(f[f"traj_{i}/obs"])[:-1]  # the last entry is the final observation
            a = np.asarray(f[f"traj_{i}/actions"])
            n = len(a)
            for t in range(n):
                expected_obs.append(np.stack([o[max(t - 1, 0)], o[t]]))
                expected_act.append(np.stack([a[min(t + k, n - 1)] for k in range(4)]))
    assert data.episodes == len(SEEDS)
    torch.testing.assert_close(obs, torch.from_numpy(np.stack(expected_obs)).float(), rtol=0, atol=0)
    torch.testing.assert_close(act, torch.from_numpy(np.stack(expected_act)).float(), rtol=0, atol=0)


def test_env_history_is_the_training_layout():
    """At step t the policy reads (o[t-1], o[t]), and (o[0], o[0]) right after a reset."""
    env = bc_torchrl.with_history(ManiSkillEnv(TASK, obs_mode="state", **KW), obs_horizon=2)
    try:
        env.set_seed(3)
        rollout = env.rollout(5, break_when_any_done=False)
    finally:
        env.close()
    o = rollout["observation"]  # (1, time, obs_dim): ManiSkillEnv's batch is num_envs=1
    expected = torch.cat([torch.cat([o[:, :1], o[:, :-1]], 1), o], -1)
    torch.testing.assert_close(rollout["observation_history"], expected, rtol=0, atol=0)
    assert rollout["is_init"][:, 0].all() and not rollout["is_init"][:, 1:].any()


@pytest.mark.parametrize("policy", ["mlp", "diffusion"])
def test_loss_falls_on_the_demonstrations(demos, tmp_path, policy):
    rb = ManiSkillExperienceReplay(demos, 8, root=tmp_path)
    data = bc_torchrl.ChunkDataset(rb, obs_horizon=2, pred_horizon=4)
    settings = {
        "policy": policy,
        "obs_horizon": 2,
        "pred_horizon": 4,
        "act_horizon": 2,
        "obs_dim": data.observation.shape[-1],
        "act_dim": data.action.shape[-1],
        "hidden": 128,
        "depth": 2,
    }
    torch.manual_seed(0)
    model = bc_torchrl.make_policy(settings, data)
    optim = torch.optim.Adam(model.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    fixed = data.sample(256, torch.Generator().manual_seed(1))

    def loss() -> float:
        with torch.no_grad():
            return model.loss(*fixed, torch.Generator().manual_seed(2)).item()

    before = loss()
    for _ in range(300):
        optim.zero_grad()
        model.loss(*data.sample(64, gen), gen).backward()
        optim.step()
    after = loss()
    assert after < 0.5 * before, (before, after)
    with torch.no_grad():
        chunk = model(fixed[0][:3])
    assert chunk.shape == (3, 4, data.action.shape[-1]) and chunk.abs().max() <= 1


def test_example_end_to_end_and_checkpoint(demos, tmp_path):
    out = tmp_path / "run"
    args = ["--demos", str(demos), "--env-id", TASK, "--policy", "diffusion", "--hidden", "64", "--depth", "2"]
    args += ["--iterations", "20", "--eval-every", "20", "--eval-episodes", "2", "--eval-envs", "1"]
    args += ["--max-episode-steps", str(STEPS), "--threads", "1", "--out", str(out)]
    assert bc_torchrl.main(args) == 0
    (record,) = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert record["iteration"] == 20 and record["episodes"] == 2
    assert 0 <= record["success_once"] <= 1 and np.isfinite(record["return"])

    actor, settings = bc_torchrl.load_policy(out / "bc_checkpoint.pt")
    assert settings["env_id"] == TASK and settings["act_horizon"] == 8
    env = bc_torchrl.with_history(ManiSkillEnv(TASK, obs_mode="state", **KW), settings["obs_horizon"])
    try:
        env.set_seed(0)
        torch.manual_seed(0)
        first = env.rollout(10, actor, break_when_any_done=False)
        env.set_seed(0)
        torch.manual_seed(0)
        again = env.rollout(10, actor, break_when_any_done=False)
    finally:
        env.close()
    torch.testing.assert_close(first["action"], again["action"], rtol=0, atol=0)
    # one chunk per 8 steps: actions 0-7 come from the first chunk, 8-9 from the second
    action, chunk = first["action"][0], first["action_chunk"][0]  # env 0 of the batch of 1
    torch.testing.assert_close(action[:8], chunk[0, :8], rtol=0, atol=0)
    torch.testing.assert_close(action[8:], chunk[8, :2], rtol=0, atol=0)
    assert not torch.equal(chunk[0], chunk[8])


def test_bad_checkpoint(tmp_path):
    torch.save({"format": "something else"}, tmp_path / "x.pt")
    with pytest.raises(ValueError, match="not a bc_torchrl.py checkpoint"):
        bc_torchrl.load_policy(tmp_path / "x.pt")
