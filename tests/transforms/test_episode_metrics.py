"""EpisodeMetrics: ManiSkill's CPUGymWrapper(record_metrics=True) numbers, bit for bit, and per env
on batched envs with partial resets (checked against plain per-env python/numpy references).

Every comparison between two env instances seeds every reset."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from mani_skill.utils.wrappers import CPUGymWrapper
from tensordict import TensorDict
from torchrl.envs import Compose, ExcludeTransform, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from maniskill_torchrl import (
    ActionRepeat,
    CPUUnbatch,
    EpisodeMetrics,
    IgnoreTerminations,
    ManiSkillEnv,
    ManiSkillWrapper,
)
from maniskill_torchrl.transforms import EpisodeMetrics as EpisodeMetricsFromTransforms
from support.helpers import bits, make_gym_env, random_actions
from support.toy_env import ToyEnv, serial_toy_env

MAX_STEPS = {"PickCube-v1": 20, "MS-CartpoleBalance-v1": 30}
SEEDS = [3, 4, 5]


@pytest.fixture(scope="module")
def envs():
    """Per task: (gym env for CPUGymWrapper, ManiSkillEnv), made once; wrappers are built per test."""
    made = {}
    for env_id, steps in MAX_STEPS.items():
        made[env_id] = (
            make_gym_env(env_id, obs_mode="state", max_episode_steps=steps),
            ManiSkillEnv(env_id, obs_mode="state", max_episode_steps=steps),
        )
    yield made
    for gym_env, env in made.values():
        gym_env.close()
        env.close()


@pytest.mark.parametrize(
    "env_id, ignore",
    [
        ("PickCube-v1", True),
        ("PickCube-v1", False),
        ("MS-CartpoleBalance-v1", True),
        ("MS-CartpoleBalance-v1", False),
    ],
)
def test_same_numbers_as_cpu_gym_wrapper(envs, env_id, ignore):
    gym_env, ms_env = envs[env_id]
    ref = CPUGymWrapper(gym_env, ignore_terminations=ignore, record_metrics=True)
    transforms = [CPUUnbatch()] + ([IgnoreTerminations()] if ignore else []) + [EpisodeMetrics()]
    env = TransformedEnv(ms_env, Compose(*transforms))
    actions = iter(random_actions(ref.action_space, 200, seed=len(env_id) + ignore))
    lengths, fail_seen = [], False
    for seed in SEEDS:
        obs, _ = ref.reset(seed=seed)
        td = env.reset(seed=seed)
        assert np.array_equal(obs, td["observation"].numpy())
        assert not td["episode"].any()  # zeros at reset
        while True:
            action = next(actions)
            obs, reward, term, trunc, info = ref.step(action.numpy())
            td["action"] = action
            td = env.step(td)
            nxt = td["next"]
            assert np.array_equal(obs, nxt["observation"].numpy())
            assert bits(np.float32(reward)) == bits(nxt["reward"].numpy()[0])
            assert bool(term) == bool(nxt["terminated"]) and bool(trunc) == bool(nxt["truncated"])
            assert bool(nxt["done"]) == bool(term or trunc)
            ours, theirs = nxt["episode"], info["episode"]
            expected_keys = {"return", "episode_len", "reward"}
            for flag in ("success", "fail"):
                if flag in info:
                    expected_keys |= {f"{flag}_once", f"{flag}_at_end"}
                    # CPUGymWrapper reports *_at_end only with ignore_terminations; ours always.
                    assert bool(ours[f"{flag}_at_end"]) == bool(info[flag])
                    fail_seen |= flag == "fail" and bool(info[flag])
            assert set(ours.keys()) == expected_keys
            for key, value in theirs.items():
                if key == "episode_len":
                    assert int(ours[key]) == value and ours[key].dtype == torch.int64
                else:  # float32 return / reward and bools: same dtype, same bits
                    assert ours[key].numpy().dtype == np.asarray(value).dtype, key
                    assert bits(ours[key].numpy()) == bits(value), (key, ours[key], value)
            if term or trunc:
                lengths.append(int(theirs["episode_len"]))
                break
            td = step_mdp(td)
    assert max(lengths) > 8  # numpy's pairwise summation differs from a running sum past 8 steps
    if ignore:
        assert lengths == [MAX_STEPS[env_id]] * len(SEEDS)
    if env_id == "MS-CartpoleBalance-v1":
        assert fail_seen
        if not ignore:  # it terminates early on fail
            assert min(lengths) < MAX_STEPS[env_id]


# ----------------------------------------------------------------------------- batched, toy env
def _reference(rollout: TensorDict) -> dict:
    """Per env, from plain python lists: what EpisodeMetrics must report at every step."""
    reward = rollout["next", "reward"].squeeze(-1).numpy()
    done = rollout["next", "done"].squeeze(-1).numpy()
    success = rollout["next", "success"].numpy()
    fail = rollout["next", "fail"].numpy()
    n_env, n_t = reward.shape
    out = {
        k: np.zeros((n_env, n_t), dtype=d)
        for k, d in [
            ("return", np.float32),
            ("episode_len", np.int64),
            ("reward", np.float32),
            ("success_once", bool),
            ("success_at_end", bool),
            ("fail_once", bool),
            ("fail_at_end", bool),
        ]
    }
    for i in range(n_env):
        rewards, successes, fails = [], [], []
        for t in range(n_t):
            rewards.append(reward[i, t])
            successes.append(bool(success[i, t]))
            fails.append(bool(fail[i, t]))
            out["return"][i, t] = np.sum(rewards)
            out["episode_len"][i, t] = len(rewards)
            out["reward"][i, t] = np.sum(rewards) / len(rewards)
            out["success_once"][i, t] = any(successes)
            out["success_at_end"][i, t] = successes[-1]
            out["fail_once"][i, t] = any(fails)
            out["fail_at_end"][i, t] = fails[-1]
            if done[i, t]:
                rewards, successes, fails = [], [], []
    return out


def _assert_matches_reference(rollout: TensorDict, batch_dim_first: bool = True):
    ref = _reference(rollout)
    ep = rollout["next", "episode"]
    assert set(ep.keys()) == set(ref)
    for key, expected in ref.items():
        got = ep[key].numpy()
        assert got.dtype == expected.dtype, key
        assert bits(got) == bits(expected), (key, got, expected)
    # Root "episode" (what the policy sees): zeros right after a reset, else the last step's values.
    done = rollout["next", "done"].squeeze(-1)
    for key in ref:
        root, nxt = rollout["episode", key], ep[key]
        assert not root[:, 0].any()
        prev_done = done[:, :-1]
        assert torch.equal(root[:, 1:], torch.where(prev_done, torch.zeros_like(root[:, 1:]), nxt[:, :-1]))


def test_toy_batched_partial_resets():
    ends = [3, 5, 9, 12]
    env = TransformedEnv(ToyEnv(ends, terminate=[True, False, True, False]), EpisodeMetrics())
    check_env_specs(env)
    roll = env.rollout(40, break_when_any_done=False)
    # Several episodes per env, ending at different steps: the rollout reset them one by one.
    assert (roll["next", "done"].squeeze(-1).sum(-1) == torch.tensor([40 // e for e in ends])).all()
    assert roll["next", "episode", "episode_len"][:, -1].tolist() == [40 % e or e for e in ends]
    assert roll["next", "episode", "success_once"].any() and roll["next", "episode", "fail_once"].any()
    _assert_matches_reference(roll)


def test_toy_long_episodes_past_numpy_block():
    # Beyond 128 steps numpy's pairwise sum recurses: still bit for bit, with partial resets around.
    env = TransformedEnv(ToyEnv([140, 7], terminate=False), EpisodeMetrics())
    roll = env.rollout(300, break_when_any_done=False)
    assert roll["next", "episode", "episode_len"].max() == 140
    _assert_matches_reference(roll)


def test_toy_explicit_partial_reset():
    env = TransformedEnv(ToyEnv([10, 10, 10]), EpisodeMetrics())
    td = env.reset()
    for _ in range(3):
        td = step_mdp(env.rand_step(td))
    before = td["episode"].clone()
    assert before["episode_len"].tolist() == [3, 3, 3]
    out = env.reset(td.set("_reset", torch.tensor([[False], [True], [False]])))
    ep = out["episode"]
    assert ep["episode_len"].tolist() == [3, 0, 3]
    assert ep["return"][1] == 0 and ep["return"][0] == before["return"][0]
    assert ep["success_at_end"][1].item() is False
    assert (ep[0] == before[0]).all() and (ep[2] == before[2]).all()
    td = env.rand_step(out)
    assert td["next", "episode", "episode_len"].tolist() == [4, 1, 4]
    assert td["next", "episode", "return"][1] == td["next", "reward"][1, 0]


def test_serial_env_inside_and_on_top_agree():
    """The transform on top of a SerialEnv (batch [3], partial resets) or inside each sub-env (batch [])."""
    ends = [2, 3, 5]
    on_top = TransformedEnv(serial_toy_env(ends, terminate=[True, False, True]), EpisodeMetrics())
    inside = SerialEnv(
        3,
        [
            (lambda e=e, k=k, i=i: TransformedEnv(ToyEnv(e, terminate=k, ids=i), EpisodeMetrics()))
            for i, (e, k) in enumerate(zip(ends, [True, False, True]))
        ],
    )
    try:
        check_env_specs(on_top)
        check_env_specs(inside)
        assert inside.observation_spec["episode", "return"].shape == torch.Size([3])
        roll_top = on_top.rollout(16, break_when_any_done=False)
        roll_in = inside.rollout(16, break_when_any_done=False)
        _assert_matches_reference(roll_top)
        _assert_matches_reference(roll_in)
        assert (roll_top["next", "episode"] == roll_in["next", "episode"]).all()
    finally:
        on_top.close()
        inside.close()


def test_specs_and_no_success_fail():
    env = TransformedEnv(ToyEnv([2, 4]), EpisodeMetrics())
    spec = env.observation_spec["episode"]
    assert spec.shape == torch.Size([2])
    assert {k: spec[k].dtype for k in spec.keys()} == {
        "return": torch.float32,
        "episode_len": torch.int64,
        "reward": torch.float32,
        "success_once": torch.bool,
        "success_at_end": torch.bool,
        "fail_once": torch.bool,
        "fail_at_end": torch.bool,
    }
    assert not any(v.any() for v in env.reset()["episode"].values())  # zeros at reset
    # A task without success / fail: only return, length and mean reward.
    bare = TransformedEnv(ToyEnv([2, 4]), Compose(ExcludeTransform("success", "fail"), EpisodeMetrics()))
    check_env_specs(bare)
    assert set(bare.observation_spec["episode"].keys()) == {"return", "episode_len", "reward"}
    roll = bare.rollout(5, break_when_any_done=False)
    assert set(roll["next", "episode"].keys()) == {"return", "episode_len", "reward"}
    assert EpisodeMetrics is EpisodeMetricsFromTransforms
    assert repr(EpisodeMetrics()) == "EpisodeMetrics()"


def test_running_state_is_declared_in_full_state_spec():
    """As RewardSum's ``episode_reward``: the running metrics are env state (``full_state_spec``)
    and still observations, so TorchRL carries them from one step to the next as inputs."""
    env = TransformedEnv(ToyEnv([3, 5]), EpisodeMetrics())
    assert "episode" in env.full_state_spec.keys()
    assert env.full_state_spec["episode"] == env.observation_spec["episode"]
    check_env_specs(env)
    # A collector's output is what a rollout's is: the reference numbers, root and "next".
    from torchrl.collectors import Collector

    collector = Collector(env, None, frames_per_batch=2 * 12, total_frames=2 * 12)
    batch = next(iter(collector))
    collector.shutdown()
    assert batch.shape == torch.Size([2, 12])
    _assert_matches_reference(batch)


def test_placed_before_action_repeat_it_counts_every_inner_step():
    """Before ActionRepeat, each inner step starts from the state the last one left (the
    parent's ``full_state_spec`` entries are carried over): inner steps are counted and summed."""
    env = TransformedEnv(ToyEnv([9, 2], terminate=False), Compose(EpisodeMetrics(), ActionRepeat(3)))
    check_env_specs(env)
    td = env.reset().set("action", torch.zeros(2, 2))
    nxt = env.step(td)["next"]
    assert nxt["episode", "episode_len"].tolist() == [3, 2]
    assert torch.equal(nxt["episode", "return"], nxt["reward"].squeeze(-1))


def test_error_reward_per_agent():
    env = TransformedEnv(ToyEnv([2, 3], multi_agent=True), EpisodeMetrics())
    with pytest.raises(ValueError, match=r"one reward per env.*\('agents', 'reward'\)"):
        env.rollout(2)


def test_maniskill_specs(envs):
    _, ms_env = envs["PickCube-v1"]
    env = TransformedEnv(ms_env, Compose(CPUUnbatch(), EpisodeMetrics()))
    check_env_specs(env, seed=0)
    assert env.observation_spec["episode", "return"].shape == torch.Size([])
    # Without CPUUnbatch the [1]-batched env gets [1]-shaped metrics.
    batched = TransformedEnv(ms_env, EpisodeMetrics())
    check_env_specs(batched, seed=0)
    td = batched.rollout(3)
    assert td["next", "episode", "episode_len"].tolist() == [[1, 2, 3]]


def test_default_summation_follows_the_sim_not_the_device(envs, monkeypatch):
    """``summation=None``: the CPU sim's numpy sum even where the env's outputs are on a GPU
    (``device="cuda"`` on a CPU-sim env), the running sum on the GPU sim, the device rule where
    the base env cannot be asked (a SerialEnv hands unknown attributes on to its sub-envs).

    Stand-ins, so that it runs without CUDA: the CPU-sim env's device label says ``cuda:0``
    (nothing is allocated there), and ``gpu_sim_enabled`` says True on a CPU env."""
    _, ms_env = envs["PickCube-v1"]
    with monkeypatch.context() as patch:
        patch.setitem(ms_env.__dict__, "_device", torch.device("cuda", 0))
        env = TransformedEnv(ms_env, Compose(CPUUnbatch(), EpisodeMetrics()))
        assert env.device == torch.device("cuda", 0) and not env.base_env.gpu_sim_enabled
        stats = env.transform[-1]._make_stats()
        assert stats.summation == "numpy" and stats.device == torch.device("cuda", 0)
    serial = SerialEnv(1, lambda: TransformedEnv(ManiSkillEnv("PickCube-v1", obs_mode="state"), CPUUnbatch()))
    try:
        serial.reset(seed=0)  # builds the sub-env before the stand-in (CPUUnbatch refuses a GPU sim)
        monkeypatch.setattr(ManiSkillWrapper, "gpu_sim_enabled", property(lambda self: True))
        env = TransformedEnv(ms_env, EpisodeMetrics())
        assert env.device.type == "cpu"
        assert env.transform._make_stats().summation == "running"
        env = TransformedEnv(serial, EpisodeMetrics())
        assert env.device.type == "cpu" and env.base_env.gpu_sim_enabled == [True]
        assert env.transform._make_stats().summation == "numpy"
    finally:
        serial.close()
