"""The gym shim gives ManiSkill's ``CPUGymWrapper`` / ``ActionRepeatWrapper`` outputs bit for bit.

Every comparison runs ManiSkill's wrapper and ours on two env instances made alike,
in lockstep (ManiSkill's outputs may alias buffers that later steps mutate), with
the same actions and a seed on every reset, and checks values by bits, dtypes,
shapes and python types recursively (:func:`assert_same`).
"""

from __future__ import annotations

import doctest
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.utils.common import to_numpy
from mani_skill.utils.wrappers import ActionRepeatWrapper as MSActionRepeatWrapper
from mani_skill.utils.wrappers import CPUGymWrapper as MSCPUGymWrapper
from mani_skill.utils.wrappers import RecordEpisode

import maniskill_torchrl.wrappers.action_repeat as action_repeat_module
import maniskill_torchrl.wrappers.gymnasium as gymnasium_module
from maniskill_torchrl._internal.episode_stats import EpisodeStats
from maniskill_torchrl.wrappers import ActionRepeatWrapper, CPUGymWrapper
from maniskill_torchrl.wrappers._common import np_unbatch
from support.helpers import assert_same, close_envs, make_gym_env, random_actions
from support.maniskill_versions import nightly_action_repeat_bug

# MS-CartpoleBalance-v1's float64 Box bounds: gymnasium's casting warning, not ours.
pytestmark = pytest.mark.filterwarnings("ignore:.*precision lowered by casting")


# ----------------------------------------------------------------------------- comparison


def test_assert_same_is_strict():
    with pytest.raises(AssertionError):
        assert_same(1, True)
    with pytest.raises(AssertionError):
        assert_same(np.float32(0.0), np.float32(-0.0))
    with pytest.raises(AssertionError):
        assert_same({"a": 1, "b": 2}, {"b": 2, "a": 1})
    with pytest.raises(AssertionError):
        assert_same(np.zeros(2, np.float32), np.zeros(2, np.float64))
    with pytest.raises(AssertionError):
        assert_same(0.1, 0.1 + 1e-17 * 10)
    assert_same({"x": [np.float32(np.nan)]}, {"x": [np.float32(np.nan)]})


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def env_pair() -> Callable[..., tuple[gym.Env, gym.Env]]:
    """Two ManiSkill envs made alike (ManiSkill's wrapper goes on the first, ours on the second).

    Shared through the module: each test wraps them anew (wrapping neither steps nor
    resets) and starts with a seeded reset; both always see the same calls.
    """
    cache: dict[tuple, tuple[gym.Env, gym.Env]] = {}

    def get(task: str, obs_mode: str = "state", max_episode_steps: int = 10):
        key = (task, obs_mode, max_episode_steps)
        if key not in cache:
            cache[key] = tuple(
                make_gym_env(task, obs_mode=obs_mode, max_episode_steps=max_episode_steps) for _ in range(2)
            )
        return cache[key]

    yield get
    close_envs(env for pair in cache.values() for env in pair)


def _as_numpy(x):
    return {k: _as_numpy(v) for k, v in x.items()} if isinstance(x, dict) else x.numpy().copy()


def _actions(env: gym.Env, n: int, seed: int = 0) -> list:
    """Torch actions, every other one as numpy (both kinds users pass)."""
    acts = random_actions(env.unwrapped.single_action_space, n, seed=seed)
    return [a if i % 2 == 0 else _as_numpy(a) for i, a in enumerate(acts)]


def _copy_action(a):
    if isinstance(a, dict):
        return {k: _copy_action(v) for k, v in a.items()}
    return a.clone() if isinstance(a, torch.Tensor) else a.copy()


def run_cpu_gym_lockstep(ref: gym.Env, ours: gym.Env, actions: list, seed0: int) -> dict:
    """Seeded reset, then steps; a seeded reset after every episode end. Compares every output."""
    seed = seed0
    assert_same(ref.reset(seed=seed), ours.reset(seed=seed), "reset")
    stats = {"ends": 0, "terminated": 0, "max_len": 0}
    for i, a in enumerate(actions):
        out_ref = ref.step(_copy_action(a))
        out = ours.step(_copy_action(a))
        assert_same(out_ref, out, f"step {i}")
        if "episode" in out[4]:
            stats["max_len"] = max(stats["max_len"], out[4]["episode"]["episode_len"])
        if out[2] or out[3]:
            stats["ends"] += 1
            stats["terminated"] += out[2]
            seed += 1
            assert_same(ref.reset(seed=seed), ours.reset(seed=seed), f"reset after step {i}")
    return stats


FLAGS = [(False, False), (True, False), (False, True), (True, True)]
# task, obs_mode, max_episode_steps, steps per rollout
CPU_CASES = [
    ("PickCube-v1", "state", 10, 24),
    ("PickCube-v1", "state_dict", 10, 24),
    pytest.param("PickCube-v1", "rgb", 3, 5, marks=pytest.mark.pictures),
    ("MS-CartpoleBalance-v1", "state", 20, 40),
    ("MS-CartpoleBalance-v1", "state_dict", 20, 40),
    ("TwoRobotPickCube-v1", "state", 10, 14),
    ("TwoRobotPickCube-v1", "state_dict", 10, 14),
    ("DrawTriangle-v1", "state", 7, 10),  # bool rewards: ManiSkill's int64 return
    ("RotateValveLevel0-v1", "state", 7, 10),  # float64 rewards
]


# ----------------------------------------------------------------------------- CPUGymWrapper
@pytest.mark.parametrize("ignore_terminations,record_metrics", FLAGS)
@pytest.mark.parametrize("task,obs_mode,max_steps,n_steps", CPU_CASES, ids=lambda x: str(x))
def test_cpu_gym_wrapper_equivalence(env_pair, task, obs_mode, max_steps, n_steps, ignore_terminations, record_metrics):
    env_ref, env_ours = env_pair(task, obs_mode, max_steps)
    ref = MSCPUGymWrapper(env_ref, ignore_terminations=ignore_terminations, record_metrics=record_metrics)
    ours = CPUGymWrapper(env_ours, ignore_terminations=ignore_terminations, record_metrics=record_metrics)
    assert ours.observation_space == ref.observation_space
    assert ours.action_space == ref.action_space
    assert (ours.ignore_terminations, ours.record_metrics) == (ignore_terminations, record_metrics)
    stats = run_cpu_gym_lockstep(ref, ours, _actions(ours, n_steps, seed=n_steps), seed0=7)
    if record_metrics:  # the metrics come from the shared core, not a second copy
        assert isinstance(ours._stats, EpisodeStats)
    assert stats["ends"] >= 1  # episodes cross their end (truncation, or Cartpole's fail)
    if task.startswith("MS-Cartpole") and not ignore_terminations:
        assert stats["terminated"] >= 1  # early termination by `fail`


def test_cpu_gym_wrapper_long_episode_return(env_pair):
    """Beyond numpy's pairwise block (128): np.sum of the rewards, bit for bit."""
    env_ref, env_ours = env_pair("PickCube-v1", "state", 140)
    ref = MSCPUGymWrapper(env_ref, ignore_terminations=True, record_metrics=True)
    ours = CPUGymWrapper(env_ours, ignore_terminations=True, record_metrics=True)
    stats = run_cpu_gym_lockstep(ref, ours, _actions(ours, 141, seed=3), seed0=11)
    assert stats["max_len"] == 140 and stats["ends"] == 1


@pytest.mark.pictures
def test_cpu_gym_wrapper_render(env_pair):
    env_ref, env_ours = env_pair("PickCube-v1", "rgb", 3)
    ref, ours = MSCPUGymWrapper(env_ref), CPUGymWrapper(env_ours)
    assert_same(ref.reset(seed=5), ours.reset(seed=5))
    try:
        for mode in ("sensors", "rgb_array", "all"):
            env_ref.unwrapped.render_mode = env_ours.unwrapped.render_mode = mode
            frame = ours.render()
            assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3
            assert_same(ref.render(), frame, mode)
        # no render mode: the env's own error, as with ManiSkill's wrapper
        env_ref.unwrapped.render_mode = env_ours.unwrapped.render_mode = None
        for wrapper in (ref, ours):
            with pytest.raises(RuntimeError, match="render_mode is not set"):
                wrapper.render()
    finally:
        env_ref.unwrapped.render_mode = env_ours.unwrapped.render_mode = None


def test_cpu_gym_wrapper_is_a_maniskill_cpu_gym_wrapper(env_pair, tmp_path):
    """isinstance checks in ManiSkill (RecordEpisode's CPU handling) see ours as a CPUGymWrapper."""
    env = CPUGymWrapper(env_pair("PickCube-v1", "state", 10)[1])
    assert isinstance(env, gym.Wrapper) and isinstance(env, MSCPUGymWrapper)
    rec = RecordEpisode(env, output_dir=str(tmp_path), save_video=False, save_trajectory=False)
    assert rec.cpu_wrapped_env
    assert env.base_env is env.unwrapped


@pytest.mark.parametrize(
    "x",
    [
        torch.zeros(1, 3),
        torch.zeros(1, 1),
        torch.tensor([3], dtype=torch.int32),
        torch.tensor([True]),
        torch.tensor(2.5),
        torch.zeros(2, 3),
        np.zeros((1,), np.float64),
        np.zeros((1, 1, 2), np.uint8),
        np.zeros((0,)),
        np.float32(1.5),
        np.bool_(True),
        np.array(4),
        [1.0],
        [np.zeros(1), np.zeros(1)],
        (1, 2),
        None,
        "abc",
        True,
        3,
        1.25,
        {"a": {"b": torch.ones(1, 2)}, "c": [torch.tensor(1)]},
    ],
    ids=lambda x: type(x).__name__,
)
def test_np_unbatch_matches_maniskill(x):
    from mani_skill.utils.common import unbatch

    assert_same(unbatch(to_numpy(x)), np_unbatch(x))


# ----------------------------------------------------------------------------- ActionRepeatWrapper
AR_CASES = [
    ("PickCube-v1", "state", 10, 9),
    ("PickCube-v1", "state_dict", 10, 6),
    ("MS-CartpoleBalance-v1", "state", 20, 16),
    ("TwoRobotPickCube-v1", "state_dict", 10, 6),
    ("DrawTriangle-v1", "state", 7, 6),  # bool rewards
    ("RotateValveLevel0-v1", "state", 7, 6),  # float64 rewards
]


@pytest.mark.parametrize("repeat", [1, 2, 3])
@pytest.mark.parametrize("task,obs_mode,max_steps,n_steps", AR_CASES, ids=lambda x: str(x))
def test_action_repeat_equivalence(env_pair, task, obs_mode, max_steps, n_steps, repeat):
    env_ref, env_ours = env_pair(task, obs_mode, max_steps)
    ref = MSActionRepeatWrapper(env_ref, repeat)
    ours = ActionRepeatWrapper(env_ours, repeat)
    assert (ours.observation_space, ours.action_space) == (ref.observation_space, ref.action_space)
    assert (ours.repeat, ours.num_envs) == (repeat, 1)
    seed = 21
    assert_same(ref.reset(seed=seed), ours.reset(seed=seed), "reset")
    acts = random_actions(env_ours.unwrapped.single_action_space, n_steps, seed=repeat)
    mid_repeat_ends = 0
    for i, a in enumerate(acts):
        out_ref = ref.step(_copy_action(a))
        out = ours.step(_copy_action(a))
        assert_same(out_ref, out, f"step {i}")
        if (out[2] | out[3]).any():
            mid_repeat_ends += int(out[4]["elapsed_steps"].item()) % repeat != 0
            seed += 1
            assert_same(ref.reset(seed=seed), ours.reset(seed=seed), f"reset after {i}")
    if repeat == 3:  # max_episode_steps % 3 != 0: some episode ends inside a repeat
        assert mid_repeat_ends >= 1


class _FakeBatchedStep:
    """A batched step (3 envs, as on the GPU sim) ending env 0 by termination at step 2, env 1 by
    truncation at step 4, env 2 never; dict obs, non-trivial float rewards, a python info value."""

    def __init__(self) -> None:
        self.t = 0

    def __call__(self, action):
        self.t += 1
        t = torch.full((3,), self.t, dtype=torch.int32)
        ids = torch.arange(3)
        obs = {
            "agent": {"x": (t[:, None] + ids[:, None] * 0.5 + torch.tensor([[0.1, 0.2]])).float()},
            "img": (t * 10 + ids).to(torch.uint8)[:, None].repeat(1, 4),
        }
        reward = (t.float() * 0.1 + ids / 7).float()
        terminated = torch.tensor([self.t >= 2, False, False])
        truncated = torch.tensor([False, self.t >= 4, False])
        info = {"elapsed_steps": t, "success": t % 2 == 0, "python_value": self.t}
        return obs, reward, terminated, truncated, info


@nightly_action_repeat_bug
@pytest.mark.parametrize("repeat", [2, 3, 5])
def test_action_repeat_batched_partial_done(env_pair, repeat):
    """Several envs ending at different inner steps (GPU-sim-like batch): same masked merge as ManiSkill."""
    env = env_pair("PickCube-v1", "state", 10)[1]
    fake = _FakeBatchedStep()
    env.step = fake  # the outer gym wrapper's step, on this instance only
    try:
        outs = []
        for cls in (MSActionRepeatWrapper, ActionRepeatWrapper):
            fake.t = 0
            wrapper = cls(env, repeat)
            outs.append([wrapper.step(None) for _ in range(3)])
        assert_same(outs[0], outs[1])
        first = outs[1][0]
        assert first[2].tolist() == [True, False, False] and first[3].tolist() == [False, repeat >= 4, False]
        assert first[4]["elapsed_steps"].tolist() == [2, min(repeat, 4), repeat]  # each env's last real step
    finally:
        del env.step


def test_action_repeat_under_cpu_gym_wrapper(env_pair):
    """The documented stack CPUGymWrapper(ActionRepeatWrapper(env)), with early `fail` ends."""
    env_ref, env_ours = env_pair("MS-CartpoleBalance-v1", "state", 20)
    ref = MSCPUGymWrapper(MSActionRepeatWrapper(env_ref, 3), record_metrics=True)
    ours = CPUGymWrapper(ActionRepeatWrapper(env_ours, 3), record_metrics=True)
    stats = run_cpu_gym_lockstep(ref, ours, _actions(ours, 16, seed=5), seed0=3)
    assert stats["terminated"] >= 1


def test_action_repeat_does_not_modify_first_step_in_place(env_pair):
    env_ref, env_ours = env_pair("PickCube-v1", "state", 10)
    ref, env = MSActionRepeatWrapper(env_ref, 2), ActionRepeatWrapper(env_ours, 2)
    assert_same(ref.reset(seed=0), env.reset(seed=0))  # both envs of the pair see the same calls
    seen = []
    inner_step = env.env.step

    def spy(action):
        out = inner_step(action)
        seen.append((out[0].clone(), out[0]))
        return out

    env.env.step = spy
    try:
        action = torch.zeros(env.action_space.shape)
        out_ref, out = ref.step(action.clone()), env.step(action.clone())
    finally:
        del env.env.step
    assert_same(out_ref, out)
    (first_copy, first), (last_copy, _) = seen
    assert torch.equal(first, first_copy)  # untouched
    assert torch.equal(out[0], last_copy) and out[0] is not first


# ----------------------------------------------------------------------------- vector envs
VEC_MAX_STEPS = 6


def _thunks(wrapper_cls, n: int = 2) -> list:
    return [
        lambda: wrapper_cls(
            gym.make("PickCube-v1", num_envs=1, max_episode_steps=VEC_MAX_STEPS),
            ignore_terminations=True,
            record_metrics=True,
        )
        for _ in range(n)
    ]


def _compare_vector(venvs: list, episodes: int, autoreset_steps: int = 0) -> None:
    """Seeded resets (a list of seeds), whole episodes up to their truncation, then optionally
    gymnasium's autoreset. An autoreset is an unseeded ManiSkill reset, drawn from the process's
    torch RNG: only comparable in one process, with that RNG set alike before each vector step."""
    rng = np.random.default_rng(0)
    n, shape = venvs[0].num_envs, venvs[0].single_action_space.shape
    for ep in range(episodes):
        outs = [v.reset(seed=[10 + n * ep + i for i in range(n)]) for v in venvs]
        assert_same(outs[0], outs[1], f"reset {ep}")
        for t in range(VEC_MAX_STEPS):
            a = rng.uniform(-1, 1, (n, *shape)).astype(np.float32)
            outs = [v.step(a.copy()) for v in venvs]
            assert_same(outs[0], outs[1], f"episode {ep} step {t}")
        assert outs[1][3].all() and outs[1][4]["episode"]["episode_len"].tolist() == [VEC_MAX_STEPS] * n
    for t in range(autoreset_steps):
        a = rng.uniform(-1, 1, (n, *shape)).astype(np.float32)
        outs = []
        for v in venvs:
            torch.manual_seed(t)
            outs.append(v.step(a.copy()))
        assert_same(outs[0], outs[1], f"after autoreset, step {t}")
        if t == 0:  # the autoreset step itself
            assert outs[1][1].tolist() == [0.0] * n and "episode" not in outs[1][4]


def test_sync_vector_env():
    venvs = [gym.vector.SyncVectorEnv(_thunks(cls)) for cls in (MSCPUGymWrapper, CPUGymWrapper)]
    try:
        assert venvs[1].single_observation_space == venvs[0].single_observation_space
        assert venvs[1].single_action_space == venvs[0].single_action_space
        _compare_vector(venvs, episodes=2, autoreset_steps=3)
    finally:
        for v in venvs:
            v.close()


@pytest.mark.slow
def test_async_vector_env_forkserver():
    """Thunks pickle and run in forkserver workers (the default fork context hangs with SAPIEN).
    The workers import the wrapper's module when unpickling the thunk, which registers the tasks.
    One worker per vector env (each costs seconds of imports): what crosses the pipes is checked;
    gymnasium merges several sub-envs' outputs with the same code in the sync test above."""
    venvs = [
        gym.vector.AsyncVectorEnv(_thunks(cls, n=1), context="forkserver") for cls in (MSCPUGymWrapper, CPUGymWrapper)
    ]
    try:
        _compare_vector(venvs, episodes=2)
    finally:
        for v in venvs:
            v.close()


# ----------------------------------------------------------------------------- errors
def test_errors_non_maniskill_env():
    class Plain(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (2,))
        action_space = gym.spaces.Box(-1, 1, (1,))

    for cls, args in ((CPUGymWrapper, ()), (ActionRepeatWrapper, (2,))):
        with pytest.raises(TypeError, match="ManiSkill 3 envs only.*gym.make"):
            cls(Plain(), *args)
        with pytest.raises(TypeError, match="ManiSkill 3 envs only"):
            cls("PickCube-v1", *args)


def test_errors_num_envs_and_gpu_sim(env_pair, monkeypatch):
    env = env_pair("PickCube-v1", "state", 10)[1]
    monkeypatch.setattr(env.unwrapped, "num_envs", 4)
    with pytest.raises(ValueError, match="num_envs=1, got num_envs=4.*SyncVectorEnv"):
        CPUGymWrapper(env)
    monkeypatch.undo()
    monkeypatch.setattr(type(env.unwrapped), "gpu_sim_enabled", property(lambda self: True))
    with pytest.raises(ValueError, match="CPU sim.*sim_backend='physx_cpu'"):
        CPUGymWrapper(env)
    monkeypatch.undo()
    CPUGymWrapper(env)


def test_errors_repeat(env_pair):
    env = env_pair("PickCube-v1", "state", 10)[1]
    for bad in (0, -1):
        with pytest.raises(ValueError, match="repeat must be >= 1"):
            ActionRepeatWrapper(env, bad)
    for bad in (2.0, "2", None, True):
        with pytest.raises(TypeError, match="repeat must be an int"):
            ActionRepeatWrapper(env, bad)
    assert ActionRepeatWrapper(env, np.int64(2)).repeat == 2
    with pytest.raises(TypeError, match="Apply ActionRepeatWrapper first"):
        ActionRepeatWrapper(CPUGymWrapper(env), 2)


# ----------------------------------------------------------------------------- docs
def test_docstring_examples():
    for module in (gymnasium_module, action_repeat_module):
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
        assert result.attempted > 0 and result.failed == 0, module.__name__
