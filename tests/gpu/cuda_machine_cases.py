"""The library on a machine with CUDA running ManiSkill's CPU sim, stood in for by the test double
of ``tests/support/cuda_double.py``: pictures and ``render()`` come back on ``fakecuda:0`` (CUDA's rules:
no ``.numpy()``, no mixing with CPU tensors) as reused buffers, states on the CPU.

Not collected by ``pytest tests``: ``tests/gpu/test_cuda_machine.py`` runs this file with pytest in a
subprocess whose Python processes (the CPU workers included) all load the double. The oracle of
every value is the same env rendering through ManiSkill's CPU read (``render_backend="cpu"``),
its data moved to ``env.device`` before comparing.
"""

from __future__ import annotations

import functools
import os

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.utils.wrappers import CPUGymWrapper as ManiSkillCPUGymWrapper
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

if os.environ.get("MANISKILL_TORCHRL_CUDA_DOUBLE") != "1":
    pytest.skip("runs under the CUDA double only (tests/gpu/test_cuda_machine.py)", allow_module_level=True)

from maniskill_torchrl import EpisodeMetrics, ManiSkillEnv  # noqa: E402
from maniskill_torchrl.parallel import ManiSkillParallelEnv  # noqa: E402
from maniskill_torchrl.testing import assert_on_device, assert_tensordict_equal  # noqa: E402
from maniskill_torchrl.wrappers import CPUGymWrapper  # noqa: E402
from support.cuda_double import DEVICE  # noqa: E402  (the sitecustomize of tests/gpu/cuda_site installed it)
from support.helpers import close_envs, closed_after_test, random_actions  # noqa: E402, F401  (closed_after_test: the envs fixture)

ENV_ID = "PickCube-v1"
KW = dict(
    obs_mode="rgb",
    render_mode="rgb_array",
    max_episode_steps=5,
    sensor_configs=dict(width=32, height=32),
    human_render_camera_configs=dict(width=32, height=32),
    sim_backend="cpu",  # "auto" would pick the GPU sim for several envs on a CUDA machine
)
ORACLE = dict(KW, render_backend="cpu")  # ManiSkill's CPU read: fresh CPU pictures
STEPS = 7  # 5-step episodes: a done and a reset inside the rollout


def _actions(env, n: int = STEPS, seed: int = 3) -> list:
    shape = tuple(env.action_spec_unbatched.shape)
    return random_actions(gym.spaces.Box(-1.0, 1.0, shape, dtype=np.float32), n, seed=seed)


class Scripted:
    """A policy writing the next of a fixed list of actions on the env's device and batch."""

    def __init__(self, env, actions: list) -> None:
        self.env, self.actions = env, iter(actions)

    def __call__(self, td):
        action = next(self.actions).to(self.env.device).expand(*td.batch_size, -1).clone()
        return td.set("action", action)


def _rollout(env, seed: int = 7) -> TensorDict:
    env.set_seed(seed)
    return env.rollout(STEPS, Scripted(env, _actions(env)), break_when_any_done=False)


def _make(envs: list, **kwargs):
    env = ManiSkillEnv(ENV_ID, **kwargs)
    envs.append(env)
    return env


@pytest.fixture(scope="module")
def batched_oracle():
    """The batched CPU env of 2 sub-envs reading its pictures through ManiSkill's CPU read: the
    oracle of the tests of batched envs, made once (each of its worker processes computes SAPIEN's
    BRDF table at its first picture: seconds of CPU on lavapipe). Every use seeds its rollout."""
    env = ManiSkillEnv(ENV_ID, num_envs=2, from_pixels=True, **ORACLE)
    yield env
    close_envs([env])


def test_the_double_is_a_cuda_machine(envs):
    """Raw ManiSkill under the double, as seen on a lent H200: sapien_cuda, pictures and render()
    on the device, states on the CPU, and a kept picture changes at the next step."""
    raw = gym.make(ENV_ID, num_envs=1, **KW)
    envs.append(raw)
    obs, _ = raw.reset(seed=0)
    assert raw.unwrapped.backend.render_backend == "sapien_cuda"
    rgb = obs["sensor_data"]["base_camera"]["rgb"]
    assert rgb.device == DEVICE and obs["agent"]["qpos"].device.type == "cpu"
    assert raw.render().device == DEVICE
    with pytest.raises(TypeError, match="numpy"):
        rgb.numpy()
    before = rgb.cpu()
    raw.step(raw.action_space.sample())
    assert not torch.equal(rgb.cpu(), before), "the double's buffer is not reused"


@pytest.mark.parametrize(
    "batch_size, from_pixels",
    [(None, True), ([], True), ([], False)],
    ids=["batch1-pixels", "unbatched-pixels", "unbatched"],
)
def test_single_env(envs, batch_size, from_pixels):
    env = _make(envs, batch_size=batch_size, from_pixels=from_pixels, **KW)
    assert env.device == torch.device("cpu")  # the CPU sim's device, whatever renders
    oracle = _make(envs, batch_size=batch_size, from_pixels=from_pixels, **ORACLE)
    got, want = _rollout(env), _rollout(oracle)
    assert_on_device(got, env.device)
    assert_tensordict_equal(got, want)
    frame = env.render()
    assert_on_device(frame, env.device)
    assert torch.equal(frame, oracle.render())
    check_env_specs(env)  # after the comparison: it steps the env


@pytest.mark.parametrize("num_envs", [1, 2])
def test_cpu_sim_with_device_cuda(envs, num_envs, request):
    """device="cuda" on a CPU-sim env: every output on it, actions taken on it, the same values."""
    env = _make(envs, num_envs=num_envs, device=DEVICE, from_pixels=True, **KW)
    assert env.device == DEVICE
    if num_envs == 2:
        oracle = request.getfixturevalue("batched_oracle")
    else:
        oracle = _make(envs, num_envs=num_envs, from_pixels=True, **ORACLE)
    got, want = _rollout(env), _rollout(oracle)
    assert_on_device(got, DEVICE)
    assert_tensordict_equal(got.cpu(), want)
    assert_on_device(env.render(), DEVICE)
    state = env.get_state()
    assert_on_device(state, DEVICE)
    start = env.reset_to_state(state)
    assert_on_device(start, DEVICE)
    assert_tensordict_equal(start.cpu(), oracle.reset_to_state(oracle.get_state()))
    check_env_specs(env)


def test_episode_metrics_keep_the_cpu_sims_summation(envs):
    """A CPU-sim env on the GPU keeps numpy's summation order: returns equal the CPU env's bit for bit."""
    got = _rollout(TransformedEnv(_make(envs, device=DEVICE, **KW), EpisodeMetrics()))
    want = _rollout(TransformedEnv(_make(envs, **ORACLE), EpisodeMetrics()))
    assert_on_device(got, DEVICE)
    assert_tensordict_equal(got["next", "episode"].cpu(), want["next", "episode"])


def test_batched_cpu_env_with_partial_resets(envs, batched_oracle):
    """The batched CPU env's workers serve sapien_cuda pictures and render() (issue 32's crash)."""
    runs = []
    for env in (_make(envs, num_envs=2, from_pixels=True, **KW), batched_oracle):
        td = _rollout(env)
        partial = env.reset(TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=[2]))
        runs.append((td, partial, env.render()))
        assert_on_device(runs[-1], env.device)
    (td, partial, frame), (td_o, partial_o, frame_o) = runs
    assert_tensordict_equal(td, td_o)
    assert_tensordict_equal(partial, partial_o)
    assert torch.equal(frame, frame_o)
    check_env_specs(envs[0])


def test_async_pool_serves_sapien_cuda_pictures_on_the_host(envs, batched_oracle):
    """The split-phase workers render with sapien_cuda and send host copies: the pool (CPU only)
    equals the batched env rendering through ManiSkill's CPU read, pictures included."""
    from maniskill_torchrl import ManiSkillAsyncEnvPool

    kwargs = {k: v for k, v in KW.items() if k != "sim_backend"}
    pool = ManiSkillAsyncEnvPool(ENV_ID, 2, **kwargs)
    envs.append(pool)
    oracle = batched_oracle
    # up to the first episode's end: the pool seeds each env's next episode by its index
    # (test_async_pool.py), the batched env by its reset events
    got, want = [], []
    for env, out in ((pool, got), (oracle, want)):
        env.set_seed(7)
        out.append(env.rollout(4, Scripted(env, _actions(env)), break_when_any_done=False))
    got, want = got[0].exclude("env_index"), want[0].exclude("pixels", ("next", "pixels"))
    assert_on_device(got, torch.device("cpu"))
    assert_tensordict_equal(got, want.to("cpu"))


def test_parallel_env_of_singles(envs):
    make = functools.partial(ManiSkillEnv, ENV_ID, batch_size=[], **KW)
    env = ManiSkillParallelEnv(2, make)
    envs.append(env)
    check_env_specs(env)
    td = env.rollout(STEPS, break_when_any_done=False)
    assert_on_device(td, env.device)
    partial = env.reset(TensorDict({"_reset": torch.tensor([[False], [True]])}, batch_size=[2]))
    assert_on_device(partial, env.device)


def test_gym_shim_equals_maniskills_cpu_gym_wrapper(envs):
    """The gym shim returns numpy, as ManiSkill's CPUGymWrapper does, and the same values."""
    ours = CPUGymWrapper(gym.make(ENV_ID, num_envs=1, **KW), record_metrics=True)
    theirs = ManiSkillCPUGymWrapper(gym.make(ENV_ID, num_envs=1, **KW), record_metrics=True)
    envs.extend([ours, theirs])
    actions = [a.numpy() for a in random_actions(ours.action_space, STEPS, seed=5)]
    outs = []
    for env in (ours, theirs):
        out = [env.reset(seed=4)]
        for a in actions:
            out.append(env.step(a))
        out.append(env.render())
        outs.append(out)
    for i, (a, b) in enumerate(zip(*outs)):
        _same(a, b, f"call {i}")
    rgb = outs[0][1][0]["sensor_data"]["base_camera"]["rgb"]
    assert isinstance(rgb, np.ndarray)


def _same(a, b, where: str) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    else:
        assert type(a) is type(b), f"{where}: {type(a)} vs {type(b)}"
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes(), where
