"""Resetting to saved ManiSkill states: ``env.get_state()`` and ``env.reset(td, set_state=True,
scene_state=...)`` / ``env.reset_to_state(...)`` (TorchRL's deterministic-reset convention, as
IsaacLabWrapper's), on the single env, the batched CPU env (partial resets too) and an unbatched
env; the oracles are the recording itself and raw ManiSkill's ``reset_to_env_states``.

ManiSkill's own state reset does not replay every task bit for bit: for Panda tasks, a raw
``env.reset(seed=s)`` then ``set_state_dict(get_state_dict())`` already drifts in the last bits
of the first step (PhysX keeps more than the state dict holds). MS-CartpoleBalance-v1 replays
exactly, and is the task where a replay must equal the recording; on PickCube-v1 the library must
equal raw ManiSkill doing the same state reset.
"""

from __future__ import annotations

import pytest
import torch
from torchrl.envs import Compose, TransformedEnv

from maniskill_torchrl import EpisodeMetrics, ManiSkillEnv
from maniskill_torchrl.data import ManiSkillExperienceReplay
from maniskill_torchrl.testing import assert_tensordict_equal
from maniskill_torchrl.transforms import CPUUnbatch, EnvStates
from support.helpers import close_envs, make_gym_env, record_episodes
from support.toy_env import ToyEnv

STEPS = 12


def _actions(env, n: int = STEPS, seed: int = 0) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(env.action_spec.shape, generator=g) * 2 - 1 for _ in range(n)]


def _play(env, td, actions):
    """The "next" tensordicts of stepping ``actions`` from ``td`` (no auto-reset), stacked."""
    out = []
    for a in actions:
        td = env.step(td.set("action", a))["next"]
        out.append(td.clone())
    return torch.stack(out)


@pytest.mark.parametrize("num_envs", [1, 2])
def test_replay_from_the_first_state_equals_the_recording(num_envs):
    kwargs = dict(obs_mode="state", max_episode_steps=50)
    if num_envs > 1:
        kwargs["sim_backend"] = "cpu"
    env = ManiSkillEnv("MS-CartpoleBalance-v1", num_envs=num_envs, **kwargs)
    try:
        actions = _actions(env)
        start = env.reset(seed=5)
        first_state = env.get_state()
        assert first_state.batch_size == torch.Size([num_envs])
        recording = _play(env, start.clone(), actions)
        _play(env, env.reset(seed=77), _actions(env, 5, seed=1))  # somewhere else meanwhile
        again = env.reset_to_state(first_state)
        assert_tensordict_equal(again, start, msg="the reset")
        assert_tensordict_equal(_play(env, again, actions), recording, msg="the replay")
        # A state reset draws no seed: the next seeded full reset is the one set_seed planned.
        assert_tensordict_equal(env.reset(seed=5), start)
    finally:
        env.close()


def test_partial_reset_to_saved_states():
    env = ManiSkillEnv("MS-CartpoleBalance-v1", num_envs=2, sim_backend="cpu", obs_mode="state")
    try:
        actions = _actions(env)
        start = env.reset(seed=5)
        saved = env.get_state()
        recording = _play(env, start.clone(), actions)
        now = recording[-1]
        # Only env 0 goes back; env 1's row of the saved states is not read.
        mask = torch.tensor([[True], [False]])
        saved[1] = saved[1].apply(torch.zeros_like)
        td = env.reset(now.clone().set("_reset", mask), set_state=True, scene_state=saved)
        assert torch.equal(td["observation"][0], start["observation"][0])
        assert torch.equal(td["observation"][1], now["observation"][1])
        assert td["elapsed_steps"].tolist() == [0, STEPS]
        step = env.step(td.set("action", actions[0]))["next"]
        assert torch.equal(step["observation"][0], recording[0]["observation"][0])
    finally:
        env.close()


def test_equal_to_maniskill_state_reset_where_maniskill_drifts():
    """PickCube-v1: ManiSkill's own state reset is not a bit-exact replay; ours equals it, call for
    call (raw ManiSkill first, then the library, each doing the same sequence)."""
    actions = _actions(ManiSkillEnv("PickCube-v1", obs_mode="state"))

    def sequence(reset, step, get_state, reset_to):
        reset(5)
        state = get_state()
        reset(8)
        for a in actions[:3]:  # another episode in between: the same on both sides
            step(a)
        out = [reset_to(state)]
        return state, out + [step(a) for a in actions]

    raw = make_gym_env("PickCube-v1", obs_mode="state", max_episode_steps=50)
    try:
        raw_state, theirs = sequence(
            lambda s: raw.reset(seed=s),
            lambda a: raw.step(a.clone())[:4],
            lambda: raw.unwrapped.get_state_dict(),
            lambda st: raw.reset(seed=3, options={"reset_to_env_states": {"env_states": st}})[0],
        )
    finally:
        close_envs([raw])
    env = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=50)
    td = {}
    try:

        def step(a):
            td["now"] = env.step(td["now"].set("action", a.clone()))["next"]
            return td["now"]

        def reset(seed):
            td["now"] = env.reset(seed=seed)

        def reset_to(state):
            td["now"] = env.reset_to_state(state, seed=3)
            return td["now"]

        state, ours = sequence(reset, step, env.get_state, reset_to)
    finally:
        env.close()
    assert_tensordict_equal(state, state.empty().update(raw_state), msg="get_state")
    assert torch.equal(ours[0]["observation"], theirs[0])
    for t, (mine, (obs, reward, terminated, truncated)) in enumerate(zip(ours[1:], theirs[1:])):
        assert torch.equal(mine["observation"], obs), t
        assert torch.equal(mine["reward"][:, 0], reward), t
        assert torch.equal(mine["terminated"][:, 0], terminated), t
        assert torch.equal(mine["truncated"][:, 0], truncated), t


def test_unbatched_env_and_transformed_env():
    env = TransformedEnv(ManiSkillEnv("MS-CartpoleBalance-v1", batch_size=[], obs_mode="state"), EpisodeMetrics())
    try:
        start = env.reset(seed=2)
        state = env.base_env.get_state()
        assert state.batch_size == torch.Size([])
        env.rollout(4)
        td = env.reset(set_state=True, scene_state=state)  # the transforms reset too
        assert torch.equal(td["observation"], start["observation"])
        assert td["episode", "episode_len"].item() == 0
    finally:
        env.close()


def test_state_reset_arguments_are_checked():
    env = ManiSkillEnv("MS-CartpoleBalance-v1", obs_mode="state")
    try:
        env.reset(seed=0)
        with pytest.raises(ValueError, match=r"set_state=True and scene_state"):
            env.reset(set_state=True)
        with pytest.raises(ValueError, match=r"set_state=True and scene_state"):
            env.reset(scene_state=env.get_state())
    finally:
        env.close()


def test_batched_cpu_env_get_state_equals_each_sub_env():
    env = ManiSkillEnv("PickCube-v1", num_envs=2, sim_backend="cpu", obs_mode="state")
    raws = [make_gym_env("PickCube-v1", obs_mode="state") for _ in range(2)]
    try:
        env.reset(seed=11)
        for i, raw in enumerate(raws):
            raw.reset(seed=11 + i)
            expected = env.get_state()[i : i + 1]
            assert_tensordict_equal(expected, expected.empty().update(raw.unwrapped.get_state_dict()))
    finally:
        env.close()
        close_envs(raws)


# ----------------------------------------------------------------------------- trajectory files
@pytest.fixture(scope="module")
def pick_cube_file(tmp_path_factory):
    """One seeded PickCube-v1 episode recorded by ManiSkill's RecordEpisode, loaded."""
    out = tmp_path_factory.mktemp("states")
    env = make_gym_env("PickCube-v1", obs_mode="state", max_episode_steps=6)
    path = record_episodes(env, out, seeds=[3], lengths=6, action_seeds=[1])
    return ManiSkillExperienceReplay(path, 2, root=out / "cache")[:]


@pytest.mark.parametrize(
    "kwargs",
    [
        pytest.param(dict(batch_size=[]), id="unbatched"),
        pytest.param({}, id="batch1"),
        # a loaded dataset's rows are memory-mapped: sent to the CPU workers as plain copies
        pytest.param(dict(num_envs=2, sim_backend="cpu"), id="num_envs2"),
    ],
)
def test_a_files_env_states_row_resets_to_that_step(pick_cube_file, kwargs):
    """One step's ``env_states`` row of a RecordEpisode file (``data[i]["env_states"]``, no batch
    dim) resets every env to that step: the same observation as raw ManiSkill's
    ``reset_to_env_states`` with that row, bit for bit, and the file's observation at that step
    up to ManiSkill's state-reset drift (the TCP pose, from forward kinematics, in its last bits)."""
    data = pick_cube_file
    raw = make_gym_env("PickCube-v1", obs_mode="state")
    env = ManiSkillEnv("PickCube-v1", obs_mode="state", **kwargs)
    try:
        raw.reset(seed=0)
        env.reset(seed=0)
        for i in range(data.shape[0]):
            row = data[i]["env_states"]  # memory-mapped, as users index a loaded dataset
            theirs, _ = raw.reset(options={"reset_to_env_states": {"env_states": row.unsqueeze(0).to_dict()}})
            obs = env.reset_to_state(row)["observation"].reshape(-1, theirs.shape[-1])
            for j, ours in enumerate(obs):
                assert torch.equal(ours, theirs[0]), (i, j)
                torch.testing.assert_close(ours, data[i]["observation"], rtol=0, atol=1e-6, msg=f"step {i}, env {j}")
    finally:
        env.close()
        close_envs([raw])


# ----------------------------------------------------------------------------- EnvStates
def _scripted(actions):
    it = iter(actions)
    return lambda td: td.set("action", next(it))


def test_env_states_after_cpu_unbatch_are_unbatched():
    """EnvStates after CPUUnbatch gives what it gives before it: each step's states unbatched
    (``[T, 13]`` for the cube), in the spec too, and the env's own states after the last step."""
    rollouts, nows = {}, {}
    for name, order in (("before", [EnvStates(), CPUUnbatch()]), ("after", [CPUUnbatch(), EnvStates()])):
        env = TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state"), Compose(*order))
        try:
            assert env.observation_spec["env_states"].shape == torch.Size([]), name
            env.set_seed(4)
            rollouts[name] = env.rollout(3, policy=_scripted(_actions(env, 3)))
            nows[name] = env.base_env.get_state()[0]  # the ManiSkill env's own [1] batch, its one row
            assert env.observation_spec["env_states"].is_in(rollouts[name][0]["env_states"]), name
        finally:
            env.close()
    after = rollouts["after"]
    assert after["env_states", "actors", "cube"].shape == torch.Size([3, *nows["after"]["actors", "cube"].shape])
    assert_tensordict_equal(after["next", "env_states"][-1], nows["after"])
    assert_tensordict_equal(
        after.select("env_states", ("next", "env_states")),
        rollouts["before"].select("env_states", ("next", "env_states")),
    )


def test_env_states_needs_a_maniskill_env():
    env = TransformedEnv(ToyEnv(ends=3), EnvStates())
    with pytest.raises(TypeError, match=r"EnvStates reads ManiSkill sim states.*ManiSkillEnv"):
        env.reset()
