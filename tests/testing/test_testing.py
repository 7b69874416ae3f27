"""``maniskill_torchrl.testing`` as a user calls it, and the one reward rule it checks: TorchRL's
float32 reward for every task (bool and float64 rewards cast).

- ``assert_tensordict_equal``: bit-exact, and its error names the first differing key path;
- ``check_maniskill_env``: passes on real tasks and on a task registered here (a ``BaseEnv``
  subclass with a bool / float64 reward, as users write their own), and fails, saying where,
  when the library's output is wrong;
- the reward rule on tasks that report bool (DrawTriangle-v1) and float64 (RotateValveLevel0-v1)
  rewards: the batched CPU env's worker-side repeat equals the TorchRL ActionRepeat loop.
"""

from __future__ import annotations

import io
import time

import pytest
import torch
from mani_skill.envs.tasks.tabletop.push_cube import PushCubeEnv
from mani_skill.utils.registration import register_env
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from maniskill_torchrl import ActionRepeat, EpisodeMetrics, ManiSkillEnv, ManiSkillWrapper
from maniskill_torchrl.testing import assert_tensordict_equal, check_maniskill_env


# ----------------------------------------------------------------------------- a user's own tasks
@register_env("TestBoolRewardPushCube-v1", max_episode_steps=8)
class BoolRewardPushCube(PushCubeEnv):
    """PushCube with a bool reward (success), as a user might write a sparse task."""

    def compute_dense_reward(self, obs, action, info):
        return info["success"]

    def compute_normalized_dense_reward(self, obs, action, info):
        return info["success"]


@register_env("TestFloat64RewardPushCube-v1", max_episode_steps=8)
class Float64RewardPushCube(PushCubeEnv):
    """PushCube with its dense reward in float64."""

    def compute_normalized_dense_reward(self, obs, action, info):
        return super().compute_normalized_dense_reward(obs, action, info).to(torch.float64) / 3


# ----------------------------------------------------------------------------- assert_tensordict_equal
def _td() -> TensorDict:
    return TensorDict(
        {
            "obs": torch.arange(6.0).reshape(2, 3),
            ("next", "reward"): torch.ones(2, 1),
            "flag": torch.tensor([1, 0]).bool(),
        },
        batch_size=[2],
    )


def test_assert_tensordict_equal_passes_on_equal_bits():
    a = _td()
    assert_tensordict_equal(a, a.clone())
    nan = TensorDict({"x": torch.tensor([float("nan")])}, [1])
    assert_tensordict_equal(nan, nan.clone())  # the same NaN bits


@pytest.mark.parametrize(
    "change, message",
    [
        (
            lambda td: td.set(("next", "reward"), torch.tensor([[1.0], [-2.0]])),
            r"\('next', 'reward'\): 1 of 2 values.*\(1, 0\): -2.0 != expected 1.0",
        ),
        (  # 0.0 and -0.0 differ
            lambda td: td.set("obs", torch.where(td["obs"] == 0, -td["obs"], td["obs"])),
            r"'obs': 1 of 6 values differ in their bits, first at index \(0, 0\): -0.0 != expected 0.0",
        ),
        (lambda td: td.set("obs", td["obs"].double()), r"'obs': dtype torch.float64 != expected torch.float32"),
        (lambda td: td.set("extra", torch.zeros(2)), r"keys differ: missing \[\], unexpected \['extra'\]"),
        (lambda td: td.exclude("flag"), r"keys differ: missing \['flag'\]"),
        (lambda td: td.set("flag", ~td["flag"]), r"'flag': 2 of 2 values differ.*\(0,\): False != expected True"),
    ],
)
def test_assert_tensordict_equal_names_the_first_difference(change, message):
    expected = _td()
    expected["obs"][0, 0] = 0.0
    actual = change(expected.clone())
    with pytest.raises(AssertionError, match=message):
        assert_tensordict_equal(actual, expected)


def test_assert_tensordict_equal_batch_size_and_types():
    with pytest.raises(AssertionError, match=r"batch size \[2, 1\] != expected \[2\]"):
        assert_tensordict_equal(_td().unsqueeze(-1), _td())
    with pytest.raises(TypeError, match="compares TensorDicts; actual is a dict"):
        assert_tensordict_equal({"a": 1}, _td())


# ----------------------------------------------------------------------------- check_maniskill_env
@pytest.mark.parametrize(
    "env_id", ["PickCube-v1", "TestBoolRewardPushCube-v1", "TestFloat64RewardPushCube-v1", "RotateValveLevel0-v1"]
)
def test_check_maniskill_env_passes(env_id):
    check_maniskill_env(env_id, steps=20, seed=3, obs_mode="state", max_episode_steps=8)


def test_check_maniskill_env_fails_where_the_library_is_wrong(monkeypatch):
    step = ManiSkillWrapper._step

    def off_by_one(self, tensordict):
        out = step(self, tensordict)
        if int(self.unwrapped.elapsed_steps[0]) == 3:
            out["reward"] = out["reward"] + 1
        return out

    monkeypatch.setattr(ManiSkillWrapper, "_step", off_by_one)
    with pytest.raises(AssertionError, match=r"check_maniskill_env\('PickCube-v1', num_envs=1\), step 2: 'reward'"):
        check_maniskill_env("PickCube-v1", steps=5, obs_mode="state")


# ----------------------------------------------------------------------------- the reward rule
@pytest.mark.parametrize("env_id", ["DrawTriangle-v1", "RotateValveLevel0-v1", "TestBoolRewardPushCube-v1"])
def test_rewards_are_float32_on_every_path(env_id):
    kwargs = dict(obs_mode="state", max_episode_steps=7)
    single = TransformedEnv(ManiSkillEnv(env_id, **kwargs), EpisodeMetrics())
    td = single.rollout(9, break_when_any_done=False)
    assert td["next", "reward"].dtype == torch.float32
    assert td["next", "episode", "return"].dtype == torch.float32
    single.close()
    if env_id.startswith("Test"):  # registered in this process only: no workers
        return
    # The batched CPU env's sub-envs repeat in their own processes; the TorchRL loop repeats a
    # single env: the same float32 sums (sub-env i seeded s + i).
    batched = TransformedEnv(ManiSkillEnv(env_id, num_envs=2, sim_backend="cpu", **kwargs), ActionRepeat(2))
    singles = [TransformedEnv(ManiSkillEnv(env_id, **kwargs), ActionRepeat(2)) for _ in range(2)]
    try:
        g = torch.Generator().manual_seed(0)
        actions = [torch.rand((2, *batched.action_spec.shape[1:]), generator=g) * 2 - 1 for _ in range(5)]
        td = batched.reset(seed=10)
        tds = [s.reset(seed=10 + i) for i, s in enumerate(singles)]
        for a in actions:
            td = batched.step(td.set("action", a))
            for i, s in enumerate(singles):
                one = s.step(tds[i].set("action", a[i : i + 1]))
                assert torch.equal(td["next", "reward"][i], one["next", "reward"][0]), (env_id, i)
                tds[i] = one["next"]
            td = td["next"]
        assert td["reward"].dtype == torch.float32
    finally:
        batched.close()
        for s in singles:
            s.close()


# ----------------------------------------------------------------------------- missing assets
@pytest.mark.parametrize(
    "env_id, num_envs, names",
    [
        ("PickSingleYCB-v1", 1, ["PickSingleYCB-v1: ycb"]),
        ("PickSingleYCB-v1", 2, ["PickSingleYCB-v1: ycb"]),  # before any worker starts
        ("AnymalC-Reach-v1", 1, ["anymal_c: anymal_c"]),  # a robot's assets
    ],
)
def test_missing_assets_raise_a_clear_error_without_a_prompt(env_id, num_envs, names):
    t0 = time.perf_counter()
    with pytest.raises(FileNotFoundError) as info:
        ManiSkillEnv(env_id, num_envs=num_envs, sim_backend="cpu", obs_mode="state")
    assert time.perf_counter() - t0 < 5
    message = str(info.value)
    assert f"ManiSkill task {env_id!r} needs assets that are not downloaded" in message
    for name in names:
        assert name in message
    group = names[0].split(":")[0]
    assert f"python -m mani_skill.utils.download_asset {group}" in message


def test_manikill_prompt_becomes_an_error(monkeypatch):
    """An asset ManiSkill did not declare for the task: its (y|n) prompt raises instead of reading stdin."""
    import maniskill_torchrl.envs.engine_env as maniskill_env_module

    monkeypatch.setattr(maniskill_env_module, "check_assets", lambda *args, **kwargs: None)
    monkeypatch.setattr("sys.stdin", io.StringIO(""))  # an answer would be read from here
    with pytest.raises(
        FileNotFoundError,
        match=r"'AnymalC-Reach-v1'.*\(anymal_c: Robot anymal_c\).*`python -m mani_skill.utils.download_asset anymal_c`",
    ):
        ManiSkillEnv("AnymalC-Reach-v1", obs_mode="state")
