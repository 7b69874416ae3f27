"""CPUUnbatch: one CPU ManiSkill env (batch [1]) as an unbatched TorchRL env, and stacked again.

Every comparison between two env instances seeds every reset."""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.data import Bounded
from torchrl.envs import Compose, ParallelEnv, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from maniskill_torchrl import (
    CPUUnbatch,
    EpisodeMetrics,
    IgnoreTerminations,
    ManiSkillEnv,
    ManiSkillWrapper,
)
from maniskill_torchrl.transforms import CPUUnbatch as CPUUnbatchFromTransforms
from support.helpers import make_gym_env, random_actions
from support.toy_env import ToyEnv

T_MAX = 4  # time limit of the ParallelEnv / collector env


def worker_env():
    """Per-worker env of the ParallelEnv test (module level: spawned workers import it)."""
    env = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=T_MAX)
    return TransformedEnv(env, Compose(CPUUnbatch(), IgnoreTerminations(), EpisodeMetrics()))


@pytest.fixture(scope="module")
def pick_state():
    """(batched ManiSkillEnv, a second one under CPUUnbatch)."""
    batched = ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=6)
    unbatched = TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=6), CPUUnbatch())
    yield batched, unbatched
    batched.close()
    unbatched.close()


def _assert_specs_squeezed(parent_spec, spec):
    """Every leaf of ``spec`` is the parent's leaf without the env dim: same class, dtype, bounds."""
    assert spec.shape == parent_spec.shape[1:]
    parent_keys = set(parent_spec.keys(True, True))
    assert set(spec.keys(True, True)) == parent_keys
    for key in parent_keys:
        p, s = parent_spec[key], spec[key]
        assert type(s) is type(p), key
        assert s.dtype == p.dtype, key
        assert s.shape == p.shape[1:], key
        assert s.device == p.device, key
        if isinstance(p, Bounded):
            assert torch.equal(s.space.low, p.space.low[0]), key
            assert torch.equal(s.space.high, p.space.high[0]), key


def _assert_same_rollout(batched, unbatched, actions, seed, steps):
    """Seeded resets and the same actions: every unbatched entry is the batched one squeezed."""
    td_b = batched.reset(seed=seed)
    td_u = unbatched.reset(seed=seed)
    for key in td_b.keys(True, True):
        assert torch.equal(td_u[key], td_b[key].squeeze(0)), key
    for t in range(steps):
        act = actions[t]
        if isinstance(act, dict):
            td_u["action"] = TensorDict(act, batch_size=[])
            td_b["action"] = TensorDict(act, batch_size=[]).unsqueeze(0)
        else:
            td_u["action"] = act
            td_b["action"] = act.unsqueeze(0)
        td_b = batched.step(td_b)
        td_u = unbatched.step(td_u)
        assert td_u.batch_size == torch.Size([])
        for key in td_b["next"].keys(True, True):
            assert torch.equal(td_u["next", key], td_b["next", key].squeeze(0)), key
        # The input entries are left as given (actions stay unbatched).
        for key in td_u["action"].keys(True, True) if isinstance(act, dict) else []:
            assert td_u["action", key].shape == act[key].shape
        td_b, td_u = step_mdp(td_b), step_mdp(td_u)


def test_pickcube_state_specs_and_data(pick_state):
    batched, unbatched = pick_state
    assert unbatched.batch_size == torch.Size([])
    _assert_specs_squeezed(batched.output_spec, unbatched.output_spec)
    _assert_specs_squeezed(batched.input_spec, unbatched.input_spec)
    assert unbatched.observation_spec["observation"].shape == torch.Size([42])
    assert unbatched.action_spec.shape == torch.Size([8])
    assert unbatched.reward_spec.shape == torch.Size([1])
    assert unbatched.full_done_spec["done"].shape == torch.Size([1])
    assert unbatched.observation_spec["success"].shape == torch.Size([])
    assert unbatched.observation_spec["elapsed_steps"].dtype == torch.int32
    check_env_specs(unbatched, seed=0)
    actions = random_actions(gym.spaces.Box(-1, 1, (8,)), 4, seed=3)
    _assert_same_rollout(batched, unbatched, actions, seed=11, steps=4)


def test_pickcube_state_dict_nested_obs():
    batched = ManiSkillEnv("PickCube-v1", obs_mode="state_dict")
    unbatched = TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state_dict"), CPUUnbatch())
    try:
        _assert_specs_squeezed(batched.output_spec, unbatched.output_spec)
        assert unbatched.observation_spec["agent", "qpos"].shape == torch.Size([9])
        assert unbatched.observation_spec["extra", "tcp_pose"].shape == torch.Size([7])
        check_env_specs(unbatched, seed=0)
        actions = random_actions(batched._env.unwrapped.single_action_space, 3, seed=4)
        _assert_same_rollout(batched, unbatched, actions, seed=5, steps=3)
    finally:
        batched.close()
        unbatched.close()


def test_two_robot_dict_action():
    batched = ManiSkillEnv("TwoRobotPickCube-v1", obs_mode="state_dict")
    unbatched = TransformedEnv(ManiSkillEnv("TwoRobotPickCube-v1", obs_mode="state_dict"), CPUUnbatch())
    try:
        _assert_specs_squeezed(batched.input_spec, unbatched.input_spec)
        _assert_specs_squeezed(batched.output_spec, unbatched.output_spec)
        agents = list(batched.full_action_spec["action"].keys())
        assert len(agents) == 2
        for agent in agents:
            assert unbatched.full_action_spec["action", agent].shape == torch.Size([8])
        check_env_specs(unbatched, seed=0)
        space = batched._env.unwrapped.single_action_space
        actions = random_actions(space, 3, seed=6)
        _assert_same_rollout(batched, unbatched, actions, seed=7, steps=3)
        td = unbatched.rand_step(unbatched.reset(seed=1))
        assert td["action", agents[0]].shape == torch.Size([8])
    finally:
        batched.close()
        unbatched.close()


def test_reset_mask_and_time_limit(pick_state):
    _, env = pick_state
    env.set_seed(0)
    td = env.reset(TensorDict(_reset=torch.tensor([True])))
    assert td["observation"].shape == torch.Size([42])
    assert td["done"].shape == torch.Size([1])
    # A no-op reset keeps the unbatched done shapes.
    td = env.reset(TensorDict(_reset=torch.tensor([False])))
    assert td.batch_size == torch.Size([]) and td["done"].shape == torch.Size([1])
    # Past the time limit (6): the rollout resets through "_reset" and keeps going.
    roll = env.rollout(14, break_when_any_done=False)
    assert roll.batch_size == torch.Size([14])
    assert roll["next", "truncated"].squeeze(-1).nonzero().squeeze(-1).tolist() == [5, 11]
    assert roll["next", "elapsed_steps"].tolist() == [1, 2, 3, 4, 5, 6] * 2 + [1, 2]


def test_transforms_after_it_see_unbatched_data():
    # StepCounter / RewardSum read their state from the root tensordict: it must stay unbatched.
    env = TransformedEnv(
        ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=5),
        Compose(CPUUnbatch(), StepCounter(), RewardSum()),
    )
    try:
        env.set_seed(0)
        roll = env.rollout(7, break_when_any_done=False)
        assert roll["next", "step_count"].shape == torch.Size([7, 1])
        assert roll["next", "step_count"].squeeze(-1).tolist() == [1, 2, 3, 4, 5, 1, 2]
        rewards = roll["next", "reward"].squeeze(-1)
        assert torch.allclose(roll["next", "episode_reward"].squeeze(-1)[:5], rewards[:5].cumsum(0))
        check_env_specs(env, seed=0)
    finally:
        env.close()


def test_exported_and_picklable():
    assert CPUUnbatch is CPUUnbatchFromTransforms
    t = pickle.loads(pickle.dumps(CPUUnbatch()))
    assert isinstance(t, CPUUnbatch)
    assert repr(t) == "CPUUnbatch()"


# ----------------------------------------------------------------------------- errors
def test_error_batch_not_one():
    with pytest.raises(ValueError, match=r"batch_size \[1\].*got batch_size \[3\].*ParallelEnv"):
        TransformedEnv(ToyEnv([1, 2, 3]), CPUUnbatch())
    # Inside a Compose the parent is only known once the env is built: same error.
    with pytest.raises(ValueError, match=r"batch_size \[1\].*ParallelEnv"):
        TransformedEnv(ToyEnv([1, 2, 3]), Compose(StepCounter(), CPUUnbatch()))
    with pytest.raises(ValueError, match=r"got batch_size \[\]"):
        TransformedEnv(ToyEnv(3), CPUUnbatch())


def test_non_maniskill_parent_with_batch_one():
    # Decision: any [1]-batched env can be unbatched (the GPU check only applies to ManiSkill envs).
    env = TransformedEnv(ToyEnv([2]), CPUUnbatch())
    check_env_specs(env)
    roll = env.rollout(3, break_when_any_done=False)
    assert roll["next", "done"].squeeze(-1).tolist() == [False, True, False]
    assert roll["next", "nested", "deep", "x"].shape == torch.Size([3, 2])


class _FakeGPUWrapper(ManiSkillWrapper):
    """A CPU env that claims to run on the GPU sim (none can be made here)."""

    @property
    def gpu_sim_enabled(self) -> bool:
        return True


def test_error_gpu_sim():
    env = _FakeGPUWrapper(make_gym_env("PickCube-v1", obs_mode="state"))
    try:
        with pytest.raises(ValueError, match="GPU sim.*batched env directly"):
            TransformedEnv(env, CPUUnbatch())
        with pytest.raises(ValueError, match="GPU sim.*batched env directly"):
            TransformedEnv(env, Compose(StepCounter(), CPUUnbatch()))
    finally:
        env.close()


# ----------------------------------------------------------------------------- ParallelEnv
def test_parallel_env_and_collector():
    """ParallelEnv(2) of unbatched envs: batch [2], rollouts, and a collector keeping "episode".

    Spawned workers import ManiSkill (several seconds each): one ParallelEnv serves both checks.
    """
    penv = ParallelEnv(2, worker_env)
    try:
        assert penv.batch_size == torch.Size([2])
        assert penv.observation_spec["episode", "return"].shape == torch.Size([2])
        penv.set_seed(0)
        roll = penv.rollout(3)
        assert roll.batch_size == torch.Size([2, 3])
        assert roll["next", "observation"].shape == torch.Size([2, 3, 42])
        assert roll["next", "episode", "episode_len"].tolist() == [[1, 2, 3]] * 2

        # total_frames=-1: a finite run closes the env when it ends (slow: ManiSkill's close runs gc).
        collector = Collector(penv, None, frames_per_batch=2 * 2 * T_MAX, total_frames=-1)
        try:
            data = next(iter(collector))
        finally:
            collector.shutdown(close_env=False)
        assert data.batch_size == torch.Size([2, 2 * T_MAX])
        ep = data["next", "episode"]
        assert set(ep.keys()) == {"return", "episode_len", "reward", "success_once", "success_at_end"}
        # Episodes run to the time limit (IgnoreTerminations): the length is ManiSkill's step counter.
        assert torch.equal(ep["episode_len"], data["next", "elapsed_steps"].long())
        rewards = data["next", "reward"].squeeze(-1).numpy()
        lens = ep["episode_len"].numpy()
        for i in range(2):
            start = None
            for t in range(2 * T_MAX):
                if lens[i, t] == 1:
                    start = t
                if start is None:  # the batch may open mid-episode
                    continue
                expected = np.sum(rewards[i, start : t + 1])
                assert ep["return"][i, t].numpy().tobytes() == expected.tobytes()
    finally:
        penv.close(raise_if_closed=False)


def test_the_parent_keys_cache_is_a_declared_attribute_dropped_with_the_parent():
    """What it caches of its parent is a plain attribute, filled on first use and dropped by
    TorchRL's hooks (``empty_cache``, ``set_container``), as TorchRL's transforms keep theirs."""
    unbatch = CPUUnbatch()
    assert unbatch._parent_in_keys_cache is None
    env = TransformedEnv(ToyEnv([4]), Compose(StepCounter(), unbatch))
    env.rollout(2)
    assert unbatch._parent_in_keys_cache == ["action", "step_count"]
    env.empty_cache()
    assert unbatch._parent_in_keys_cache is None
    env.rollout(2)
    clone = unbatch.clone()
    TransformedEnv(ToyEnv([4]), clone)
    assert clone._parent_in_keys_cache is None
