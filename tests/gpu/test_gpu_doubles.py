"""The GPU sim's path, proven on the CPU: what ManiSkill's GPU sim does differently from the CPU
sim here, reproduced by test doubles at ManiSkill's own seams.

- Reused buffers: on the GPU sim (and the CPU sim rendering with ``sapien_cuda``) SAPIEN renders
  every picture into one stored buffer, and ManiSkill hands out views of it. The double makes
  ManiSkill's camera read (``RenderCamera.get_picture``) do the same on the CPU and says so the
  way ManiSkill decides it (``backend.render_backend == "sapien_cuda"``). The oracle is the same
  ManiSkill env without the double, which copies every picture out through numpy.
- Device names: ManiSkill says ``cuda``, TorchRL ``cuda:0``.
- Host syncs and op counts: counted with a dispatch mode on CPU tensors (a sync on CUDA is an op
  that reads a value back: ``nonzero``, ``item``, ``bool``).
- ``EpisodeMetrics``: its running state in the tensordict (branching, against ``StepCounter``)
  and its GPU-sim summation against ``ManiSkillVectorEnv(record_metrics=True)`` itself, run on
  the CPU sim.
- Envs the library cannot serve: auto-resetting wrappers, ``frame_skip``, a reconfiguration
  that partial resets cannot do.

``tests/gpu`` runs the real thing where CUDA and SAPIEN's PhysX GPU library are present.
"""

from __future__ import annotations

import contextlib
from collections import Counter

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.utils.structs.render_camera import RenderCamera
from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv
from tensordict import TensorDict
from torch.utils._python_dispatch import TorchDispatchMode
from torchrl.collectors import Collector
from torchrl.envs import Compose, StepCounter, TransformedEnv

from maniskill_torchrl import ActionRepeat, EpisodeMetrics, ManiSkillEnv, ManiSkillWrapper
from maniskill_torchrl.envs import maniskill as adapter
from maniskill_torchrl.envs.maniskill import _reuses_buffers as reuses_buffers
from support.helpers import alone_where_cuda, assert_same, bits, close_envs, make_gym_env, random_actions
from support.toy_env import ToyEnv

# Ops that read a device value back to the host: each one is a CUDA host sync.
SYNC_OPS = ("nonzero", "is_nonzero", "_local_scalar_dense", "item", "equal")


class CountOps(TorchDispatchMode):
    """Counts the aten ops run inside it, by name (``aten.add.Tensor`` -> ``"add"``)."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[func.overloadpacket.__name__] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def syncs(self) -> int:
        return sum(self.ops[name] for name in SYNC_OPS)


# ----------------------------------------------------------------------------- reused buffers
RGB_KWARGS = dict(
    obs_mode="rgb",
    render_backend="cpu",  # the oracle: ManiSkill's CPU read (on a CUDA machine, in a process of its own)
    render_mode="rgb_array",
    max_episode_steps=7,
    sensor_configs=dict(width=32, height=32),
    human_render_camera_configs=dict(width=32, height=32),
)


@contextlib.contextmanager
def sapien_reused_pictures(gym_env: gym.Env):
    """ManiSkill's camera read as on the GPU sim: each picture is copied into one buffer per camera
    and texture, which every later read overwrites, and that buffer is returned (ManiSkill's
    shaders then slice views of it, e.g. ``rgb = Color[..., :3]``). The env reports
    ``render_backend="sapien_cuda"``, where ManiSkill takes that road on the CPU sim."""
    original = RenderCamera.get_picture
    buffers: dict = {}
    backend = gym_env.unwrapped.backend
    render_backend = backend.render_backend

    def get_picture(self, names):
        backend.render_backend = render_backend  # the picture itself: ManiSkill's CPU read
        try:
            fresh = original(self, names)
        finally:
            backend.render_backend = "sapien_cuda"
        names = [names] if isinstance(names, str) else names
        out = []
        for name, picture in zip(names, fresh):
            buf = buffers.get((id(self), name))
            if buf is None:
                buf = buffers[id(self), name] = torch.empty_like(picture)
            buf.copy_(picture)
            out.append(buf)
        return out

    RenderCamera.get_picture = get_picture
    backend.render_backend = "sapien_cuda"
    try:
        yield buffers
    finally:
        RenderCamera.get_picture = original
        backend.render_backend = render_backend


class Scripted:
    """A collector policy that writes the next of a fixed list of actions."""

    def __init__(self, actions: list[torch.Tensor]) -> None:
        self._actions = iter(actions)

    def __call__(self, td):
        td.set("action", next(self._actions).expand(td.batch_size + (-1,)).clone())
        return td


def _wrap(gym_env, keep: list) -> ManiSkillWrapper:
    """A wrapper around the test's gym env, kept alive in ``keep`` until the test ends: a collected
    wrapper closes its env, which the test's next wrappers share."""
    env = ManiSkillWrapper(gym_env, from_pixels=True)
    keep.append(env)
    return env


def _pipeline(gym_env, steps: int, keep: list) -> TensorDict:
    """ManiSkillWrapper -> ActionRepeat(2) -> EpisodeMetrics in a Collector, seeded, scripted."""
    env = TransformedEnv(_wrap(gym_env, keep), Compose(ActionRepeat(2), EpisodeMetrics()))
    keep.append(env)
    env.set_seed(5)
    actions = random_actions(gym_env.unwrapped.single_action_space, steps + 1, seed=11)
    # No total_frames: a collector that reaches it closes its env, which the next run reuses.
    collector = Collector(env, Scripted(actions), frames_per_batch=steps, total_frames=-1)
    batch = next(iter(collector))
    collector.shutdown(close_env=False)
    return batch


@pytest.mark.pictures
def test_reused_picture_buffers_do_not_alias_returned_data(request):
    # The oracle renders with render_backend="cpu": on a CUDA machine, alone in its own process.
    if alone_where_cuda(request):
        return
    rgb_env, keep = make_gym_env("PickCube-v1", **RGB_KWARGS), []
    try:
        _reused_picture_buffers(rgb_env, keep)
    finally:
        close_envs([*keep, rgb_env])


def _reused_picture_buffers(rgb_env, keep: list) -> None:
    steps = 6  # 7-step episodes, repeat 2: an episode ends mid-repeat, and a reset follows
    actions = random_actions(rgb_env.unwrapped.single_action_space, steps, seed=3)

    def rollout(env):
        env.set_seed(9)
        td = env.reset()
        out = [td.clone()]  # the reference: what the env returned, copied at once
        kept = [td.exclude("action")]  # what a user keeps: the returned tensors themselves
        for a in actions:
            td = env.step(td.set("action", a.unsqueeze(0)))["next"]
            out.append(td.clone())
            kept.append(td.exclude("action"))
        return out, kept

    assert not reuses_buffers(rgb_env.unwrapped)
    expected, _ = rollout(_wrap(rgb_env, keep))
    with sapien_reused_pictures(rgb_env) as buffers:
        env = _wrap(rgb_env, keep)
        assert reuses_buffers(rgb_env.unwrapped)
        got, kept = rollout(env)
        assert buffers, "the double saw no camera read"
        batch = _pipeline(rgb_env, steps, keep)
    # The frames change from step to step: an aliased frame would show.
    frames = [td["sensor_data", "base_camera", "rgb"] for td in expected]
    assert any(not torch.equal(frames[0], f) for f in frames[1:])
    assert any(not torch.equal(expected[0]["pixels"], td["pixels"]) for td in expected[1:])
    for i, (want, now, later) in enumerate(zip(expected, got, kept)):
        assert_same(now, want, f"step {i} as returned")
        assert_same(later, want, f"step {i} after the later steps")

    reference = _pipeline(rgb_env, steps, keep)  # the same pipeline on ManiSkill's copying CPU read
    assert_same(batch, reference, "collector batch")
    rgb = reference["next", "sensor_data", "base_camera", "rgb"]
    assert any(not torch.equal(rgb[:, 0], rgb[:, t]) for t in range(1, steps))


# ----------------------------------------------------------------------------- devices
@pytest.mark.parametrize(
    "a, b, current, same",
    [
        ("cuda", "cuda:0", 0, True),
        ("cuda", torch.device("cuda", 0), 0, True),
        ("cuda", "cuda:0", 1, False),  # "cuda" is the current device
        ("cuda", "cuda:1", 1, True),
        ("physx_cuda:0", "cuda:0", 0, True),
        ("physx_cuda", "cuda:1", 1, True),
        ("gpu", "cuda:0", 0, True),
        ("physx_cpu", "cpu", 0, True),
        ("cpu", "cuda:0", 0, False),
        ("cuda:1", "cuda:0", 0, False),
    ],
)
def test_device_names_compare_with_an_index(a, b, current, same, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # what a CUDA machine answers
    monkeypatch.setattr(torch.cuda, "current_device", lambda: current)
    assert (adapter._canonical_device(a) == adapter._canonical_device(b)) == same


@pytest.fixture
def gym_env():
    env = make_gym_env("PickCube-v1", obs_mode="state")
    yield env
    close_envs([env])


def test_cuda_device_named_either_way(monkeypatch):
    """The env's device: the sim's when none is asked (ManiSkill's GPU sim says "cuda", TorchRL
    "cuda:0"), else the one asked for, named either way."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # what a CUDA machine answers
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    # The wrapper's own check, on what it reads: the sim's device.
    wrapper = type("Sim", (), {"_sim_device": adapter._canonical_device("cuda")})()
    for device in ("cuda", "cuda:0", torch.device("cuda:0"), None):
        assert ManiSkillWrapper._checked_device(wrapper, device) == torch.device("cuda", 0)
    assert ManiSkillWrapper._checked_device(wrapper, "cpu") == torch.device("cpu")
    assert ManiSkillWrapper._checked_device(wrapper, "cuda:1") == torch.device("cuda", 1)


def test_device_that_is_not_there_is_refused(gym_env, monkeypatch):
    env = ManiSkillWrapper(gym_env, device="cpu")
    assert env.device == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # a machine without CUDA
    with pytest.raises(ValueError, match=r"device='cuda:0', but torch.cuda.is_available\(\) is False"):
        ManiSkillWrapper(gym_env, device="cuda:0")
    with pytest.raises(ValueError, match=r"device='nowhere' is not a torch device"):
        ManiSkillWrapper(gym_env, device="nowhere")


def _cuda_machine(monkeypatch, devices: int) -> None:
    """What torch answers on a machine with ``devices`` CUDA devices, device 0 current."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: devices)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)


def test_sim_device_is_read_from_the_built_env(gym_env, monkeypatch):
    """``sim_backend="physx_cuda:1"``: the sim's device is what ManiSkill reports (cuda:1), not a
    guess from the backend's name (which gave the current device, cuda:0). The env stands for
    ManiSkill's GPU sim on device 1; outputs are asked on the CPU so that no tensor is made there."""
    _cuda_machine(monkeypatch, 2)
    monkeypatch.setattr(gym_env.unwrapped, "device", torch.device("cuda", 1))
    made = []

    def make(env_id, **kwargs):
        made.append(kwargs["sim_backend"])
        return gym_env

    monkeypatch.setattr(gym, "make", make)
    env = adapter.ManiSkillEnv("PickCube-v1", sim_backend="physx_cuda:1", device="cpu", obs_mode="state")
    assert made == ["physx_cuda:1"]
    assert env._sim_device == torch.device("cuda", 1) and env.device == torch.device("cpu")
    # Actions and partial-reset indices go to the sim's device, cuda:1: not the env's.
    assert env.device != env._sim_device
    wrapper = ManiSkillWrapper(gym_env, device="cpu")
    assert wrapper._sim_device == torch.device("cuda", 1)


def test_sim_device_that_is_not_there_is_refused(monkeypatch):
    """``physx_cuda:1`` on a one-GPU machine is refused before anything is built."""
    _cuda_machine(monkeypatch, 1)
    monkeypatch.setattr(gym, "make", lambda *a, **k: pytest.fail("gym.make was called"))
    for backend in ("physx_cuda:1", "cuda:3", "physx_cuda:x"):
        with pytest.raises(ValueError, match=r"names CUDA device .* this machine has 1"):
            adapter.ManiSkillEnv("PickCube-v1", num_envs=2, sim_backend=backend)


# ----------------------------------------------------------------------------- host syncs
def test_partial_reset_makes_one_host_sync(gym_env, monkeypatch):
    """A reset with a ``"_reset"`` mask reads which envs once (one ``nonzero``), whether it
    resets some, all or none of them. The sim is a stand-in answering as a 3-env GPU sim would."""
    base = gym_env.unwrapped
    obs, info = gym_env.reset(seed=0)
    monkeypatch.setattr(base, "num_envs", 3)
    env = ManiSkillWrapper(gym_env)
    obs = obs.expand(3, -1).clone()
    info = {k: v.expand(3, *v.shape[1:]).clone() if torch.is_tensor(v) else v for k, v in info.items()}
    calls = []

    def reset(*, seed=None, options=None):
        calls.append(options)
        return obs, info

    monkeypatch.setattr(env, "_env", type("Sim", (), {"reset": staticmethod(reset)})())
    for mask, env_idx in (([True, False, True], [0, 2]), ([True, True, True], None), ([False, False, False], "none")):
        calls.clear()
        with CountOps() as ops:
            env._reset(TensorDict({"_reset": torch.tensor(mask).unsqueeze(-1)}, batch_size=[3]))
        assert ops.syncs == 1 and ops.ops["nonzero"] == 1, ops.ops
        if env_idx == "none":
            assert calls == []
        elif env_idx is None:
            assert "env_idx" not in calls[0]
        else:
            assert calls[0]["env_idx"].tolist() == env_idx


# ----------------------------------------------------------------------------- EpisodeMetrics
def _episode_step_ops(batch: int, lengths: torch.Tensor) -> CountOps:
    """The ops of one EpisodeMetrics step (running summation) from a root whose episodes are
    ``lengths`` steps long."""
    env = TransformedEnv(ToyEnv([10**6] * batch), EpisodeMetrics(summation="running"))
    root = env.reset()
    root["episode", "episode_len"] = lengths
    root["episode", "return"] = torch.randn(batch)
    next_td = env.base_env._step(env.rand_action(root))
    with CountOps() as ops:
        out = env.transform._step(root, next_td)
    assert torch.equal(out["episode", "episode_len"], lengths + 1)
    return ops


def test_episode_metrics_running_sum_ops_do_not_grow_with_episodes():
    """4096 envs with lengths spread up to 1000 (about 980 distinct): the same few ops as
    4096 fresh episodes, and none that would sync the host on CUDA."""
    g = torch.Generator().manual_seed(0)
    spread = torch.randint(0, 1000, (4096,), generator=g)
    assert spread.unique().numel() > 900
    long = _episode_step_ops(4096, spread)
    fresh = _episode_step_ops(4096, torch.zeros(4096, dtype=torch.int64))
    assert long.ops == fresh.ops
    assert long.syncs == 0, long.ops
    assert long.total <= 12, long.ops


def test_episode_metrics_default_summation_by_device():
    env = TransformedEnv(ToyEnv([3, 5]), EpisodeMetrics())
    env.rollout(2)
    assert env.transform._stats.summation == "numpy"
    with pytest.raises(ValueError, match="summation='sum'"):
        EpisodeMetrics(summation="sum")
    assert repr(EpisodeMetrics(summation="running")) == "EpisodeMetrics(summation='running')"


@pytest.mark.parametrize("summation", ["numpy", "running"])
def test_episode_metrics_branching_from_a_root(summation):
    """Two rollouts from one root: both start from the root's metrics, as StepCounter does (the
    toy env is not rewound, so the two branches get different rewards)."""
    env = TransformedEnv(ToyEnv([50, 60]), Compose(StepCounter(), EpisodeMetrics(summation=summation)))
    first = env.rollout(5, break_when_any_done=False)
    root = first[..., -1]["next"]
    for _ in range(2):
        branch = env.rollout(12, tensordict=root.clone(), auto_reset=False, break_when_any_done=False)
        ep = branch["next", "episode"]
        assert torch.equal(ep["episode_len"], branch["next", "step_count"].squeeze(-1))
        assert ep["episode_len"][:, 0].tolist() == [6, 6]
        for i in range(2):
            rewards = torch.cat([first["next", "reward"][i, :, 0], branch["next", "reward"][i, :, 0]])
            total = root["episode", "return"][i]
            for t in range(12):
                if summation == "running":
                    total = total + rewards[5 + t]
                else:  # CPUGymWrapper's np.sum over the whole episode: the root's rewards and the branch's
                    total = np.sum(rewards[: 6 + t].numpy())
                assert bits(ep["return"][i, t].numpy()) == bits(np.asarray(total, np.float32)), (i, t)


@pytest.mark.parametrize("env_id, steps", [("PickCube-v1", 30), ("MS-CartpoleBalance-v1", 40)])
def test_running_summation_equals_maniskill_vector_env(env_id, steps):
    """EpisodeMetrics(summation="running") on ManiSkillVectorEnv(auto_reset=False) equals that
    wrapper's own record_metrics=True, bit for bit (the GPU sim's anchor, on the CPU sim)."""
    kwargs = dict(obs_mode="state", max_episode_steps=steps)
    ref_gym, ours_gym = make_gym_env(env_id, **kwargs), make_gym_env(env_id, **kwargs)
    try:
        ref = ManiSkillVectorEnv(ref_gym, auto_reset=False, ignore_terminations=True, record_metrics=True)
        vec = ManiSkillVectorEnv(ours_gym, auto_reset=False, ignore_terminations=True)
        env = TransformedEnv(ManiSkillWrapper(vec), EpisodeMetrics(summation="running"))
        actions = random_actions(ref.single_action_space, steps, seed=1)
        obs, _ = ref.reset(seed=2)
        td = env.reset(seed=2)
        assert torch.equal(obs, td["observation"])
        for a in actions:
            obs, reward, terminated, truncated, info = ref.step(a.unsqueeze(0))
            td = env.step(td.set("action", a.unsqueeze(0)))["next"]
            assert torch.equal(obs, td["observation"]) and torch.equal(reward.float(), td["reward"].squeeze(-1))
            assert torch.equal(terminated, td["terminated"].squeeze(-1))
            for key, value in info["episode"].items():
                ours = td["episode", key]
                if ours.dtype == torch.float32:  # return, reward: same bits
                    assert bits(value.numpy()) == bits(ours.numpy()), key
                else:  # episode_len is int32 there (elapsed_steps), int64 here
                    assert value.tolist() == ours.tolist(), key
        assert bool(truncated)
        returns = [td["episode", "return"].item(), info["episode"]["return"].item()]
        assert returns[0] == returns[1]
    finally:
        close_envs([ref_gym, ours_gym])


# ----------------------------------------------------------------------------- refused envs
def test_auto_resetting_envs_are_refused(gym_env):
    with pytest.raises(ValueError, match=r"ManiSkillVectorEnv\(auto_reset=True\).*auto_reset=False"):
        ManiSkillWrapper(ManiSkillVectorEnv(gym_env))
    with pytest.raises(ValueError, match=r"gymnasium.wrappers.Autoreset"):
        ManiSkillWrapper(gym.wrappers.Autoreset(gym_env))
    env = ManiSkillWrapper(ManiSkillVectorEnv(gym_env, auto_reset=False))
    assert env.batch_size == torch.Size([1])


def test_maniskill_vector_env_without_auto_reset_equals_raw():
    """Wrapped ManiSkillVectorEnv(auto_reset=False): the raw env's data, the final observation of
    each episode kept, then TorchRL's own reset (seeded resets, a raw loop as the oracle)."""
    kwargs = dict(obs_mode="state", max_episode_steps=4)
    raw, ours_gym = make_gym_env("PickCube-v1", **kwargs), make_gym_env("PickCube-v1", **kwargs)
    try:
        env = ManiSkillWrapper(ManiSkillVectorEnv(ours_gym, auto_reset=False))
        env.set_seed(4)
        space = raw.unwrapped.single_action_space
        rollout = env.rollout(10, break_when_any_done=False, policy=_Fixed(random_actions(space, 10)))
        rng = np.random.RandomState(4)  # the documented seeds after set_seed(4)
        seeds = [4, int(rng.randint(2**31)), int(rng.randint(2**31))]
        obs, _ = raw.reset(seed=seeds.pop(0))
        for t, a in enumerate(random_actions(space, 10)):
            assert torch.equal(rollout["observation"][:, t], obs), t
            obs, reward, terminated, truncated, _ = raw.step(a.unsqueeze(0))
            assert torch.equal(rollout["next", "observation"][:, t], obs), t
            assert torch.equal(rollout["next", "truncated"][:, t, 0], truncated), t
            if truncated.item():
                obs, _ = raw.reset(seed=seeds.pop(0))
        assert rollout["next", "done"].sum().item() == 2
    finally:
        close_envs([raw, ours_gym])


class _Fixed:
    def __init__(self, actions):
        self._it = iter(actions)

    def __call__(self, td):
        return td.set("action", next(self._it).unsqueeze(0))


def test_frame_skip_is_refused(gym_env):
    with pytest.raises(ValueError, match=r"frame_skip=2 is not supported.*ActionRepeat\(2\)"):
        ManiSkillWrapper(gym_env, frame_skip=2)
    with pytest.raises(ValueError, match=r"frame_skip=3 is not supported"):
        ManiSkillEnv("PickCube-v1", frame_skip=3)


def test_reconfiguration_that_partial_resets_cannot_do_is_refused(gym_env, monkeypatch):
    base = gym_env.unwrapped
    vec = ManiSkillVectorEnv(gym_env, auto_reset=False, ignore_terminations=True)
    monkeypatch.setattr(base, "num_envs", 4)  # a GPU-sim batch
    monkeypatch.setattr(base, "reconfiguration_freq", 1)
    # The adapter's checks of an env, on the options they read.
    options = type("Options", (), {"_from_pixels": False})()
    with pytest.raises(ValueError, match=r"reconfiguration_freq=1 with num_envs=4.*reconfiguration_freq=0"):
        adapter.ManiSkillWrapper._check_kwargs(options, {"env": gym_env})
    # Envs that end together never reset partially: ManiSkillVectorEnv's own exception.
    adapter.ManiSkillWrapper._check_kwargs(options, {"env": vec})
    monkeypatch.setattr(base, "reconfiguration_freq", 0)
    adapter.ManiSkillWrapper._check_kwargs(options, {"env": gym_env})
