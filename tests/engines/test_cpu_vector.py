"""ManiSkillEnv(env_id, num_envs=N) on the CPU sim: one TorchRL env of batch [N] over N workers.

The oracle is N independent raw ManiSkill envs (``gym.make(..., num_envs=1)``) in this
process, every reset seeded as the contract says: after ``set_seed(s)`` sub-env ``i``
starts with ``reset(seed=s + i)``; every later reset event draws ``d`` from
``numpy.random.RandomState(s)`` and the sub-envs it resets restart with ``d + i``.
"""

from __future__ import annotations

import itertools
import os
import signal
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper
from torchrl.collectors import Collector
from torchrl.data import Bounded
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from maniskill_torchrl import (
    ActionRepeat,
    CPUUnbatch,
    CPUVectorEnv,
    EpisodeMetrics,
    ManiSkillEnv,
    ManiSkillWrapper,
)
from support.helpers import ctrl_c_after_a_length, ctrl_c_at_line, make_gym_env, no_hang, random_actions, start

N = 2
CART = dict(obs_mode="state", max_episode_steps=30, sim_backend="cpu")  # random actions fail it after ~20 steps
PICK = dict(obs_mode="state_dict", max_episode_steps=5, sim_backend="cpu")


@pytest.fixture(scope="module", params=[True, False], ids=["in_process", "workers"])
def cartpole(request):
    """Sub-env 0 in this process (the default), or every sub-env in a worker process."""
    env = ManiSkillEnv("MS-CartpoleBalance-v1", num_envs=N, in_process=request.param, **CART)
    yield env
    env.close()


def _closed(env) -> bool:
    """Closed, or its CPUVectorEnv closed (after a worker died)."""
    return env.is_closed or getattr(env._env, "_closed", False) is True


@pytest.fixture(scope="module")
def shared_envs():
    """Batched envs shared by the tests of this module (each costs seconds of worker start-up),
    made on first use. A test that closes one (on purpose: ``test_dead_worker_...``,
    ``test_wrapper_...``) runs after the others that use it; one that finds it closed (another
    order, ``-k``) gets a new one."""
    makers = {
        "pick": lambda: ManiSkillEnv("PickCube-v1", num_envs=N, **PICK),
        # made by hand, as ManiSkillEnv(num_envs=3) makes it; an odd batch, flat observations
        "pick_vec": lambda: ManiSkillWrapper(CPUVectorEnv("PickCube-v1", 3, obs_mode="state", max_episode_steps=4)),
    }
    made: dict = {}

    def get(name: str):
        if name not in made or _closed(made[name]):
            made[name] = makers[name]()
        return made[name]

    yield get
    for env in made.values():
        env.close()


@pytest.fixture
def pick(shared_envs):
    """``ManiSkillEnv("PickCube-v1", num_envs=2)``, state_dict observations, 5-step episodes;
    killed by the last test that uses it, ``test_dead_worker_raises_instead_of_hanging``."""
    return shared_envs("pick")


@pytest.fixture
def pick_vec(shared_envs):
    """``ManiSkillWrapper(CPUVectorEnv("PickCube-v1", 3))``, state observations, 4-step episodes;
    closed by the last test that uses it, ``test_wrapper_accepts_a_cpu_vector_env``."""
    return shared_envs("pick_vec")


@pytest.fixture(scope="module", autouse=True)
def no_guard_script(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    """The script of ``test_script_without_main_guard_gets_a_clear_error``, started with the
    module's first test when that test is selected: alone it runs for 15-25 s (two processes
    importing torch, TorchRL and ManiSkill one after the other), mostly on one core, while the
    other tests of the module leave that core idle for seconds at a time. Killed at the end."""
    name = "test_script_without_main_guard_gets_a_clear_error"
    if not any(item.name == name and item.module is request.module for item in request.session.items):
        yield None
        return
    folder = tmp_path_factory.mktemp("no_guard")
    script = folder / "no_guard.py"
    script.write_text(
        'from maniskill_torchrl import ManiSkillEnv\nManiSkillEnv("PushCube-v1", num_envs=2, sim_backend="cpu")\n'
    )
    handle = start([sys.executable, str(script)], cwd=folder)
    yield handle
    handle.kill()


def _leaves(x, prefix=()):
    if isinstance(x, dict):
        for k, v in x.items():
            yield from _leaves(v, prefix + (k,))
    else:
        yield prefix, x


def _assert_sub_env(td, i, obs, info, what):
    """Row ``i`` of ``td`` holds the raw env's ``obs`` and tensor infos, bit for bit."""
    obs = obs if isinstance(obs, dict) else {"observation": obs}
    n = 0
    for key, want in list(_leaves(obs)) + [((k,), v) for k, v in info.items() if isinstance(v, torch.Tensor)]:
        got = td.get(key if len(key) > 1 else key[0])[i]
        assert got.dtype == want.dtype, (what, key, got.dtype, want.dtype)
        assert torch.equal(got, want[0]), (what, key, got, want[0])
        n += 1
    assert n >= 3


def _clone(x):
    if isinstance(x, dict):
        return {k: _clone(v) for k, v in x.items()}
    return x.clone() if isinstance(x, torch.Tensor) else x


def test_specs_are_the_single_env_specs_batched(pick):
    """Same keys, spec classes, dtypes and bounds as batch [1] (the GPU sim's code path), batch [N]."""
    single = ManiSkillEnv("PickCube-v1", **PICK)
    try:
        for name in ("full_observation_spec", "full_action_spec", "full_reward_spec", "full_done_spec"):
            want, got = getattr(single, name), getattr(pick, name)
            assert got.shape == torch.Size([N])
            assert set(got.keys(True, True)) == set(want.keys(True, True)), name
            for key in want.keys(True, True):
                w, g = want[key], got[key]
                assert type(g) is type(w) and g.dtype == w.dtype, (name, key)
                assert g.shape == torch.Size([N]) + w.shape[1:], (name, key)
                if isinstance(w, Bounded):
                    assert torch.equal(g.space.low[0], w.space.low[0]), key
    finally:
        single.close()
    assert pick.batch_size == torch.Size([N]) and not pick.gpu_sim_enabled
    assert ("agent", "qpos") in pick.observation_spec.keys(True, True)


def test_without_a_seed_every_sub_env_plays_its_own_episode(pick_vec):
    """First to use the env, before any seed: its worker processes fork from one process, and
    ManiSkill's unseeded resets would replay one episode in each (issue 51's finding 2, lockstep)."""
    obs = pick_vec.reset()["observation"]
    assert all(not torch.equal(obs[i], obs[j]) for i in range(3) for j in range(i)), "two sub-envs alike"


def test_check_env_specs(pick_vec):
    check_env_specs(pick_vec, seed=0)


def test_ctrl_c_inside_a_lockstep_read_comes_after_the_read(cartpole, monkeypatch):
    """A Ctrl-C inside the read of a worker's answer to a lockstep step (between its length and its body)
    comes once that answer is read whole. Before the fix it came mid-read, and the read of the answers
    owed took the body left in the pipe for a length: a hang."""
    engine = cartpole._env
    td = cartpole.reset().set("action", torch.zeros(N, 1))
    with ctrl_c_after_a_length(engine._pool.pipes[0], monkeypatch) as reads:
        with pytest.raises(KeyboardInterrupt):
            cartpole.step(td)
        out = cartpole.step(td)  # in step: the next step reads its own answers
    assert reads[:2] == [4, 1], reads
    assert out["next", "observation"].shape[0] == N
    assert not engine._pool.owed.any() and not any(pipe.poll(0) for pipe in engine._pool.pipes)


def test_ctrl_c_at_any_line_of_a_lockstep_step_leaves_the_engine_in_step(cartpole):
    """A Ctrl-C at each line, in turn, of a lockstep step (the engine's files and ``multiprocessing``'s pipe
    reads): a ``KeyboardInterrupt`` every time, at once (no wait for a worker is held), and the next step
    reads its own answers: those the cut step left owed are read first, nothing is left in a pipe and no
    read hangs. Before the fix, a Ctrl-C between an answer's length and its body left the body in the pipe
    and the next read took it for a length: a hang, cut here by SIGALRM; one in the sends, or between the
    sends and the wait, left answers the next step took for its own."""
    engine = cartpole._env
    action = torch.zeros(N, 1)
    engine.reset(seed=0)
    with ctrl_c_at_line(0) as counted:
        engine.step(action)
    lines, interrupted = counted[0], 0
    for line in range(1, lines + 1):
        if line % 20 == 0:
            engine.reset(seed=line)
        with no_hang(10.0):
            with ctrl_c_at_line(line) as ran:
                try:
                    engine.step(action)
                except KeyboardInterrupt:
                    interrupted += 1
                else:  # a step's lines vary a little (what each select finds): this one ended before the line
                    assert ran[0] < line, f"a Ctrl-C at line {line} of {lines} was lost"
                    lines = min(lines, ran[0])
            engine.step(action)
        left = [i for i, pipe in enumerate(engine._pool.pipes) if pipe.poll(0)]
        assert not left and not engine._pool.owed.any(), (
            f"a Ctrl-C at line {line} of {lines} left answers in the pipes of workers {left}"
        )
    assert interrupted >= lines


def test_held_ctrl_c_comes_when_the_block_ends():
    """``engines/_interrupts.HELD``: a SIGINT inside the block is the handler's at its end (the outermost
    block's), once; a second one at once; the handler that was there is back after; nothing changes for
    ``SIG_IGN`` or in another thread."""
    import threading

    from maniskill_torchrl.engines._interrupts import HELD

    got: list[int] = []
    old = signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
    try:
        mine = signal.getsignal(signal.SIGINT)
        with HELD:
            with HELD:
                signal.raise_signal(signal.SIGINT)
            assert got == []  # the inner block's end is not the hold's
        assert got == [signal.SIGINT] and signal.getsignal(signal.SIGINT) is mine
        signal.signal(signal.SIGINT, signal.default_int_handler)
        after = []
        with pytest.raises(KeyboardInterrupt):
            with HELD:
                signal.raise_signal(signal.SIGINT)
                after.append("held")
                signal.raise_signal(signal.SIGINT)  # a second Ctrl-C: at once
                after.append("not reached")
        assert after == ["held"] and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        with pytest.raises(KeyboardInterrupt):
            with HELD:  # held again
                signal.raise_signal(signal.SIGINT)
                after.append("held again")
        assert after == ["held", "held again"]
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with HELD:
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        signal.signal(signal.SIGINT, signal.default_int_handler)
        seen = []

        def elsewhere():
            with HELD:
                seen.append(signal.getsignal(signal.SIGINT))

        thread = threading.Thread(target=elsewhere)
        thread.start()
        thread.join()
        assert seen == [signal.default_int_handler]
    finally:
        signal.signal(signal.SIGINT, old)


def test_each_sub_env_equals_a_raw_env(cartpole):
    """Auto-resets across episodes that end at different steps (partial resets) and together."""
    raws = [make_gym_env("MS-CartpoleBalance-v1", **CART) for _ in range(N)]
    seed, steps = 7, 70
    rng = np.random.RandomState(seed)
    actions = random_actions(gym.spaces.Box(-1, 1, (N, 1)), steps, seed=3)
    try:
        cartpole.set_seed(seed)
        td = cartpole.reset()
        for i, raw in enumerate(raws):
            obs, info = raw.reset(seed=seed + i)
            _assert_sub_env(td, i, obs, info, "first reset")
        partial = 0
        for t, action in enumerate(actions):
            td, td_next = cartpole.step_and_maybe_reset(td.set("action", action))
            dones = []
            for i, raw in enumerate(raws):
                obs, reward, term, trunc, info = raw.step(action[i : i + 1])
                _assert_sub_env(td["next"], i, obs, info, f"step {t}")
                assert torch.equal(td["next", "reward"][i], reward), t
                assert bool(td["next", "terminated"][i]) == bool(term) and bool(td["next", "truncated"][i]) == bool(
                    trunc
                )
                dones.append(bool(term | trunc))
            if any(dones):
                partial += not all(dones)
                d = int(rng.randint(2**31))
                for i, raw in enumerate(raws):
                    if dones[i]:
                        obs, info = raw.reset(seed=d + i)
                        _assert_sub_env(td_next, i, obs, info, f"reset after step {t}")
            td = td_next
        assert partial >= 2, "sub-envs should end at different steps"
    finally:
        for raw in raws:
            raw.close()


def test_reset_mask_resets_only_masked(pick):
    raws = [make_gym_env("PickCube-v1", **PICK) for _ in range(N)]
    actions = random_actions(gym.spaces.Box(-1, 1, (N, 8)), 4, seed=1)
    try:
        td = pick.reset(seed=10)
        for i, raw in enumerate(raws):
            raw.reset(seed=10 + i)
        for a in actions[:2]:
            td = step_mdp(pick.step(td.set("action", a)))
            for i, raw in enumerate(raws):
                raw.step(a[i : i + 1])
        before = td.clone()
        td = pick.reset(td.set("_reset", torch.tensor([True, False])), seed=50)
        obs, info = raws[0].reset(seed=50)
        _assert_sub_env(td, 0, obs, info, "reset sub-env")
        assert int(td["elapsed_steps"][0]) == 0 and int(td["elapsed_steps"][1]) == 2
        assert (td[1] == before[1].exclude("_reset")).all(), "the unmasked sub-env must keep its data"
        for t, a in enumerate(actions[2:]):
            td = pick.step(td.set("action", a))
            for i, raw in enumerate(raws):
                obs, _, _, _, info = raw.step(a[i : i + 1])
                _assert_sub_env(td["next"], i, obs, info, f"after partial reset, step {t}")
            td = step_mdp(td)
    finally:
        for raw in raws:
            raw.close()


def test_action_repeat_equals_maniskill_wrapper(cartpole):
    """ActionRepeat over the batched CPU env: each sub-env is ManiSkill's ActionRepeatWrapper.

    The repeat runs inside each worker (tests/test_worker_repeat.py): a sub-env that ends
    mid-repeat stops there; each is compared up to its own end."""
    repeat = 4
    env = TransformedEnv(cartpole, ActionRepeat(repeat))
    oracles = [ActionRepeatWrapper(make_gym_env("MS-CartpoleBalance-v1", **CART), repeat) for _ in range(N)]
    actions = random_actions(gym.spaces.Box(-1, 1, (N, 1)), 20, seed=5)
    try:
        td = env.reset(seed=21)
        for i, o in enumerate(oracles):
            obs, info = o.reset(seed=21 + i)
            _assert_sub_env(td, i, obs, info, "reset")
        running = [True] * N
        mid_repeat = False
        for t, a in enumerate(actions):
            td = env.step(td.set("action", a))
            for i, o in enumerate(oracles):
                if not running[i]:
                    continue
                obs, reward, term, trunc, info = _clone(o.step(a[i : i + 1]))
                _assert_sub_env(td["next"], i, obs, info, f"outer step {t}")
                assert torch.equal(td["next", "reward"][i], reward), t
                if bool(term | trunc):
                    running[i] = False
                    mid_repeat |= int(info["elapsed_steps"]) % repeat != 0
            if not any(running):
                break
            td = step_mdp(td)
        assert not any(running), "both episodes should end within 80 inner steps"
        assert mid_repeat, "an episode should end mid-repeat"
    finally:
        for o in oracles:
            o.close()


def test_collector_with_transforms(pick_vec):
    env = TransformedEnv(pick_vec, Compose(ActionRepeat(2), EpisodeMetrics()))  # 4-step episodes
    n = env.batch_size[0]
    env.set_seed(0)
    # total_frames=-1 and two batches: a finite run closes the env when it ends, and it is shared.
    collector = Collector(env, None, frames_per_batch=8 * n, total_frames=-1)
    try:
        batches = list(itertools.islice(collector, 2))
    finally:
        collector.shutdown(close_env=False)
    assert len(batches) == 2 and batches[0].shape == (n, 8)
    batch = torch.cat(batches, 1)
    done = batch["next", "done"].squeeze(-1)
    assert int(done.sum()) == 16 * n // 2  # an episode every 2 agent steps, in each sub-env
    assert (batch["next", "episode", "episode_len"][done] == 2).all()
    assert (batch["next", "elapsed_steps"][done] == 4).all()


@pytest.mark.pictures
def test_rgb_observations_and_render():
    env = ManiSkillEnv(
        "PickCube-v1",
        num_envs=N,
        sim_backend="cpu",
        obs_mode="rgb",
        from_pixels=True,
        sensor_configs=dict(width=32, height=32),
        human_render_camera_configs=dict(width=48, height=40),
    )
    raw = make_gym_env(
        "PickCube-v1",
        obs_mode="rgb",
        render_mode="rgb_array",
        sensor_configs=dict(width=32, height=32),
        human_render_camera_configs=dict(width=48, height=40),
    )
    try:
        rgb_key = ("sensor_data", "base_camera", "rgb")
        assert env.observation_spec[rgb_key].shape == (N, 32, 32, 3)
        assert env.observation_spec["pixels"].shape == (N, 40, 48, 3)
        td = env.reset(seed=4)
        assert td["pixels"].dtype == torch.uint8 and td.get(rgb_key).dtype == torch.uint8
        obs, _ = raw.reset(seed=5)
        # Raw pictures are on ManiSkill's render device (CUDA with sapien_cuda): compared on env.device.
        assert td.device == env.device and td["pixels"].device == td.get(rgb_key).device == env.device
        assert torch.equal(td.get(rgb_key)[1], obs["sensor_data"]["base_camera"]["rgb"][0].to(env.device))
        assert torch.equal(td["pixels"][1], raw.render()[0].to(env.device))
        frames = env.render()
        assert frames.shape == (N, 40, 48, 3) and frames.dtype == torch.uint8 and frames.device == env.device
    finally:
        env.close()
        raw.close()


def test_dict_actions():
    env = ManiSkillEnv("TwoRobotPickCube-v1", num_envs=N, sim_backend="cpu", obs_mode="state", max_episode_steps=3)
    try:
        td = env.rollout(4, break_when_any_done=False)
        assert td.shape == (N, 4)
        assert set(env.full_action_spec["action"].keys()) == set(td["action"].keys())
        assert td["next", "done"].squeeze(-1)[:, 2].all()
    finally:
        env.close()


def test_wrapper_accepts_a_cpu_vector_env(pick_vec):
    """``pick_vec`` is ``ManiSkillWrapper(CPUVectorEnv(...))``; closing the wrapper stops the workers."""
    env, vec = pick_vec, pick_vec._env
    assert isinstance(vec, CPUVectorEnv)
    try:
        assert env.batch_size == torch.Size([3])
        assert env.rand_step(env.reset(seed=0))["next", "observation"].shape == (3, 42)
    finally:
        env.close()
    assert all(not p.is_alive() for p in vec._pool.processes)


def test_one_sub_env_runs_in_this_process_alone():
    """``CPUVectorEnv(id, 1)`` starts no worker: its one sub-env is this process's, and equals a raw env."""

    def assert_same(got, want, what):
        got = dict(_leaves(got))
        want = {k: v for k, v in _leaves(want) if isinstance(v, torch.Tensor)}
        assert set(want) <= set(got), (what, sorted(want), sorted(got))
        for key, w in want.items():
            assert got[key].dtype == w.dtype and torch.equal(got[key], w), (what, key)

    vec = CPUVectorEnv("PickCube-v1", 1, **PICK)
    raw = make_gym_env("PickCube-v1", **PICK)
    try:
        assert vec._pool is None
        obs, info = vec.reset(seed=4)
        want_obs, want_info = _clone(raw.reset(seed=4))
        assert_same(obs, want_obs, "reset obs")
        assert_same(info, want_info, "reset info")
        for t, a in enumerate(random_actions(gym.spaces.Box(-1, 1, (1, 8)), 3, seed=2)):
            got = vec.step(a)
            want = _clone(raw.step(a))
            assert_same(got[0], want[0], f"step {t} obs")
            assert_same(got[4], want[4], f"step {t} info")
            for i, what in ((1, "reward"), (2, "terminated"), (3, "truncated")):
                assert got[i].dtype == want[i].dtype and torch.equal(got[i], want[i]), (t, what)
    finally:
        vec.close()
        raw.close()


def test_a_failure_in_sub_env_0_leaves_the_workers_ready(pick):
    """Sub-env 0 steps in this process while the workers step theirs: its error is raised once
    they are done, and the env steps on (no call left pending in gymnasium's AsyncVectorEnv)."""
    vec = pick.unwrapped
    td = pick.reset(seed=0)

    def fail(action):
        raise RuntimeError("sub-env 0 failed")

    vec._local.step = fail
    try:
        with pytest.raises(RuntimeError, match="sub-env 0 failed"):
            pick.step(td.set("action", torch.zeros(N, 8)))
    finally:
        del vec._local.step
    assert pick.step(td.set("action", torch.zeros(N, 8)))["next", "reward"].shape == (N, 1)


def test_bad_input(pick):
    with pytest.raises(ValueError, match="forkserver"):
        CPUVectorEnv("PickCube-v1", 2, context="fork")
    with pytest.raises(ValueError, match="positive int, got 0"):
        CPUVectorEnv("PickCube-v1", 0)
    with pytest.raises(ValueError, match="3 seeds for 2 sub-envs"):
        pick.unwrapped.reset(seed=[1, 2, 3])
    td = pick.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2, 7\)"):
        pick.step(td.set("action", torch.zeros(N, 7)))
    with pytest.raises(ValueError, match="batch_size \\[1\\]"):
        TransformedEnv(pick, CPUUnbatch())
    # the env still steps after the refused action
    assert pick.step(td.set("action", torch.zeros(N, 8)))["next", "reward"].shape == (N, 1)


def test_dead_worker_raises_instead_of_hanging(pick):
    """Kills a worker of the shared ``pick`` env: the last test that uses it."""
    env = pick
    td = env.reset(seed=0)
    worker = env._env._pool.processes[-1]  # sub-env N - 1's (sub-env 0 runs in this process)
    os.kill(worker.pid, signal.SIGKILL)
    worker.join(5)
    with pytest.raises(
        RuntimeError, match=rf"CPUVectorEnv\(PickCube-v1\): worker\(s\) of sub-env\(s\) \[{N - 1}\] died during step"
    ):
        env.rand_step(td)
    assert all(not p.is_alive() for p in env._env._pool.processes)
    env.close()  # closing again is harmless


def test_a_worker_dead_outside_a_partial_reset_is_said_to_have_died():
    """A lockstep call to some workers (a partial reset) while another worker is dead: the wait sees the dead
    one's closed pipe and says it died (not that the engine is out of step with its workers)."""
    engine = CPUVectorEnv("MS-CartpoleBalance-v1", 3, in_process=False, **CART)
    try:
        engine.reset(seed=0)
        worker = engine._pool.processes[2]
        os.kill(worker.pid, signal.SIGKILL)
        worker.join(5)
        with pytest.raises(RuntimeError, match=r"worker\(s\) of sub-env\(s\) \[2\] died"):
            engine.reset(seed=1, options={"env_idx": [0]})
    finally:
        engine.close()


def test_script_without_main_guard_gets_a_clear_error(no_guard_script) -> None:
    """forkserver workers import the main script again: without a guard they die while starting."""
    proc = no_guard_script.result(check=False)
    assert proc.returncode != 0
    assert "a worker process died while starting" in proc.stderr, proc.stderr[-3000:]
    assert "if __name__ == '__main__':" in proc.stderr, proc.stderr[-3000:]


def test_workers_fork_from_a_preloaded_forkserver(monkeypatch):
    """A pool with workers asks the forkserver to import the workers' modules first (the tests' own
    forkserver already has: here the call is recorded, not made); without workers nothing is asked."""
    import maniskill_torchrl.engines.cpu_vector as cpu_vector_module

    asked = []
    monkeypatch.setattr(cpu_vector_module, "preload_forkserver", lambda modules: asked.append(tuple(modules)))
    CPUVectorEnv("PickCube-v1", num_envs=1, obs_mode="state").close()
    assert asked == []
    CPUVectorEnv("PickCube-v1", num_envs=2, obs_mode="state", in_process=True).close()
    assert asked == [cpu_vector_module.WORKER_IMPORTS] and "mani_skill.envs" in asked[0]
