# Copyright (c) Meta Platforms, Inc. and affiliates.
#
# This source code is licensed under the MIT license found in the
# LICENSE file in the root directory of this source tree.
"""Tests for the ManiSkill 3 environment wrapper.

Every test but the ``gpu``-marked ones runs ManiSkill's CPU sim, which builds an
env in well under a second once ManiSkill is imported. ManiSkill needs a Vulkan
device even for state observations (on a machine without a GPU, Mesa's lavapipe
works). Outputs are compared with those of a raw ManiSkill env made with
``gym.make``: two instances in one process agree only where every reset is
seeded, so every reset here is.
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import re
import subprocess
import sys

import pytest
import torch
import torchrl.envs.libs.maniskill as maniskill_lib
from tensordict import TensorDictBase

from torchrl.collectors import Collector
from torchrl.envs import ParallelEnv
from torchrl.envs.libs.maniskill import _has_maniskill, ManiSkillEnv, ManiSkillWrapper
from torchrl.envs.utils import check_env_specs

requires_maniskill = pytest.mark.skipif(
    not _has_maniskill, reason="mani_skill not installed"
)

_has_hydra = importlib.util.find_spec("hydra") is not None

_TASK = "PickCube-v1"
_CPU = torch.device("cpu")
_SEED = 7
_DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=pytest.mark.skipif(
            not torch.cuda.is_available(), reason="CUDA not available"
        ),
    ),
]


def _raw_env(env_id: str = _TASK, **kwargs):
    """A ManiSkill env as its users make it: one env on the CPU sim."""
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401

    return gym.make(env_id, num_envs=1, **kwargs)


def _leaves(tree, prefix=()):
    for key, value in tree.items():
        if isinstance(value, dict):
            yield from _leaves(value, prefix + (key,))
        elif isinstance(value, torch.Tensor):
            yield prefix + (key,), value


def _assert_obs_equal(td: TensorDictBase, obs, device) -> None:
    """``td`` holds ManiSkill's observation ``obs``, bit for bit, on ``device``."""
    if isinstance(obs, torch.Tensor):
        obs = {"observation": obs}
    for key, value in _leaves(obs):
        ours = td.get(key)
        assert ours.device == device, key
        torch.testing.assert_close(ours, value.to(device), rtol=0, atol=0)


def _assert_infos_equal(td: TensorDictBase, info: dict, device) -> None:
    assert "success" in info and "elapsed_steps" in info
    for key, value in info.items():
        if isinstance(value, torch.Tensor) and value.shape[:1] == (1,):
            torch.testing.assert_close(td.get(key), value.to(device), rtol=0, atol=0)


def _raw_action(td: TensorDictBase):
    action = td.get("action")
    if isinstance(action, TensorDictBase):
        return {key: value.cpu() for key, value in action.items()}
    return action.cpu()


def _assert_matches_raw(env, raw, *, device=_CPU, steps=4) -> None:
    """A seeded reset and ``steps`` random steps of ``env`` give what ``raw``
    gives for the same seed and actions."""
    td = env.reset(seed=_SEED)
    obs, info = raw.reset(seed=_SEED)
    _assert_obs_equal(td, obs, device)
    _assert_infos_equal(td, info, device)
    torch.manual_seed(_SEED)
    for _ in range(steps):
        td = env.rand_action(td)
        td = env.step(td)
        obs, reward, terminated, truncated, info = raw.step(_raw_action(td))
        nxt = td.get("next")
        _assert_obs_equal(nxt, obs, device)
        _assert_infos_equal(nxt, info, device)
        torch.testing.assert_close(
            nxt["reward"], reward.to(device, torch.float32).view(1, 1), rtol=0, atol=0
        )
        assert nxt["reward"].dtype == torch.float32
        assert (nxt["terminated"] == terminated.to(device).view(1, 1)).all()
        assert (nxt["truncated"] == truncated.to(device).view(1, 1)).all()
        assert (nxt["done"] == (terminated | truncated).to(device).view(1, 1)).all()
        td = td.get("next")


@pytest.fixture(scope="module")
def raw_envs():
    """Raw ManiSkill envs (``gym.make``), built on first use and shared by this
    module's tests (every reset is seeded), closed at the end.

    ManiSkill runs a garbage collection whenever it builds or closes an env, and
    SAPIEN makes its render engine (seconds on a CPU Vulkan driver) for the first
    env that renders in a process and frees it with the last one: shared reference
    envs keep this module fast.
    """
    if not _has_maniskill:
        pytest.skip("mani_skill not installed")
    envs = {}

    def get(env_id: str = _TASK, **kwargs):
        key = (env_id, *sorted(kwargs.items()))
        if key not in envs:
            envs[key] = _raw_env(env_id, **kwargs)
        return envs[key]

    yield get
    for env in envs.values():
        env.close()


@pytest.fixture(scope="module")
def rendering_env(raw_envs):
    """A raw env with cameras (``obs_mode="rgb"``) that renders (``render()``)."""
    return raw_envs(obs_mode="rgb", render_mode="rgb_array")


@requires_maniskill
class TestManiSkillSpecs:
    def test_library_attributes(self):
        import mani_skill
        import torchrl.envs

        assert torchrl.envs.ManiSkillEnv is ManiSkillEnv
        assert torchrl.envs.ManiSkillWrapper is ManiSkillWrapper
        assert ManiSkillWrapper.lib is mani_skill
        assert ManiSkillWrapper.libname == "mani_skill"
        assert "ManiSkill" in ManiSkillWrapper.git_url
        assert _TASK in ManiSkillEnv.available_envs

    @pytest.mark.parametrize(
        "obs_mode,key,shape,dtype",
        [
            ("state", "observation", (42,), torch.float32),
            ("state_dict", ("agent", "qpos"), (9,), torch.float32),
        ],
    )
    def test_specs(self, obs_mode, key, shape, dtype):
        env = ManiSkillEnv(_TASK, obs_mode=obs_mode)
        try:
            assert env.batch_size == torch.Size([1])
            assert not env.gpu_sim_enabled
            spec = env.observation_spec[key]
            assert spec.shape == torch.Size([1, *shape])
            assert spec.dtype == dtype
            assert env.observation_spec["success"].dtype == torch.bool
            assert env.full_action_spec["action"].shape == torch.Size([1, 8])
            assert env.reward_spec.shape == torch.Size([1, 1])
            assert env.reward_spec.dtype == torch.float32
            for done_key in ("done", "terminated", "truncated"):
                assert env.full_done_spec[done_key].shape == torch.Size([1, 1])
                assert env.full_done_spec[done_key].dtype == torch.bool
            check_env_specs(env, seed=_SEED)
        finally:
            env.close()

    def test_unbatched(self):
        env = ManiSkillEnv(_TASK, obs_mode="state", batch_size=[])
        try:
            assert env.batch_size == torch.Size([])
            assert env.observation_spec["observation"].shape == torch.Size([42])
            assert env.reward_spec.shape == torch.Size([1])
            check_env_specs(env, seed=_SEED)
        finally:
            env.close()

    def test_multi_agent_actions(self):
        env = ManiSkillEnv("TwoRobotPickCube-v1", obs_mode="state")
        try:
            agents = {"panda_wristcam-0", "panda_wristcam-1"}
            assert set(env.full_action_spec["action"].keys()) == agents
            for agent in agents:
                assert env.full_action_spec["action", agent].shape == (1, 8)
            check_env_specs(env, seed=_SEED)
        finally:
            env.close()

    def test_info_keys(self):
        env = ManiSkillEnv(_TASK, obs_mode="state", info_keys=["success"])
        try:
            assert "success" in env.observation_spec.keys()
            assert "elapsed_steps" not in env.observation_spec.keys()
            td = env.rand_step(env.reset(seed=_SEED))
            assert td["next", "success"].shape == torch.Size([1])
        finally:
            env.close()


@requires_maniskill
class TestManiSkillRawParity:
    @pytest.mark.parametrize("device", _DEVICES)
    @pytest.mark.parametrize("obs_mode", ["state", "state_dict"])
    def test_steps_match_maniskill(self, obs_mode, device, raw_envs):
        env = ManiSkillEnv(_TASK, obs_mode=obs_mode, device=device)
        raw = raw_envs(obs_mode=obs_mode)
        try:
            assert env.device.type == device
            _assert_matches_raw(env, raw, device=env.device)
        finally:
            env.close()

    def test_rgb_matches_maniskill(self, rendering_env):
        env = ManiSkillEnv(_TASK, obs_mode="rgb")
        try:
            spec = env.observation_spec["sensor_data", "base_camera", "rgb"]
            assert spec.shape == torch.Size([1, 128, 128, 3])
            assert spec.dtype == torch.uint8
            check_env_specs(env, seed=_SEED)
            _assert_matches_raw(env, rendering_env, steps=2)
        finally:
            env.close()

    def test_truncation_at_time_limit(self, raw_envs):
        env = ManiSkillEnv(_TASK, obs_mode="state", max_episode_steps=3)
        raw = raw_envs(obs_mode="state", max_episode_steps=3)
        try:
            _assert_matches_raw(env, raw, steps=3)
            td = env.reset(seed=_SEED)
            rollout = env.rollout(5, tensordict=td, auto_reset=False)
            assert rollout.shape == torch.Size([1, 3])
            assert rollout["next", "truncated"][:, -1].all()
            assert not rollout["next", "truncated"][:, :-1].any()
        finally:
            env.close()

    def test_bool_reward_is_float(self, raw_envs):
        # DrawTriangle-v1 reports a bool (sparse) reward.
        env = ManiSkillEnv("DrawTriangle-v1", obs_mode="state")
        raw = raw_envs("DrawTriangle-v1", obs_mode="state")
        try:
            raw.reset(seed=_SEED)
            assert raw.step(raw.action_space.sample())[1].dtype == torch.bool
            _assert_matches_raw(env, raw, steps=2)
        finally:
            env.close()

    def test_multi_agent_matches_maniskill(self, raw_envs):
        env = ManiSkillEnv("TwoRobotPickCube-v1", obs_mode="state")
        raw = raw_envs("TwoRobotPickCube-v1", obs_mode="state")
        try:
            _assert_matches_raw(env, raw, steps=2)
        finally:
            env.close()

    def test_outputs_are_not_overwritten(self):
        env = ManiSkillEnv(_TASK, obs_mode="state")
        try:
            torch.manual_seed(_SEED)
            rollout = env.rollout(4, tensordict=env.reset(seed=_SEED), auto_reset=False)
            obs = rollout["next", "observation"]
            assert not (obs[:, 1:] == obs[:, :-1]).all(-1).any()
            steps = rollout["next", "elapsed_steps"]
            assert steps.tolist() == [[1, 2, 3, 4]]
        finally:
            env.close()


@requires_maniskill
class TestManiSkillSeeding:
    def test_reset_seed_matches_maniskill(self, raw_envs):
        env = ManiSkillEnv(_TASK, obs_mode="state")
        raw = raw_envs(obs_mode="state")
        try:
            for seed in (0, 1):
                obs, _ = raw.reset(seed=seed)
                _assert_obs_equal(env.reset(seed=seed), obs, _CPU)
        finally:
            env.close()

    def test_set_seed(self, raw_envs):
        envs = [ManiSkillEnv(_TASK, obs_mode="state") for _ in range(2)]
        raw = raw_envs(obs_mode="state")
        try:
            first, second = [], []
            for env in envs:
                env.set_seed(_SEED)
                first.append(env.reset())
                second.append(env.reset())
            obs, _ = raw.reset(seed=_SEED)
            _assert_obs_equal(first[0], obs, _CPU)
            torch.testing.assert_close(first[0]["observation"], first[1]["observation"])
            torch.testing.assert_close(
                second[0]["observation"], second[1]["observation"]
            )
            # The seed of a later reset is drawn from the first one's.
            assert (first[0]["observation"] != second[0]["observation"]).any()
        finally:
            for env in envs:
                env.close()


@requires_maniskill
class TestManiSkillState:
    def test_get_state_matches_maniskill(self, raw_envs):
        env = ManiSkillEnv(_TASK, obs_mode="state")
        raw = raw_envs(obs_mode="state")
        try:
            env.reset(seed=_SEED)
            raw.reset(seed=_SEED)
            state = env.get_state()
            assert state.batch_size == torch.Size([1])
            raw_state = raw.unwrapped.get_state_dict()
            for key, value in _leaves(raw_state):
                torch.testing.assert_close(state.get(key), value, rtol=0, atol=0)
        finally:
            env.close()

    def test_reset_to_saved_state(self):
        env = ManiSkillEnv(_TASK, obs_mode="state")
        try:
            start = env.reset(seed=_SEED)
            state = env.get_state()
            torch.manual_seed(_SEED)
            env.rollout(3, tensordict=start, auto_reset=False)
            td = env.reset(set_state=True, scene_state=state)
            torch.testing.assert_close(td["observation"], start["observation"])
            env.rollout(3, tensordict=td, auto_reset=False)
            td = env.reset_to_state(state)
            torch.testing.assert_close(td["observation"], start["observation"])
            # One env's state, without the batch dim, as a trajectory file holds it.
            td = env.reset_to_state(state[0])
            torch.testing.assert_close(td["observation"], start["observation"])
        finally:
            env.close()

    def test_bad_states_are_refused(self):
        env = ManiSkillEnv(_TASK, obs_mode="state")
        try:
            env.reset(seed=_SEED)
            state = env.get_state()
            with pytest.raises(ValueError, match="scene_state"):
                env.reset(set_state=True)
            key = next(iter(state.keys(True, True)))
            with pytest.raises(ValueError, match="missing"):
                env.reset_to_state(state.exclude(key))
            bad = state.clone()
            bad.set(key, bad.get(key)[..., :1])
            with pytest.raises(ValueError, match="shape"):
                env.reset_to_state(bad)
        finally:
            env.close()


@requires_maniskill
class TestManiSkillPixels:
    @pytest.mark.parametrize("pixels_only", [False, True])
    def test_pixels_match_render(self, pixels_only, rendering_env):
        raw = rendering_env
        env = ManiSkillEnv(
            _TASK,
            obs_mode="rgb",
            from_pixels=True,
            pixels_only=pixels_only,
            pixels_key="frames",
        )
        try:
            spec = env.observation_spec["frames"]
            assert spec.dtype == torch.uint8
            sensor_key = ("sensor_data", "base_camera", "rgb")
            assert (sensor_key in env.observation_spec.keys(True)) != pixels_only
            td = env.reset(seed=_SEED)
            raw.reset(seed=_SEED)
            frame = torch.as_tensor(raw.render()).to(env.device)
            assert td["frames"].shape == spec.shape == frame.shape
            torch.testing.assert_close(td["frames"], frame, rtol=0, atol=0)
            td = env.rand_step(td)
            raw.step(_raw_action(td))
            frame = torch.as_tensor(raw.render()).to(env.device)
            torch.testing.assert_close(td["next", "frames"], frame, rtol=0, atol=0)
            check_env_specs(env, seed=_SEED)
        finally:
            env.close()


@requires_maniskill
class TestManiSkillWrapper:
    def test_wrapper_matches_maniskill(self, raw_envs):
        wrapped = _raw_env(obs_mode="state_dict")
        env = ManiSkillWrapper(wrapped)
        raw = raw_envs(obs_mode="state_dict")
        try:
            assert env.base_env is wrapped.unwrapped
            check_env_specs(env, seed=_SEED)
            _assert_matches_raw(env, raw)
        finally:
            env.close()

    def test_collector(self):
        env = ManiSkillEnv(_TASK, obs_mode="state")
        env.set_seed(_SEED)
        collector = Collector(env, None, frames_per_batch=4, total_frames=8)
        try:
            batches = list(collector)
            assert len(batches) == 2
            for batch in batches:
                assert batch.numel() == 4
                assert batch["next", "reward"].dtype == torch.float32
        finally:
            collector.shutdown()
            env.close()

    def test_num_workers_returns_parallel_env(self):
        env = ManiSkillEnv(_TASK, obs_mode="state", num_workers=2)
        try:
            assert isinstance(env, ParallelEnv)
            assert env.batch_size == torch.Size([2, 1])
            check_env_specs(env, seed=_SEED)
        finally:
            env.close()


@requires_maniskill
class TestManiSkillErrors:
    def test_maniskill_not_installed(self, monkeypatch):
        monkeypatch.setattr(maniskill_lib, "_has_maniskill", False)
        with pytest.raises(ImportError, match="pip install mani_skill"):
            ManiSkillEnv(_TASK)

    def test_unknown_task(self):
        with pytest.raises(ValueError, match="available_envs"):
            ManiSkillEnv("PickCub-v1")

    def test_several_envs_on_cpu_sim(self):
        message = (
            "num_envs=2 on ManiSkill's CPU sim, which holds one env per process: pass "
            "num_workers=2 for a ParallelEnv of single envs, or sim_backend='gpu' on a "
            "CUDA machine."
        )
        with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
            ManiSkillEnv(_TASK, num_envs=2, sim_backend="cpu")

    def test_bad_arguments(self):
        with pytest.raises(ValueError, match="from_pixels"):
            ManiSkillEnv(_TASK, pixels_only=True)
        with pytest.raises(ValueError, match="batch_size"):
            ManiSkillEnv(_TASK, batch_size=[3])

    def test_not_a_maniskill_env(self):
        import gymnasium as gym

        env = gym.make("CartPole-v1")
        with pytest.raises(TypeError, match="GymWrapper"):
            ManiSkillWrapper(env)

    def test_auto_reset_refused(self):
        from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

        raw = ManiSkillVectorEnv(_raw_env(obs_mode="state"), auto_reset=True)
        try:
            with pytest.raises(ValueError, match="auto_reset=False"):
                ManiSkillWrapper(raw)
        finally:
            raw.close()

    def test_missing_action(self):
        env = ManiSkillEnv(_TASK, obs_mode="state")
        try:
            td = env.reset(seed=_SEED)
            with pytest.raises(KeyError, match="action"):
                env.step(td)
        finally:
            env.close()


@requires_maniskill
@pytest.mark.skipif(not _has_hydra, reason="Hydra is not installed")
class TestManiSkillConfig:
    @pytest.mark.parametrize("from_pixels", [False, True])
    def test_config_instantiates(self, from_pixels, rendering_env):
        from hydra.utils import instantiate

        from torchrl.trainers.algorithms.configs import ManiSkillEnvConfig

        cfg = ManiSkillEnvConfig(
            env_name=_TASK, obs_mode="state", from_pixels=from_pixels
        )
        env = instantiate(cfg)
        try:
            assert isinstance(env, ManiSkillEnv)
            assert ("pixels" in env.observation_spec.keys()) == from_pixels
            check_env_specs(env, seed=_SEED)
        finally:
            env.close()


_NO_GPU_SIM = 3  # exit code of _gpu_sim_smoke where the GPU sim cannot start


def _gpu_sim_smoke() -> int:
    """The GPU sim's smoke test, run in a process of its own (see below)."""
    import sapien.physx as physx

    try:
        physx.enable_gpu()
    except Exception as err:  # e.g. SAPIEN could not fetch its PhysX GPU library
        print(f"ManiSkill's GPU sim cannot start here: {err}")
        return _NO_GPU_SIM
    env = ManiSkillEnv(_TASK, num_envs=4, sim_backend="gpu", obs_mode="state")
    try:
        assert env.gpu_sim_enabled
        assert env.device.type == "cuda"
        assert env.batch_size == torch.Size([4])
        check_env_specs(env, seed=_SEED)
        td = env.reset(seed=_SEED)
        torch.manual_seed(_SEED)
        rollout = env.rollout(3, tensordict=td, auto_reset=False)
        assert rollout.shape == torch.Size([4, 3])
        for value in rollout.values(True, True):
            assert value.device == env.device
        # A partial reset resets the masked envs only.
        td = rollout[:, -1].get("next").clone()
        td["_reset"] = torch.tensor(
            [[True], [False], [False], [False]], device=env.device
        )
        out = env.reset(td)
        torch.testing.assert_close(out["observation"][1:], td["observation"][1:])
        assert out["elapsed_steps"][0] == 0
        assert (out["elapsed_steps"][1:] == td["elapsed_steps"][1:]).all()
    finally:
        env.close()
    return 0


@pytest.mark.gpu
@requires_maniskill
class TestManiSkillGPUSim:
    def test_gpu_sim_smoke(self):
        if not torch.cuda.is_available():
            pytest.skip("ManiSkill's GPU sim needs CUDA")
        # PhysX's GPU mode can only be enabled in a process that has not used PhysX
        # yet, and this one runs the CPU sim: the GPU sim gets a process of its own.
        code = (
            f"import sys; sys.path.insert(0, {os.path.dirname(__file__)!r}); "
            f"from {__name__} import _gpu_sim_smoke; sys.exit(_gpu_sim_smoke())"
        )
        proc = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=600
        )
        if proc.returncode == _NO_GPU_SIM:
            pytest.skip(proc.stdout.strip().splitlines()[-1])
        assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]


if __name__ == "__main__":
    args, unknown = argparse.ArgumentParser().parse_known_args()
    pytest.main([__file__, "--capture", "no", "--exitfirst"] + unknown)
