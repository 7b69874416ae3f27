"""What only the GPU sim shows, for the first lent GPU: frames that outlive later steps, the
``cuda:0`` device name, ``EpisodeMetrics`` over 1000-step episodes against
``ManiSkillVectorEnv(record_metrics=True)`` without host syncs, and a wrapped
``ManiSkillVectorEnv(auto_reset=False)``.

``tests/test_gpu_doubles.py`` proves the same on the CPU with test doubles; these run the real GPU
sim (SAPIEN's PhysX GPU library needed). Skipped without CUDA.
"""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv
from torchrl.envs import Compose, TransformedEnv

from gpu_helpers import (
    CUDA,
    NUM_ENVS,
    SEED,
    SIM_BACKEND,
    Recorder,
    Replay,
    actions,
    count_host_syncs,
    needs_one_gym_env,
    requires_gpu,
    swapped,
    sync_counts,
    sync_sites,
)
from maniskill_torchrl import ActionRepeat, EpisodeMetrics, IgnoreTerminations, ManiSkillEnv, ManiSkillWrapper
from maniskill_torchrl.testing import assert_on_device
from support.helpers import assert_same, clone_tree

pytestmark = requires_gpu

# Small pictures: the point is their buffers, not their size.
RGB = dict(
    obs_mode="rgb",
    sim_backend=SIM_BACKEND,
    max_episode_steps=5,
    sensor_configs=dict(width=32, height=32),
    human_render_camera_configs=dict(width=32, height=32),
)


def test_rgb_frames_outlive_later_steps_and_resets():
    """Every tensordict returned keeps its frames after later steps and (partial) resets: what a
    collector stores. SAPIEN renders each picture into one CUDA buffer on the GPU sim."""
    n = min(NUM_ENVS, 16)
    env = TransformedEnv(
        ManiSkillEnv("PushCube-v1", num_envs=n, from_pixels=True, **RGB), Compose(ActionRepeat(2), EpisodeMetrics())
    )
    try:
        env.set_seed(SEED)
        td = env.reset()
        copies, kept = [td.clone()], [td.exclude("action")]
        acts = actions(env.base_env.unwrapped.single_action_space, env.device, 8, seed=3)
        for a in acts:  # 5-step episodes, repeat 2: every env ends mid-repeat, then resets
            td, td_next = env.step_and_maybe_reset(td.set("action", a[:n]))
            copies.append(td["next"].clone())
            kept.append(td["next"].exclude("action"))
            td = td_next
        rgb = [c["sensor_data", "base_camera", "rgb"] for c in copies]
        assert any(not torch.equal(rgb[0], r) for r in rgb[1:]), "frames should change between steps"
        for i, (copy, later) in enumerate(zip(copies, kept)):
            assert_same(later, copy, f"step {i}, read after the later steps")
    finally:
        env.close()


def test_cuda_device_names():
    """ManiSkill's GPU sim says "cuda", TorchRL "cuda:0": both name the sim's device, and a GPU-sim
    env asked for device="cpu" returns every output on the CPU."""
    if not CUDA:
        pytest.skip("needs CUDA")
    for device in ("cuda:0", "cuda", torch.device("cuda")):
        env = ManiSkillEnv("PushCube-v1", num_envs=4, obs_mode="state", sim_backend="gpu", device=device)
        try:
            assert env.device == torch.device("cuda", torch.cuda.current_device())
            assert env.rollout(2)["next", "observation"].device == env.device
        finally:
            env.close()
    env = ManiSkillEnv("PushCube-v1", num_envs=4, obs_mode="state", sim_backend="gpu", device="cpu")
    try:
        assert env.device == torch.device("cpu")
        assert_on_device(env.rollout(2), env.device)
    finally:
        env.close()


def test_episode_metrics_1000_step_episodes_equal_maniskill_vector_env():
    """MS-CartpoleBalance-v1's own 1000-step limit, terminations ignored: at every step ours equals
    ManiSkillVectorEnv(record_metrics=True) bit for bit (return, reward, length, flags), on a
    replay of the very same steps, and this library makes no host sync while stepping."""
    needs_one_gym_env()
    raw = gym.make("MS-CartpoleBalance-v1", num_envs=NUM_ENVS, obs_mode="state", sim_backend=SIM_BACKEND)
    try:
        limit = gym.spec("MS-CartpoleBalance-v1").max_episode_steps
        assert limit == 1000
        acts = actions(raw.unwrapped.single_action_space, raw.unwrapped.device, limit, seed=4)
        recorder = Recorder(raw)
        vec = ManiSkillVectorEnv(recorder, auto_reset=False, ignore_terminations=True, record_metrics=True)
        vec.reset(seed=SEED)
        theirs = [clone_tree(vec.step(a)[4]["episode"]) for a in acts]

        # The default on CUDA; the CPU check of this test's code asks for it (the CPU's is numpy's order).
        summation = None if CUDA else "running"
        ours = TransformedEnv(ManiSkillWrapper(raw), Compose(IgnoreTerminations(), EpisodeMetrics(summation)))
        with swapped(ours.base_env, Replay(raw, recorder.calls, strict=False)):
            td = ours.reset(seed=SEED)
            got = []
            with count_host_syncs() as stacks:
                for a in acts:
                    td = ours.step(td.set("action", a))["next"]
                    got.append(td["episode"])
        for t, (mine, ms) in enumerate(zip(got, theirs)):
            for key, value in ms.items():
                value = value.to(torch.int64) if key == "episode_len" else value
                assert_same(mine[key], value, f"step {t}: {key}")
        counts = sync_counts(stacks)
        assert counts.get("maniskill_torchrl", 0) == 0, sync_sites(stacks, "maniskill_torchrl")
    finally:
        raw.close()


def test_maniskill_vector_env_without_auto_reset():
    """ManiSkillVectorEnv(auto_reset=False) wrapped: each step's "next" is ManiSkill's own step
    output (the final observation of an ended episode kept), and TorchRL resets the done envs."""
    needs_one_gym_env()
    raw = gym.make("MS-CartpoleBalance-v1", num_envs=NUM_ENVS, obs_mode="state", sim_backend=SIM_BACKEND)
    recorder = Recorder(raw)
    env = ManiSkillWrapper(ManiSkillVectorEnv(recorder, auto_reset=False))
    try:
        env.set_seed(SEED)
        acts = iter(actions(raw.unwrapped.single_action_space, env.device, 40, seed=5))
        rollout = env.rollout(40, policy=lambda td: td.set("action", next(acts)), break_when_any_done=False)
        steps = [out for kind, _, out in recorder.calls if kind == "step"]
        assert len(steps) == 40
        for t, (obs, reward, terminated, truncated, _) in enumerate(steps):
            assert_same(rollout["next", "observation"][:, t], obs, f"step {t}: observation")
            assert_same(rollout["next", "reward"][:, t, 0], reward, f"step {t}: reward")
            assert_same(rollout["next", "terminated"][:, t, 0], terminated, f"step {t}: terminated")
            assert_same(rollout["next", "truncated"][:, t, 0], truncated, f"step {t}: truncated")
        assert rollout["next", "done"].any(), "random actions should end some Cartpole episodes"
        resets = [arg for kind, arg, _ in recorder.calls if kind == "reset"]
        if NUM_ENVS > 1:  # one env's reset is a full one
            assert any("env_idx" in (r["options"] or {}) for r in resets[1:]), "expected partial resets"
    finally:
        env.close()


def test_partial_reset_to_saved_states():
    """env.get_state() then a masked env.reset(td, set_state=True, scene_state=...): the masked envs
    get their saved observation back, the others keep theirs (ManiSkill's reset_to_env_states with
    the rows of the envs being reset)."""
    env = ManiSkillEnv("MS-CartpoleBalance-v1", num_envs=NUM_ENVS, obs_mode="state", sim_backend=SIM_BACKEND)
    try:
        start = env.reset(seed=SEED)
        saved = env.get_state()
        assert saved.batch_size == env.batch_size and saved.device == env.device
        td = start
        for a in actions(env.unwrapped.single_action_space, env.device, 3, seed=6):
            td = env.step(td.set("action", a))["next"]
        now = td["observation"].clone()
        mask = (torch.arange(NUM_ENVS, device=env.device) % 2 == 0).unsqueeze(-1)
        back = env.reset(td.clone().set("_reset", mask), set_state=True, scene_state=saved)
        m = mask.squeeze(-1)
        assert torch.equal(back["observation"][m], start["observation"][m])
        assert torch.equal(back["observation"][~m], now[~m])
    finally:
        env.close()
