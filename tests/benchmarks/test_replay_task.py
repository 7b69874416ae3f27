"""The many-core emulator's task (``benchmarks/replay_task.py``): a seeded replayed episode is the real
PickCube-v1 episode it was recorded from, bit for bit; its specs are the real task's; it builds no
SAPIEN scene; its steps sleep the recorded times scaled to the target (sleeps counted, not timed)."""

from __future__ import annotations

import types

import gymnasium as gym
import numpy as np
import pytest
import torch

replay = pytest.importorskip("benchmarks.replay_task")

REAL = "PickCube-v1"
KWARGS = {"obs_mode": "state", "max_episode_steps": 50, "sim_backend": "physx_cpu"}


@pytest.fixture
def no_sleep(monkeypatch):
    """The replay's clock stopped and its sleeps recorded (seconds each), not slept."""
    slept: list[float] = []
    fake = types.SimpleNamespace(perf_counter=lambda: 0.0, sleep=slept.append)
    monkeypatch.setattr(replay, "time", fake)
    return slept


def _cpu(line: str) -> str:
    return line.split(",")[0].strip()


def _recorded_here() -> bool:
    """Whether this machine's CPU is the one the recording was made on: PhysX's floats differ in their
    last bits between CPUs (an AMD EPYC here against the recording's Intel Xeon, 2026-12-02)."""
    from benchmarks.machine import _cpu_model

    return _cpu_model() == _cpu(replay.load_recording()["meta"]["machine"])


def _same(a, b, where: str, exact: bool = True) -> None:
    """Equal types, dtypes and shapes; values bit for bit, or (``exact=False``) floats within float32 rounding."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for k in a:
            _same(a[k], b[k], f"{where}.{k}", exact)
        return
    if isinstance(a, tuple):
        assert isinstance(b, tuple) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]", exact)
        return
    assert type(a) is type(b), (where, type(a), type(b))
    x, y = np.asarray(a), np.asarray(b)
    assert x.dtype == y.dtype and x.shape == y.shape, (where, x.dtype, y.dtype, x.shape, y.shape)
    if exact or not np.issubdtype(x.dtype, np.floating):
        assert np.array_equal(x, y), where
    else:
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6, err_msg=where)


@pytest.fixture(scope="module")
def real_and_replay():
    """The real task and its replay, made as ManiSkill's documented gym usage makes them (every
    reset of a test seeded: a seeded episode does not depend on what ran before it)."""
    envs = [gym.make(env_id, num_envs=1, **KWARGS) for env_id in (REAL, replay.REPLAY_ID)]
    yield envs
    for env in envs:
        env.close()


@pytest.mark.parametrize("seed", [0, 7, 19])
def test_seeded_episode_is_the_real_one(seed, real_and_replay, no_sleep):
    """Through the gym shim, at repeat 1 and 2: the same outputs, types and dtypes, bit for bit on the
    recording's CPU (elsewhere the real task's floats differ in their last bits: within float32 rounding)."""
    from maniskill_torchrl.wrappers import ActionRepeatWrapper, CPUGymWrapper

    rec = replay.load_recording()
    exact = _recorded_here()
    for repeat in (1, 2):
        real, rep = (CPUGymWrapper(ActionRepeatWrapper(e, repeat) if repeat > 1 else e) for e in real_and_replay)
        _same(real.reset(seed=seed), rep.reset(seed=seed), "reset", exact)
        # the recorded actions are held for 2 steps: at repeat 2, one of them per outer step
        for t, action in enumerate(rec["actions"][seed][::repeat]):
            _same(real.step(action), rep.step(action), f"repeat {repeat} step {t}", exact)


def test_specs_are_the_real_tasks():
    from maniskill_torchrl import ManiSkillEnv

    real = ManiSkillEnv(REAL, obs_mode="state")
    rep = ManiSkillEnv(replay.REPLAY_ID, obs_mode="state")
    for name in ("observation_spec", "action_spec", "reward_spec", "full_done_spec", "state_spec"):
        assert getattr(rep, name) == getattr(real, name), name
    a, b = real.rand_step(real.reset(seed=3)), rep.rand_step(rep.reset(seed=3))
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert (a[key].dtype, a[key].shape) == (b[key].dtype, b[key].shape), key
    torch.testing.assert_close(a["observation"], b["observation"], rtol=0, atol=0)  # the reset
    real.close()
    rep.close()


def _leaves(spec) -> dict:
    """Each leaf's dtype and shape past the batch dimension."""
    if not hasattr(spec, "items"):
        return {(): (spec.dtype, spec.shape[1:])}
    return {k: (v.dtype, v.shape[1:]) for k, v in spec.items(True, True)}


def test_the_library_builds_it_in_workers():
    """The lockstep CPU engine and the asynchronous pool make it in their forkserver workers (by its
    ``module:EnvId`` name), with the task's specs; seeded, the same episodes as in process."""
    from maniskill_torchrl import ManiSkillAsyncEnvPool, ManiSkillEnv

    one = ManiSkillEnv(replay.REPLAY_ID, obs_mode="state")
    two = ManiSkillEnv(replay.REPLAY_ID, num_envs=2, obs_mode="state", step_ms=0.1)
    try:
        for name in ("observation_spec", "action_spec", "reward_spec", "full_done_spec"):
            assert _leaves(getattr(two, name)) == _leaves(getattr(one, name)), name
        obs = two.reset(seed=5)["observation"]
        rec = replay.load_recording()
        assert torch.equal(obs, torch.from_numpy(rec["reset_obs"][5:7]))
        td = two.rand_step(two.reset(seed=5))
        assert torch.equal(td["next", "observation"], torch.from_numpy(rec["obs"][5:7, 0]))
    finally:
        one.close()
        two.close()
    pool = ManiSkillAsyncEnvPool(replay.REPLAY_ID, 2, repeat=2, obs_mode="state", step_ms=0.1)
    try:
        assert _leaves(pool.observation_spec) == _leaves(one.observation_spec)
        assert pool.reset()["observation"].shape == (2, 42)
    finally:
        pool.close()


def test_gym_async_vector_env_builds_it():
    """gymnasium's ``AsyncVectorEnv(context="forkserver")`` of ``CPUGymWrapper(ActionRepeatWrapper)``:
    the workers register the task by importing its module (``gym.make``'s ``module:EnvId`` rule).
    After each auto-reset (unseeded, in workers forked with one torch RNG state) every worker replays
    its own episode, the one after its last: the emulator's gym waits on distinct episodes, as the
    library's engines do (issue 59: all replayed one)."""
    from maniskill_torchrl.wrappers import ActionRepeatWrapper, CPUGymWrapper

    # a lambda: cloudpickle sends it by value (this test module is not importable in the workers)
    thunk = lambda: CPUGymWrapper(  # noqa: E731
        ActionRepeatWrapper(gym.make(replay.REPLAY_ID, num_envs=1, step_ms=0.1, **KWARGS), 2)
    )
    envs = gym.vector.AsyncVectorEnv([thunk] * 3, context="forkserver")
    try:
        obs, _ = envs.reset(seed=11)
        rec = replay.load_recording()
        np.testing.assert_array_equal(obs, rec["reset_obs"][11:14])
        obs, reward, *_ = envs.step(envs.action_space.sample())
        np.testing.assert_array_equal(obs, rec["obs"][11:14, 1])
        np.testing.assert_array_equal(reward, rec["reward"][11:14, 0] + rec["reward"][11:14, 1])
        for episode in (1, 2):  # 25 outer steps of 2 (the time limit, 50), then gym's autoreset step
            for _ in range(25 if episode == 1 else 26):
                envs.step(envs.action_space.sample())
            assert list(envs.call("episode")) == [(11 + i + episode) % 20 for i in range(3)], episode
    finally:
        envs.close()


def test_no_sapien_scene(monkeypatch):
    from mani_skill.envs.sapien_env import BaseEnv
    from mani_skill.envs.scene import ManiSkillScene

    def refuse(*args, **kwargs):
        raise AssertionError("the replay built a SAPIEN scene")

    for cls, name in ((BaseEnv, "__init__"), (BaseEnv, "_reconfigure"), (BaseEnv, "_setup_scene")):
        monkeypatch.setattr(cls, name, refuse)
    monkeypatch.setattr(ManiSkillScene, "__init__", refuse)
    env = gym.make(replay.REPLAY_ID, num_envs=1, step_ms=0.01, **KWARGS)
    env.reset(seed=1)
    env.step(env.action_space.sample())
    base = env.unwrapped
    assert isinstance(base, BaseEnv) and base.scene is None and getattr(base, "agent", None) is None
    assert not base.gpu_sim_enabled and base.num_envs == 1 and base.device == torch.device("cpu")


def _steps(env, k: int, seed: int | None = None) -> None:
    """A reset with ``seed`` (if given) and ``k`` steps, under inference mode (as the recording's and the
    library's workers' steps)."""
    with torch.inference_mode():
        if seed is not None:
            env.reset(seed=seed)
        for _ in range(k):
            env.step(env.action_space.sample())


def test_sleeps_the_scaled_recorded_times(no_sleep, monkeypatch):
    rec = replay.load_recording()
    steps, resets = rec["step_s"], rec["reset_s"]
    # spread 0: every step and every reset lasts the recorded mean, scaled so that an episode's 50 steps
    # and its reset last 50 x the target
    env = gym.make(replay.REPLAY_ID, num_envs=1, step_ms=3.0, spread=0.0, **KWARGS)
    _steps(env, 50, seed=2)
    scale = env.unwrapped.time_scale
    np.testing.assert_allclose(no_sleep[0], resets.mean() * scale)
    np.testing.assert_allclose(no_sleep[1:], steps.mean() * scale)
    assert sum(no_sleep) == pytest.approx(50 * 3e-3)
    # spread 1 (as recorded): step k of episode e sleeps one of the passes' times of (e, k), scaled;
    # the target from the environment (read where the env is made), a name of TARGETS
    monkeypatch.setenv(replay.STEP_MS_ENV, "h200")
    no_sleep.clear()
    env = gym.make(replay.REPLAY_ID, num_envs=1, timing_seed=0, **KWARGS)
    scale = replay.TARGETS["h200"] / 1e3 / (steps.mean() + resets.mean() / 50)
    assert env.unwrapped.time_scale == pytest.approx(scale)
    _steps(env, 50, seed=4)
    assert any(np.isclose(no_sleep[0], resets[:, 4] * scale))
    for k, slept in enumerate(no_sleep[1:]):
        assert np.isclose(slept, steps[:, 4, k] * scale).any(), k
    # a keyword wins over the environment
    env = gym.make(replay.REPLAY_ID, num_envs=1, step_ms="2.5", **KWARGS)
    assert env.unwrapped.time_scale * (steps.mean() + resets.mean() / 50) == pytest.approx(2.5e-3)
    # ManiSkill's ActionRepeatWrapper(2): one outer step, two sleeps
    from maniskill_torchrl.wrappers import ActionRepeatWrapper

    env = gym.make(replay.REPLAY_ID, num_envs=1, step_ms=1.0, spread=0.0, **KWARGS)
    one = steps.mean() * env.unwrapped.time_scale
    wrapped = ActionRepeatWrapper(env, 2)
    wrapped.reset(seed=0)
    no_sleep.clear()
    _steps(wrapped, 1)
    np.testing.assert_allclose(no_sleep, [one, one])
    # a step in grad mode (gymnasium's worker loop) costs what a real sim's costs there: GRAD_FACTOR more
    no_sleep.clear()
    with torch.enable_grad():
        env.step(torch.zeros(1, 8))
    with torch.no_grad():
        env.step(torch.zeros(1, 8))
    np.testing.assert_allclose(no_sleep, [one * replay.GRAD_FACTOR, one])
    # the factor from the environment (what bench_many_cores measures), or a keyword; 1 drops it
    monkeypatch.setenv(replay.GRAD_FACTOR_ENV, "1.5")
    for env, factor in (
        (gym.make(replay.REPLAY_ID, num_envs=1, step_ms=1.0, spread=0.0, **KWARGS), 1.5),
        (gym.make(replay.REPLAY_ID, num_envs=1, step_ms=1.0, spread=0.0, grad_factor=1, **KWARGS), 1.0),
    ):
        env.reset(seed=0)
        no_sleep.clear()
        with torch.enable_grad():
            env.step(torch.zeros(1, 8))
        np.testing.assert_allclose(no_sleep, [one * factor])


def test_each_env_goes_on_from_its_own_offset(no_sleep):
    """An unseeded reset replays the episode after the one the env last played, whatever torch's RNG
    says: envs seeded 18, 19, 20, 21 (gymnasium's ``seed + i``), each reset with one torch RNG state
    (workers forked from one process), replay 4 distinct episodes after every reset."""
    envs = [gym.make(replay.REPLAY_ID, num_envs=1, **KWARGS).unwrapped for _ in range(4)]
    for i, env in enumerate(envs):
        env.reset(seed=18 + i)
    for k in range(1, 23):
        for env in envs:
            torch.manual_seed(0)
            env.reset()
        assert [env.episode for env in envs] == [(18 + i + k) % 20 for i in range(4)], k
    state = torch.get_rng_state()
    envs[0].reset(seed=25)  # a seeded reset: episode 25 % 20, torch's RNG untouched
    assert envs[0].episode == 5 and torch.equal(torch.get_rng_state(), state)
    envs[0].reset()
    assert envs[0].episode == 6 and torch.equal(torch.get_rng_state(), state)


def test_first_unseeded_reset_draws_from_torchs_rng(no_sleep):
    """An env that has played no episode draws its first from torch's global RNG (ManiSkill's
    unseeded reset draws there), then goes on from it."""
    drawn = []
    for _ in range(2):
        env = gym.make(replay.REPLAY_ID, num_envs=1, **KWARGS).unwrapped
        torch.manual_seed(123)
        env.reset()
        env.reset()
        drawn.append((env.episode, torch.get_rng_state()))
    first = int(torch.randint(20, (), generator=torch.Generator().manual_seed(123)))
    assert drawn[0][0] == drawn[1][0] == (first + 1) % 20
    assert torch.equal(drawn[0][1], drawn[1][1])


def test_refuses_what_was_not_recorded():
    for kwargs in ({"obs_mode": "rgb"}, {"control_mode": "pd_ee_delta_pose"}, {"sim_backend": "physx_cuda"}):
        with pytest.raises(ValueError, match="replays PickCube-v1 as recorded"):
            gym.make(replay.REPLAY_ID, num_envs=1, **kwargs)
    with pytest.raises(ValueError, match="step_ms"):
        gym.make(replay.REPLAY_ID, num_envs=1, step_ms="fast")
