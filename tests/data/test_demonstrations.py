"""ManiSkill trajectory files as TorchRL replay buffers (``ManiSkillExperienceReplay``): a file that
ManiSkill's own ``RecordEpisode`` writes here (nothing can be downloaded) loads as exactly what
``ManiSkillEnv(batch_size=[])`` gives stepping the same seeds and actions; selection, slices,
the memmap cache, and bad files. TorchRL rollouts written by ``save_trajectories`` read back as
the rollout through ManiSkill's ``ManiSkillTrajectoryDataset`` and the library's loader."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import h5py
import pytest
import torch
from mani_skill.trajectory.dataset import ManiSkillTrajectoryDataset
from torchrl.data.replay_buffers import SliceSampler
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import step_mdp

from maniskill_torchrl import ManiSkillEnv, ManiSkillWrapper
from maniskill_torchrl.data import ManiSkillExperienceReplay, save_trajectories
from maniskill_torchrl.testing import assert_tensordict_equal
from maniskill_torchrl.transforms import EnvStates
from support.helpers import TIMEOUT_S, make_gym_env, random_actions, record_episodes

TASK = "PickCube-v1"
STEPS = 6  # the time limit: every episode truncates there
SEEDS = [11, 12, 13]


def _actions(space) -> list[list[torch.Tensor]]:
    return [random_actions(space, STEPS, seed=s) for s in SEEDS]


@pytest.fixture(scope="module", params=["state", "state_dict"])
def recorded(request, tmp_path_factory):
    """ManiSkill's RecordEpisode file of 3 seeded episodes, the obs mode, and the reference: the
    same episodes stepped through ``ManiSkillWrapper(env, batch_size=[])`` on the very gym env
    that then records them."""
    out = tmp_path_factory.mktemp(f"demos-{request.param}")
    env = make_gym_env(TASK, obs_mode=request.param, max_episode_steps=STEPS)
    actions = _actions(env.unwrapped.single_action_space)
    # Not the instance's first reset on either side: ManiSkill's first reset gives a cube
    # quaternion's zero components the other sign (-0.0) than later resets of the same seed.
    env.reset(seed=0)
    wrapped = ManiSkillWrapper(env, batch_size=[])
    steps = []
    for seed, episode in zip(SEEDS, actions):
        td = wrapped.reset(seed=seed)
        td["env_states"] = wrapped.get_state()  # what RecordEpisode records after the reset
        for a in episode:
            td = wrapped.step(td.set("action", a))
            td["next", "env_states"] = wrapped.get_state()
            # Leaf by leaf: TensorDict.clone() (tensordict 0.14) adds 0 to float leaves, which
            # turns ManiSkill's -0.0 quaternion components into +0.0.
            steps.append(td.apply(torch.Tensor.clone))
            td = step_mdp(td)
    return record_episodes(env, out, SEEDS, STEPS), request.param, torch.stack(steps)


def test_loads_as_the_env_steps(recorded, tmp_path):
    path, obs_mode, expected = recorded
    demos = ManiSkillExperienceReplay(path, batch_size=4, env_id=TASK, root=tmp_path)
    data = demos[:]
    assert len(demos) == len(SEEDS) * STEPS
    assert data["collector", "traj_ids"].tolist() == [i for i in range(len(SEEDS)) for _ in range(STEPS)]
    keys = [k for k in data.keys(include_nested=True, leaves_only=True) if k != ("collector", "traj_ids")]
    missing = set(keys) - set(expected.keys(include_nested=True, leaves_only=True))
    assert not missing, f"keys the env does not have: {missing}"
    assert_tensordict_equal(data.exclude("collector"), expected.select(*keys))
    assert ("next", "reward") in keys and ("next", "success") in keys
    # The sim states too: each step's starting state at the root, the one after it in "next".
    assert {("env_states", "actors", "cube"), ("next", "env_states", "articulations", "panda")} <= set(keys)
    # The observation keys are all there, nested as the env nests them.
    obs_keys = set(ManiSkillEnv(TASK, batch_size=[], obs_mode=obs_mode).observation_spec.keys(True, True))
    assert {k for k in obs_keys if k not in ("is_grasped", "is_obj_placed", "is_robot_static")} <= set(keys)
    # Sampling gives the same layout.
    assert set(demos.sample().keys(True, True)) - {"index"} == set(data.keys(True, True))


def test_selection_slices_and_cache(recorded, tmp_path):
    path, _, _ = recorded
    meta = json.loads(path.with_suffix(".json").read_text())
    succeeded = [e["episode_id"] for e in meta["episodes"] if e.get("success")]
    if succeeded:
        only = ManiSkillExperienceReplay(path, 4, success_only=True, root=tmp_path)
        assert sorted(set(only[:]["collector", "traj_ids"].tolist())) == succeeded
    else:
        with pytest.raises(ValueError, match="no episode left"):
            ManiSkillExperienceReplay(path, 4, success_only=True, root=tmp_path)
    two = ManiSkillExperienceReplay(path, 4, num_episodes=2, root=tmp_path)
    assert set(two[:]["collector", "traj_ids"].tolist()) == {0, 1}
    sliced = ManiSkillExperienceReplay(
        path, 8, root=tmp_path, sampler=SliceSampler(slice_len=4, traj_key=("collector", "traj_ids"))
    )
    batch = sliced.sample()
    ids = batch["collector", "traj_ids"].reshape(2, 4)
    assert (ids == ids[:, :1]).all()  # each slice within one episode
    steps = batch["next", "elapsed_steps"].reshape(2, 4)
    assert (steps[:, 1:] - steps[:, :-1] == 1).all()  # consecutive steps
    # A second load reads the memmap cache: same data.
    again = ManiSkillExperienceReplay(path, 4, root=tmp_path)
    assert again._is_downloaded()
    assert_tensordict_equal(again[:], ManiSkillExperienceReplay(path, 4, root=tmp_path)[:])
    assert "episodes=3" in repr(again)


def test_bad_files(recorded, tmp_path):
    path, _, _ = recorded
    lone = tmp_path / "lone.h5"
    shutil.copy(path, lone)
    with pytest.raises(FileNotFoundError, match=r"lone.json not found"):
        ManiSkillExperienceReplay(lone, 4, root=tmp_path)
    with pytest.raises(ValueError, match=r"holds episodes of 'PickCube-v1', not 'PushCube-v1'"):
        ManiSkillExperienceReplay(path, 4, env_id="PushCube-v1", root=tmp_path)
    broken = tmp_path / "broken.h5"
    broken.write_bytes(path.read_bytes()[:200])
    shutil.copy(path.with_suffix(".json"), broken.with_suffix(".json"))
    with pytest.raises(OSError, match=r"broken.h5 as HDF5.*truncated"):
        ManiSkillExperienceReplay(broken, 4, root=tmp_path)
    bare = tmp_path / "bare.h5"
    shutil.copy(path, bare)
    shutil.copy(path.with_suffix(".json"), bare.with_suffix(".json"))
    with h5py.File(bare, "a") as f:
        for key in f:
            del f[key]["obs"]
    with pytest.raises(ValueError, match=r"no observations.*replay_trajectory"):
        ManiSkillExperienceReplay(bare, 4, root=tmp_path)
    (tmp_path / "other.json").write_text("{}")
    shutil.copy(path, tmp_path / "other.h5")
    with pytest.raises(ValueError, match="not a ManiSkill trajectory .json"):
        ManiSkillExperienceReplay(tmp_path / "other.h5", 4, root=tmp_path)


def test_a_file_without_observations_is_refused(tmp_path):
    """RecordEpisode(obs_mode="none") writes an empty obs group: refused as a file without
    observations, with the way to add them."""
    env = make_gym_env(TASK, obs_mode="none", max_episode_steps=STEPS)
    record_episodes(env, tmp_path, SEEDS[:1], STEPS, name="none")
    with h5py.File(tmp_path / "none.h5") as f:
        assert len(f["traj_0"]["obs"]) == 0  # the case: an obs group, empty
    with pytest.raises(ValueError, match=r"no observations.*replay_trajectory --traj-path .*none.h5 -o state"):
        ManiSkillExperienceReplay(tmp_path / "none.h5", 4, root=tmp_path / "cache")


# ----------------------------------------------------------------------------- recording
class _Scripted:
    def __init__(self, actions):
        self._it = iter(actions)

    def __call__(self, td):
        return td.set("action", next(self._it))


@pytest.mark.parametrize("num_envs", [1, 2])
def test_rollouts_saved_in_maniskill_format(tmp_path, num_envs):
    """A TorchRL rollout written by save_trajectories: ManiSkill's ManiSkillTrajectoryDataset reads
    it as the rollout, the library's loader gives the rollout back, and its env_states reset the
    env to each episode's start."""
    kwargs = dict(obs_mode="state", max_episode_steps=5)
    if num_envs > 1:
        kwargs["sim_backend"] = "cpu"
    env = TransformedEnv(ManiSkillEnv(TASK, num_envs=num_envs, **kwargs), EnvStates())
    try:
        env.set_seed(3)
        g = torch.Generator().manual_seed(0)
        actions = [torch.rand(env.action_spec.shape, generator=g) * 2 - 1 for _ in range(12)]
        rollout = env.rollout(12, policy=_Scripted(actions), break_when_any_done=False)
        path = tmp_path / "ours.h5"
        ids = save_trajectories(path, rollout, env)
        assert len(ids) == 3 * num_envs  # per env: 2 full episodes (5 steps) and 2 steps of a third
        rows = rollout.reshape(-1, 12)
        flat = torch.cat(list(rows))  # episodes in the order written: env by env, in time

        theirs = ManiSkillTrajectoryDataset(str(path))
        assert theirs.env_id == TASK and theirs.env_kwargs["obs_mode"] == "state"
        assert torch.equal(torch.from_numpy(theirs.obs), flat["observation"])
        assert torch.equal(torch.from_numpy(theirs.actions), flat["action"])
        assert torch.equal(torch.from_numpy(theirs.rewards), flat["next", "reward"].reshape(-1))
        assert torch.equal(torch.from_numpy(theirs.terminated), flat["next", "terminated"].reshape(-1))
        assert torch.equal(torch.from_numpy(theirs.truncated), flat["next", "truncated"].reshape(-1))
        assert torch.equal(torch.from_numpy(theirs.success), flat["next", "success"])

        ours = ManiSkillExperienceReplay(path, 4, root=tmp_path / "cache")[:]
        keys = [k for k in ours.keys(True, True) if k not in (("collector", "traj_ids"), "elapsed_steps")]
        keys = [k for k in keys if k != ("next", "elapsed_steps")]
        # The saved env_states load back where EnvStates put them.
        assert {("env_states", "actors", "cube"), ("next", "env_states", "actors", "cube")} <= set(keys)
        assert_tensordict_equal(ours.select(*keys), flat.select(*keys))

        # Each episode's first env_states row takes the env back to that episode's start.
        with h5py.File(path) as f:
            first = {k: torch.from_numpy(v[:1]) for k, v in f["traj_1"]["env_states"]["actors"].items()}
            arts = {k: torch.from_numpy(v[:1]) for k, v in f["traj_1"]["env_states"]["articulations"].items()}
            start = torch.from_numpy(f["traj_1"]["obs"][0])
        if num_envs == 1:
            td = env.reset(set_state=True, scene_state={"actors": first, "articulations": arts})
            assert torch.equal(td["observation"][0], start)
    finally:
        env.close()


def test_maniskill_replay_trajectory_reads_saved_rollouts(tmp_path):
    """ManiSkill's replay_trajectory converts a saved rollout (with EnvStates) to state_dict
    observations; the library loads the converted file: the same actions, and the qpos it
    replayed from the recorded states match the rollout's (the first 9 entries of its state)."""
    env = TransformedEnv(ManiSkillEnv(TASK, obs_mode="state", max_episode_steps=5), EnvStates())
    try:
        env.set_seed(1)
        rollout = env.rollout(10, break_when_any_done=False)
        save_trajectories(tmp_path / "ours.h5", rollout, env)
    finally:
        env.close()
    cmd = [sys.executable, "-m", "mani_skill.trajectory.replay_trajectory", "--traj-path", str(tmp_path / "ours.h5")]
    cmd += ["--use-env-states", "-o", "state_dict", "--save-traj", "-b", "physx_cpu", "--allow-failure"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (converted,) = tmp_path.glob("ours.state_dict.*.h5")
    data = ManiSkillExperienceReplay(converted, 4, env_id=TASK, root=tmp_path / "cache")[:]
    steps = rollout.reshape(-1)
    assert torch.equal(data["action"], steps["action"])
    # ManiSkill's replay steps each action before setting the recorded state: its observations
    # carry the state reset's drift (see test_env_states.py), within 1e-4 here, none at a reset.
    torch.testing.assert_close(data["agent", "qpos"], steps["observation"][:, :9], rtol=0, atol=1e-4)
    torch.testing.assert_close(data["next", "agent", "qpos"], steps["next", "observation"][:, :9], rtol=0, atol=1e-4)
    starts = data["elapsed_steps"] == 0
    assert starts.sum() == 2 and torch.equal(data["agent", "qpos"][starts], steps["observation"][starts, :9])


@pytest.mark.parametrize("num_envs", [1, 2])
def test_saved_time_limit_is_the_envs(tmp_path, num_envs):
    """save_trajectories writes the env's time limit as RecordEpisode does for the same env, and
    in env_kwargs too: ManiSkillEnv(rb.env_id, **rb.env_kwargs) ends its episodes there. A
    RecordEpisode file (limit in env_info only) loads with the limit in env_kwargs as well."""
    limit = STEPS + 2  # not the task's registered 50
    raw = make_gym_env(TASK, obs_mode="state", max_episode_steps=limit)
    record_episodes(raw, tmp_path, SEEDS[:1], 1, name="theirs")
    theirs = json.loads((tmp_path / "theirs.json").read_text())["env_info"]["max_episode_steps"]
    assert theirs == limit

    kwargs = dict(obs_mode="state", max_episode_steps=limit)
    if num_envs > 1:
        kwargs["sim_backend"] = "cpu"  # one process per env
    env = ManiSkillEnv(TASK, num_envs=num_envs, **kwargs)
    try:
        env.set_seed(SEEDS[0])
        save_trajectories(tmp_path / "ours.h5", env.rollout(2), env)
    finally:
        env.close()
    info = json.loads((tmp_path / "ours.json").read_text())["env_info"]
    assert info["max_episode_steps"] == theirs
    assert info["env_kwargs"]["max_episode_steps"] == theirs

    loaded = {
        n: ManiSkillExperienceReplay(tmp_path / f"{n}.h5", 2, root=tmp_path / "cache") for n in ("ours", "theirs")
    }
    for name, rb in loaded.items():
        assert rb.env_kwargs["max_episode_steps"] == theirs, name
    replay = ManiSkillEnv(loaded["ours"].env_id, **loaded["ours"].env_kwargs)
    try:
        replay.set_seed(SEEDS[0])
        episode = replay.rollout(3 * limit)  # stops at the first done
    finally:
        replay.close()
    assert episode.shape[-1] == theirs and episode["next", "truncated"][..., -1, :].all()
