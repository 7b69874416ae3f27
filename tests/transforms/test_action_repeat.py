"""ActionRepeat: bit-for-bit equal to ManiSkill's ActionRepeatWrapper, and to a per-env reference.

- real ManiSkill on the CPU sim (PickCube-v1, MS-CartpoleBalance-v1 which fails early,
  a Dict observation mode) against ``mani_skill.utils.wrappers.action_repeat.ActionRepeatWrapper``;
- property tests on ``tests/toy_env.py`` (many envs ending at different inner steps) against a
  straightforward per-env reference, with and without partial steps;
- what TorchRL's ``FrameSkipTransform`` gets wrong on the same scenario;
- inner steps counted per sub-env under ``SerialEnv``; composition with other transforms,
  ``CPUUnbatch``, ``check_env_specs`` and a collector.
"""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper
from tensordict import TensorDictBase
from torchrl.envs import (
    Compose,
    FrameSkipTransform,
    RewardSum,
    SerialEnv,
    StepCounter,
    Transform,
    TransformedEnv,
)
from torchrl.envs.utils import check_env_specs, step_mdp

from maniskill_torchrl import ActionRepeat, ManiSkillEnv
from maniskill_torchrl.transforms import ActionRepeat as ActionRepeatFromTransforms
from support.helpers import assert_same, make_gym_env, random_actions
from support.toy_env import ToyEnv, serial_toy_env, toy_nested, toy_reward


# ============================================================================ helpers
def _clone(x):
    """Deep copy of ManiSkill outputs (its wrapper mutates them in place; elapsed_steps aliases a counter)."""
    if isinstance(x, torch.Tensor):
        return x.clone()
    if isinstance(x, dict):
        return {k: _clone(v) for k, v in x.items()}
    if isinstance(x, tuple):
        return tuple(_clone(v) for v in x)
    return x


def _leaves(d, prefix=()):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, prefix + (k,))
        else:
            yield prefix + (k,), v


def _assert_obs_infos(nxt, obs, info, unbatched: bool) -> None:
    """``nxt`` (a TensorDict) holds ManiSkill's ``obs`` and tensor ``info`` bit for bit."""
    sq = (lambda x: x.squeeze(0)) if unbatched else (lambda x: x)
    if isinstance(obs, dict):
        for key, val in _leaves(obs):
            assert_same(nxt.get(key), sq(val), key)
    else:
        assert_same(nxt.get("observation"), sq(obs), "observation")
    n_info = 0
    for key, val in info.items():
        if isinstance(val, torch.Tensor):
            td_key = key if key in nxt.keys() else f"info_{key}"
            assert_same(nxt.get(td_key), sq(val), key)
            n_info += 1
    assert n_info >= 2  # elapsed_steps and success / fail at least


def _compare_with_maniskill(gym_env, ours, repeat, seeds, actions, unbatched=False) -> list[int]:
    """Steps ManiSkill's wrapper and ``ours`` (a TransformedEnv ending in ActionRepeat) in lockstep,
    across ``len(seeds)`` episode ends; returns the inner steps of each episode."""
    oracle = ActionRepeatWrapper(gym_env, repeat)
    acts = iter(actions)
    lengths = []
    for seed in seeds:
        obs, info = _clone(oracle.reset(seed=seed))
        td = ours.reset(seed=seed)
        _assert_obs_infos(td, obs, info, unbatched)
        while True:
            action = next(acts)
            obs, rew, term, trunc, info = _clone(oracle.step(action.clone()))
            td.set("action", action.squeeze(0) if unbatched else action.clone())
            out = ours.step(td)
            nxt = out.get("next")
            _assert_obs_infos(nxt, obs, info, unbatched)
            # reward [B] -> [B, 1] ([1] unbatched), flags likewise; dtypes must match too
            for key, want in (("reward", rew), ("terminated", term), ("truncated", trunc), ("done", term | trunc)):
                got = nxt.get(key)
                assert got.shape == ((1,) if unbatched else (want.shape[0], 1)), (key, got.shape)
                assert_same(got, want.reshape(got.shape), key)
            if (term | trunc).any():
                lengths.append(int(info["elapsed_steps"].reshape(-1)[0]))
                break
            td = step_mdp(out)
    return lengths


def _batched_action(space: gym.Space, n: int, seed: int) -> list[torch.Tensor]:
    return [a.unsqueeze(0) for a in random_actions(space, n, seed=seed)]


# ============================================================================ ManiSkill oracle
@pytest.fixture(scope="module")
def pick_pair():
    """PickCube-v1 (state obs, 8-step episodes): one env for ManiSkill's wrapper, one for ours."""
    kw = dict(obs_mode="state", max_episode_steps=8)
    return make_gym_env("PickCube-v1", **kw), ManiSkillEnv("PickCube-v1", **kw)


@pytest.fixture(scope="module")
def cartpole_pair():
    """MS-CartpoleBalance-v1: random actions make it fail (terminate) after about 20 steps."""
    kw = dict(obs_mode="state", max_episode_steps=24)
    return make_gym_env("MS-CartpoleBalance-v1", **kw), ManiSkillEnv("MS-CartpoleBalance-v1", **kw)


@pytest.mark.parametrize("repeat", [1, 2, 3, 5])
def test_equals_maniskill_pickcube(pick_pair, repeat):
    gym_env, ours = pick_pair
    actions = _batched_action(gym_env.unwrapped.single_action_space, 40, seed=repeat)
    lengths = _compare_with_maniskill(gym_env, TransformedEnv(ours, ActionRepeat(repeat)), repeat, [11, 12], actions)
    assert lengths == [8, 8]  # truncated mid-repeat for repeat 3 and 5


@pytest.mark.parametrize("repeat", [1, 2, 3, 5])
def test_equals_maniskill_cartpole_fail(cartpole_pair, repeat):
    gym_env, ours = cartpole_pair
    actions = _batched_action(gym_env.unwrapped.single_action_space, 100, seed=11)
    lengths = _compare_with_maniskill(gym_env, TransformedEnv(ours, ActionRepeat(repeat)), repeat, [3, 4, 5], actions)
    # Episodes end by `fail` before the time limit, some mid-repeat (not a multiple of repeat).
    assert max(lengths) < 24
    if repeat > 1:
        assert any(n % repeat for n in lengths)


@pytest.mark.parametrize("repeat", [2, 3])
def test_equals_maniskill_dict_obs(repeat):
    kw = dict(obs_mode="state_dict", max_episode_steps=7)
    gym_env, ours = make_gym_env("PickCube-v1", **kw), ManiSkillEnv("PickCube-v1", **kw)
    assert isinstance(gym_env.observation_space, gym.spaces.Dict)
    actions = _batched_action(gym_env.unwrapped.single_action_space, 30, seed=7)
    env = TransformedEnv(ours, ActionRepeat(repeat))
    assert _compare_with_maniskill(gym_env, env, repeat, [21, 22], actions) == [7, 7]
    gym_env.close()
    ours.close()


def test_equals_maniskill_with_cpu_unbatch(cartpole_pair):
    """CPUUnbatch before ActionRepeat: its action inverse (an unsqueeze) is applied once per inner step."""
    from maniskill_torchrl.transforms import CPUUnbatch

    gym_env, ours = cartpole_pair
    env = TransformedEnv(ours, Compose(CPUUnbatch(), ActionRepeat(3)))
    assert env.batch_size == torch.Size([])
    actions = _batched_action(gym_env.unwrapped.single_action_space, 60, seed=99)
    lengths = _compare_with_maniskill(gym_env, env, 3, [8, 9], actions, unbatched=True)
    assert len(lengths) == 2


# ============================================================================ per-env reference
def _reference_step(state, ends, terminate, repeat, action, partial, multi_agent, done_once=False):
    """One outer step, env by env, written plainly: returns the expected "next" entries.

    ``state`` holds per env ``t`` (steps since reset), ``count`` (real steps so far, the toy's
    counter) and is updated in place.
    """
    n = len(ends)
    rows, taken = [], []

    def ended(i, t):  # sticky, or (done_once) an event at the end step only
        return t == ends[i] if done_once else t >= ends[i]

    for i in range(n):
        t0 = state["t"][i]
        k, ret, agents_ret = 0, None, [None, None]
        while k < repeat:
            k += 1
            t = t0 + k
            r = toy_reward(i, t)
            ret = r if ret is None else ret + r
            for a in range(2):
                ra = r * (a + 1)
                agents_ret[a] = ra if agents_ret[a] is None else agents_ret[a] + ra
            if ended(i, t):
                break
        taken.append(k)
        t = t0 + k
        done = ended(i, t)
        term, trunc = done and terminate[i], done and not terminate[i]
        row = {
            "observation": torch.tensor([float(t), float(i), float(action[i, 0])]),
            ("nested", "deep", "x"): toy_nested(i, t),
            ("nested", "count"): torch.tensor(state["count"][i] + k),
            "elapsed_steps": torch.tensor(t),
            "success": torch.tensor(t % 3 == 2),
            "fail": torch.tensor(term),
            "done": torch.tensor([done]),
            "terminated": torch.tensor([term]),
            "truncated": torch.tensor([trunc]),
        }
        if multi_agent:
            row[("agents", "reward")] = torch.stack(agents_ret).reshape(2, 1)
            for key, flag in (("done", done), ("terminated", term), ("truncated", trunc)):
                row[("agents", key)] = torch.full((2, 1), flag)
        else:
            row["reward"] = ret.reshape(1)
        rows.append(row)
    # Without partial steps every env is stepped as long as any env runs.
    most = max(taken)
    for i in range(n):
        real = taken[i] if partial else most
        state["t"][i] += real
        state["count"][i] += real
    return {key: torch.stack([row[key] for row in rows]) for key in rows[0]}, taken


def _step_counts(env) -> list[int]:
    base = env.base_env
    if isinstance(base, SerialEnv):
        return [int(e.step_count) for e in base._envs]
    return base.step_count.tolist()


@st.composite
def _scenarios(draw):
    n = draw(st.integers(1, 5))
    return dict(
        ends=draw(st.lists(st.integers(1, 9), min_size=n, max_size=n)),
        terminate=draw(st.lists(st.booleans(), min_size=n, max_size=n)),
        repeat=draw(st.integers(1, 6)),
        outer=draw(st.integers(1, 4)),
        auto_reset=draw(st.booleans()),
        multi_agent=draw(st.booleans()),
        done_once=draw(st.booleans()),
        seed=draw(st.integers(0, 2**16)),
    )


@pytest.mark.parametrize("partial", [False, True], ids=["one-batched-env", "SerialEnv"])
@settings(max_examples=30, deadline=None, derandomize=True, database=None)
@given(sc=_scenarios())
def test_matches_per_env_reference(partial, sc):
    ends, terminate, repeat = sc["ends"], sc["terminate"], sc["repeat"]
    n = len(ends)
    if partial:
        base = serial_toy_env(ends, terminate, multi_agent=sc["multi_agent"], done_once=sc["done_once"])
    else:
        base = ToyEnv(ends, terminate=terminate, multi_agent=sc["multi_agent"], done_once=sc["done_once"])
    env = TransformedEnv(base, ActionRepeat(repeat))
    g = torch.Generator().manual_seed(sc["seed"])
    state = {"t": [0] * n, "count": [0] * n}
    total_taken = [0] * n
    td = env.reset()
    for _ in range(sc["outer"]):
        action = torch.rand(n, 2, generator=g) * 2 - 1
        td.set("action", action)
        expected, taken = _reference_step(
            state, ends, terminate, repeat, action, partial, sc["multi_agent"], sc["done_once"]
        )
        if sc["auto_reset"]:
            out, td = env.step_and_maybe_reset(td)
            for i in range(n):
                if expected["done"][i]:
                    state["t"][i] = 0
        else:
            out = env.step(td)
            td = step_mdp(out)
        nxt = out.get("next")
        for key, want in expected.items():
            assert_same(nxt.get(key), want, key)
        total_taken = [a + b for a, b in zip(total_taken, taken)]
        # Early stop and skipping, read on the toy's own counters.
        assert _step_counts(env) == state["count"]
    if partial:  # each env was stepped exactly as often as it really took steps
        assert state["count"] == total_taken


# ============================================================================ FrameSkipTransform
class _AddOneToAction(Transform):
    """An inverse transform: the env receives ``action + 1``."""

    def __init__(self):
        super().__init__(in_keys_inv=["action"], out_keys_inv=["action"])

    def _inv_apply_transform(self, action):
        return action + 1


def test_frameskip_gets_wrong_what_action_repeat_gets_right():
    """Env 0 terminates at inner step 2 of 3 (an event, not sticky); env 1 runs on.

    FrameSkipTransform adds env 0's third reward (after its end), reports the third step's
    flags (its termination is lost) and applies the earlier inverse transform twice to the
    action of its extra steps. ActionRepeat does none of that.
    """
    ends, repeat = [2, 5], 3
    action = torch.tensor([[0.25, 0.0], [-0.5, 0.0]])

    def run(repeat_transform):
        env = TransformedEnv(ToyEnv(ends, done_once=True), Compose(_AddOneToAction(), repeat_transform))
        td = env.reset()
        return env.step(td.set("action", action.clone()))["next"]

    fs, ar = run(FrameSkipTransform(repeat)), run(ActionRepeat(repeat))
    right_env0 = toy_reward(0, 1) + toy_reward(0, 2)
    past_end_env0 = right_env0 + toy_reward(0, 3)
    assert ar["reward"][0, 0] == right_env0 and ar["terminated"][0, 0] and ar["elapsed_steps"][0] == 2
    assert fs["reward"][0, 0] == past_end_env0  # reward from after the episode's end
    assert not fs["terminated"][0, 0] and not fs["done"][0, 0]  # the termination is lost
    # Env 1 ran all three inner steps in both; the action it saw:
    assert ar["observation"][1, 2] == action[1, 0] + 1
    assert fs["observation"][1, 2] == action[1, 0] + 2  # inverse transform applied twice
    assert ar["reward"][1, 0] == toy_reward(1, 1) + toy_reward(1, 2) + toy_reward(1, 3)


def test_inverse_transforms_after_it_apply_once():
    env = TransformedEnv(ToyEnv([9]), Compose(ActionRepeat(3), _AddOneToAction()))
    td = env.reset().set("action", torch.tensor([[0.5, 0.0]]))
    nxt = env.step(td)["next"]
    assert nxt["observation"][0, 2] == 1.5 and nxt["elapsed_steps"][0] == 3


# ============================================================================ partial steps, counted
def test_serial_env_steps_an_ended_env_only_until_its_end():
    ends, repeat = [1, 2, 5, 9], 4
    env = TransformedEnv(serial_toy_env(ends), ActionRepeat(repeat))
    td = env.reset().set("action", torch.zeros(4, 2))
    nxt = env.step(td)["next"]
    assert _step_counts(env) == [1, 2, 4, 4]
    assert nxt["elapsed_steps"].tolist() == [1, 2, 4, 4]
    assert nxt["done"].squeeze(-1).tolist() == [True, True, False, False]
    # One batched simulator cannot skip envs: all are stepped, results of ended ones discarded.
    env = TransformedEnv(ToyEnv(ends), ActionRepeat(repeat))
    td = env.reset().set("action", torch.zeros(4, 2))
    nxt = env.step(td)["next"]
    assert _step_counts(env) == [4, 4, 4, 4]
    assert nxt["elapsed_steps"].tolist() == [1, 2, 4, 4]
    # Stop early when all are done: 3 inner steps of 8.
    env = TransformedEnv(serial_toy_env([1, 3]), ActionRepeat(8))
    env.step(env.reset().set("action", torch.zeros(2, 2)))
    assert _step_counts(env) == [1, 3]
    env = TransformedEnv(ToyEnv([1, 3]), ActionRepeat(8))
    env.step(env.reset().set("action", torch.zeros(2, 2)))
    assert _step_counts(env) == [3, 3]


def test_serial_env_of_maniskill_skips_ended_envs():
    """SerialEnv(2) of MS-CartpoleBalance-v1 with repeat 8: an env that fails mid-repeat is not
    stepped again (ManiSkill's own elapsed_steps counter stops where the reported one does)."""
    from maniskill_torchrl.transforms import CPUUnbatch

    def make():
        return TransformedEnv(ManiSkillEnv("MS-CartpoleBalance-v1", obs_mode="state"), CPUUnbatch())

    serial = SerialEnv(2, make)
    env = TransformedEnv(serial, ActionRepeat(8))
    check_env_specs(env, seed=0)
    td = env.reset(seed=5)
    actions = random_actions(gym.spaces.Box(-1, 1, (2, 1)), 20, seed=3)
    saw_skip = False
    for action in actions:
        out = env.step(td.set("action", action))
        nxt = out["next"]
        inner = [int(e.base_env.unwrapped.elapsed_steps[0]) for e in serial._envs]
        assert nxt["elapsed_steps"].tolist() == inner  # no step past an env's end
        done = nxt["done"].squeeze(-1)
        # One env ended before the other: stepping both would have left equal counters.
        saw_skip = saw_skip or inner[0] != inner[1]
        if done.all():
            break
        td = step_mdp(out)
    assert saw_skip
    serial.close()


# ============================================================================ composition
def test_composes_with_stepcounter_rewardsum_and_check_env_specs():
    ends = [2, 4, 7]
    inner = Compose(StepCounter(), ActionRepeat(3), StepCounter(step_count_key="outer_count"), RewardSum())
    for base in (ToyEnv(ends), serial_toy_env(ends)):
        env = TransformedEnv(base, inner.clone())
        check_env_specs(env)
        td = env.reset().set("action", torch.zeros(3, 2))
        out = env.step(td)
        nxt = out["next"]
        # StepCounter before ActionRepeat counts inner steps, the one after counts outer steps.
        assert nxt["step_count"].squeeze(-1).tolist() == [2, 3, 3]
        assert nxt["outer_count"].squeeze(-1).tolist() == [1, 1, 1]
        assert torch.equal(nxt["episode_reward"], nxt["reward"])
        td = step_mdp(out).set("action", torch.zeros(3, 2))
        nxt2 = env.step(td)["next"]
        assert nxt2["step_count"].squeeze(-1).tolist()[1:] == [4, 6]
        assert torch.equal(nxt2["episode_reward"][1:], nxt["reward"][1:] + nxt2["reward"][1:])
    # A StepCounter time limit before it truncates mid-repeat: the env stops there.
    env = TransformedEnv(serial_toy_env([20, 20]), Compose(StepCounter(max_steps=4), ActionRepeat(3)))
    td = env.reset().set("action", torch.zeros(2, 2))
    out = env.step(td)
    nxt = env.step(step_mdp(out).set("action", torch.zeros(2, 2)))["next"]
    assert nxt["step_count"].squeeze(-1).tolist() == [4, 4]
    assert nxt["truncated"].all() and _step_counts(env) == [4, 4]


def test_nested_repeats_and_repeat_one():
    env = TransformedEnv(serial_toy_env([5, 20]), Compose(ActionRepeat(3), ActionRepeat(2)))
    nxt = env.step(env.reset().set("action", torch.zeros(2, 2)))["next"]
    assert nxt["elapsed_steps"].tolist() == [5, 6] and _step_counts(env) == [5, 6]
    env = TransformedEnv(ToyEnv([1, 2]), ActionRepeat(1))
    plain = ToyEnv([1, 2])
    a = env.step(env.reset().set("action", torch.zeros(2, 2)))["next"]
    b = plain.step(plain.reset().set("action", torch.zeros(2, 2)))["next"]
    assert (a == b).all()


def test_collector_resets_finished_envs():
    from torchrl.collectors import Collector

    ends, repeat = [2, 3, 7], 3
    env = TransformedEnv(serial_toy_env(ends), ActionRepeat(repeat))
    collector = Collector(env, None, frames_per_batch=3 * 6, total_frames=3 * 6)
    batch = next(iter(collector))
    collector.shutdown()
    for i, end in enumerate(ends):
        # episodes of `end` inner steps split into outer steps of at most `repeat`
        one_episode = []
        t = 0
        while t < end:
            t = min(t + repeat, end)
            one_episode.append(t)
        want = (one_episode * 6)[:6]
        assert batch["next", "elapsed_steps"][i].tolist() == want
        assert batch["next", "done"][i].squeeze(-1).tolist() == [e == end for e in want]


# ============================================================================ errors, exports
@pytest.mark.parametrize(
    ("bad", "error"),
    [(0, ValueError), (-1, ValueError), (2.5, TypeError), (True, TypeError), ("3", TypeError), (None, TypeError)],
)
def test_bad_repeat(bad, error):
    # One check for the transform and the gym shim: ValueError for a bad value, TypeError for a non-int.
    with pytest.raises(error, match=r"int >= 1.*1 means no repeat"):
        ActionRepeat(bad)


def test_exported_and_repr():
    assert ActionRepeat is ActionRepeatFromTransforms
    assert repr(ActionRepeat(4)) == "ActionRepeat(repeat=4)"


def test_forward_outside_an_env_raises_with_the_fix():
    """Called on a tensordict alone it has no env to step: it says so, as TorchRL's
    FrameSkipTransform does, instead of returning the data unchanged."""
    td = ToyEnv([3]).reset().set("action", torch.zeros(1, 2))
    with pytest.raises(RuntimeError, match=r"inside a TransformedEnv.*FrameSkipTransform"):
        ActionRepeat(2)(td)
    with pytest.raises(RuntimeError, match=r"inside a TransformedEnv"):
        Compose(ActionRepeat(2)).forward(td)


def test_keeps_nothing_from_its_inverse_pass():
    """The inner loop reads what it needs from the ``tensordict`` that ``_step`` is given: an
    inverse pass alone (a replay buffer's ``inv``, say) leaves no data on the transform, and the
    earlier transform's inverse still reaches every inner step once."""
    env = TransformedEnv(ToyEnv([9, 2]), Compose(_AddOneToAction(), ActionRepeat(3)))
    repeat = env.transform[1]
    td = env.reset().set("action", torch.tensor([[0.5, 0.0], [0.25, 0.0]]))
    env.transform.inv(td.clone())
    held = [name for name, value in vars(repeat).items() if isinstance(value, TensorDictBase)]
    assert not held, held
    nxt = env.step(td)["next"]
    assert nxt["elapsed_steps"].tolist() == [3, 2]
    assert nxt["observation"][:, 2].tolist() == [1.5, 1.25]  # action + 1, not + 2
    assert not [name for name, value in vars(repeat).items() if isinstance(value, TensorDictBase)]
