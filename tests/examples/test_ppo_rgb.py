"""``examples/ppo_torchrl.py --obs rgb`` (issue 63, item 3): its training env gives the inputs of ManiSkill's
PPO-from-rgb baseline (``ppo_rgb.py``: ``gym.make(obs_mode="rgb")`` -> ``FlattenRGBDObservationWrapper(rgb=True,
depth=False, state=True)`` -> ``ManiSkillVectorEnv(ignore_terminations=False, record_metrics=True)``), bit for
bit on a seeded rollout across an episode's end; its models read them; a smoke run trains and saves."""

from __future__ import annotations

import json
from pathlib import Path

import torch
from mani_skill.utils.wrappers import FlattenRGBDObservationWrapper
from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

import ppo_torchrl
from support.helpers import close_envs, make_gym_env

SIZE, EPISODE = 48, 4
FLAGS = ["--obs", "rgb", "--image-size", str(SIZE), "--device", "cpu", "--sim-backend", "cpu"]


def _baseline_env():
    env = make_gym_env(
        "PushCube-v1",
        obs_mode="rgb",
        control_mode="pd_joint_delta_pos",
        render_backend="cpu",
        sensor_configs={"width": SIZE, "height": SIZE},
        max_episode_steps=EPISODE,
    )
    env = FlattenRGBDObservationWrapper(env, rgb=True, depth=False, state=True)
    return ManiSkillVectorEnv(env, 1, ignore_terminations=False, record_metrics=True)


def test_the_training_env_is_maniskills_ppo_rgb_stack():
    args = ppo_torchrl.parse_args([*FLAGS, "--num-envs", "1", "--max-episode-steps", str(EPISODE)])
    env, ref = ppo_torchrl.make_env(args), _baseline_env()
    try:
        assert env.observation_spec["rgb"].shape == (1, SIZE, SIZE, 3)
        obs, _ = ref.reset(seed=7)
        env.set_seed(7)
        td = env.reset()
        for key in ("rgb", "state"):
            assert td[key].dtype == obs[key].dtype and torch.equal(td[key], obs[key]), f"reset: {key}"
        steps = 0
        for t in range(EPISODE + 2):
            action = torch.sin(torch.arange(8.0) + t).reshape(1, 8) * 0.8
            obs, reward, term, trunc, info = ref.step(action)
            td = env.step(td.set("action", action))
            nxt = td["next"]
            steps += 1
            done = bool((term | trunc).any())
            final = info["final_observation"] if done else obs  # ManiSkillVectorEnv has reset already
            for key in ("rgb", "state"):
                assert torch.equal(nxt[key], final[key]), f"step {t}: {key}"
            assert torch.equal(nxt["reward"].reshape(-1), reward.reshape(-1).float()), f"step {t}: reward"
            assert bool(nxt["done"].any()) == done, f"step {t}: done"
            if bool(nxt["done"].any()):
                assert steps == EPISODE
                # the episode's end: both restart from the same seed (the library's autoreset seeds are its own)
                obs, _ = ref.reset(seed=8)
                env.set_seed(8)
                td = env.reset()
                assert torch.equal(td["rgb"], obs["rgb"]) and torch.equal(td["state"], obs["state"])
                steps = 0
            else:
                td = nxt
        policy, value = ppo_torchrl.make_models(env, 256, torch.device("cpu"))
        out = value(policy(env.reset()))
        assert out["action"].shape == (1, 8) and out["state_value"].shape == (1, 1)
        shared = {id(p) for p in policy.parameters()} & {id(p) for p in value.parameters()}
        assert shared, "the encoder is shared by the actor and the critic, as in ManiSkill's Agent"
    finally:
        close_envs([env, ref])


def test_a_smoke_run_from_rgb_trains_and_saves(tmp_path: Path):
    out = tmp_path / "out"
    assert ppo_torchrl.main([*FLAGS, "--smoke", "--out", str(out)]) == 0
    checkpoint = torch.load(out / "ppo_checkpoint.pt", weights_only=False)
    assert checkpoint["obs_mode"] == "rgb" and checkpoint["args"]["image_size"] == SIZE
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert records, "no metrics"
