"""``ManiSkillEnv(env_id, batch_size=[])``: one ManiSkill env as an unbatched TorchRL env.

Oracles: ``TransformedEnv(ManiSkillEnv(env_id), CPUUnbatch())`` (itself checked against ManiSkill
in ``test_cpu_unbatch.py``) and a raw ManiSkill loop. Every comparison seeds every reset.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from maniskill_torchrl import ActionRepeat, CPUUnbatch, ManiSkillEnv, ManiSkillWrapper
from support.helpers import close_envs, make_gym_env, random_actions

MAX_STEPS = 5  # short episodes: every rollout below crosses an automatic reset


def _pair(env_id: str, **kwargs) -> tuple[ManiSkillEnv, TransformedEnv]:
    """(the unbatched env, the CPUUnbatch oracle), two ManiSkill envs made alike."""
    return (
        ManiSkillEnv(env_id, batch_size=[], **kwargs),
        TransformedEnv(ManiSkillEnv(env_id, **kwargs), CPUUnbatch()),
    )


def _as_action(a) -> torch.Tensor | TensorDict:
    return TensorDict(a, batch_size=[]) if isinstance(a, dict) else a


def _run(env, actions: list, seed: int) -> TensorDictBase:
    """Seeded reset, then ``step_and_maybe_reset`` with ``actions``: the stacked steps."""
    td = env.reset(seed=seed)
    steps = []
    for a in actions:
        td["action"] = _as_action(a)
        out, td = env.step_and_maybe_reset(td)
        steps.append(out.clone())
    return torch.stack(steps)


def _assert_equal_tds(got: TensorDictBase, want: TensorDictBase) -> None:
    got_keys = set(got.keys(True, True))
    assert got_keys == set(want.keys(True, True))
    assert len(got_keys) > 5  # observations, action, flags, infos: never an empty comparison
    assert got.batch_size == want.batch_size
    for key in got_keys:
        g, w = got[key], want[key]
        assert g.dtype == w.dtype and g.shape == w.shape, key
        assert torch.equal(g, w), key


@pytest.mark.parametrize(
    ("env_id", "obs_mode", "inference_mode"),
    [
        ("PickCube-v1", "state", None),
        ("PickCube-v1", "state", False),
        ("PickCube-v1", "state_dict", None),
        ("TwoRobotPickCube-v1", "state_dict", None),  # a Dict action space
    ],
)
def test_same_specs_and_steps_as_cpu_unbatch(env_id: str, obs_mode: str, inference_mode: bool | None) -> None:
    env, oracle = _pair(env_id, obs_mode=obs_mode, max_episode_steps=MAX_STEPS, inference_mode=inference_mode)
    try:
        assert env.batch_size == torch.Size([]) and env.inference_mode == oracle.base_env.inference_mode
        assert env.output_spec == oracle.output_spec
        assert env.input_spec == oracle.input_spec
        space = env.unwrapped.single_action_space
        actions = random_actions(space, 2 * MAX_STEPS + 2, seed=3)
        got, want = _run(env, actions, seed=9), _run(oracle, actions, seed=9)
        assert got["next", "done"].sum() == 2  # two episodes ended, two automatic resets
        _assert_equal_tds(got, want)
        check_env_specs(env, seed=0)
    finally:
        close_envs([env, oracle])


def _raw_entries(obs: Any, info: dict, frame: torch.Tensor | None) -> dict:
    """ManiSkill's ``[1, ...]`` outputs without the env dim, keyed as the unbatched env keys them
    (Box obs: ``"observation"``; Dict obs: nested key tuples; tensor infos: their names)."""

    def flat(d: dict, prefix: tuple = ()) -> dict:
        out = {}
        for k, v in d.items():
            out.update(flat(v, prefix + (k,)) if isinstance(v, dict) else {prefix + (k,): v[0]})
        return out

    out = flat(obs) if isinstance(obs, dict) else {("observation",): obs[0]}
    out.update({(k,): v[0] for k, v in info.items() if isinstance(v, torch.Tensor) and v.ndim >= 1})
    if frame is not None:
        out[("pixels",)] = frame[0]
    return out


def _assert_matches_raw(td: TensorDictBase, raw: dict, what: str) -> None:
    td_keys = {k if isinstance(k, tuple) else (k,) for k in td.keys(True, True)}
    flags = {("reward",), ("terminated",), ("truncated",), ("done",), ("action",)}
    assert td_keys - flags == set(raw), what  # every entry is checked, and nothing is missing
    for key, want in raw.items():
        got = td[key]
        want = want.to(got.device)  # on a CUDA machine, raw ManiSkill's pictures are on the GPU
        assert got.dtype == want.dtype and got.shape == want.shape, (what, key)
        assert torch.equal(got, want), (what, key)


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [
        ("PickCube-v1", {"obs_mode": "state"}),  # inference mode (the default)
        ("PickCube-v1", {"obs_mode": "state", "inference_mode": False}),
        ("PickCube-v1", {"obs_mode": "state_dict"}),
        ("TwoRobotPickCube-v1", {"obs_mode": "state_dict"}),  # a Dict action space
        pytest.param("PickCube-v1", {"obs_mode": "rgb", "from_pixels": True}, marks=pytest.mark.pictures),
    ],
)
def test_same_as_raw_maniskill_loop(env_id: str, kwargs: dict) -> None:
    """Every entry, reset and step, against a raw ManiSkill env stepped with the same actions
    (made with a batch of one), across two episodes with explicitly seeded resets."""
    raw_kwargs = {k: v for k, v in kwargs.items() if k not in ("inference_mode", "from_pixels")}
    if kwargs.get("from_pixels"):
        raw_kwargs["render_mode"] = "rgb_array"
    env = ManiSkillEnv(env_id, batch_size=[], max_episode_steps=MAX_STEPS, **kwargs)
    raw = make_gym_env(env_id, max_episode_steps=MAX_STEPS, **raw_kwargs)
    render = raw.render if kwargs.get("from_pixels") else lambda: None
    try:
        actions = random_actions(raw.unwrapped.single_action_space, MAX_STEPS + 2, seed=1)
        seeds = iter([4, 17])
        ended = 0
        td = None
        for t, a in enumerate(actions):
            if td is None or td["done"].item():
                seed = next(seeds)
                td = env.reset(seed=seed)
                obs, info = raw.reset(seed=seed)
                _assert_matches_raw(td, _raw_entries(obs, info, render()), f"reset before step {t}")
            td = env.step(td.set("action", _as_action(a)))
            batched = {k: v.unsqueeze(0) for k, v in a.items()} if isinstance(a, dict) else a.unsqueeze(0)
            obs, reward, terminated, truncated, info = raw.step(batched)
            nxt = td["next"]
            _assert_matches_raw(nxt, _raw_entries(obs, info, render()), f"step {t}")
            assert nxt["reward"].shape == nxt["done"].shape == (1,)
            assert torch.equal(nxt["reward"], reward)
            assert torch.equal(nxt["terminated"], terminated) and torch.equal(nxt["truncated"], truncated)
            assert torch.equal(nxt["done"], terminated | truncated)
            ended += int(nxt["done"].item())
            td = nxt.clone()
        assert ended >= 1  # the second episode started from a seeded reset
    finally:
        close_envs([env, raw])


@pytest.mark.pictures
def test_pixels_and_rgb_observations() -> None:
    env, oracle = _pair("PickCube-v1", obs_mode="rgb", from_pixels=True, max_episode_steps=MAX_STEPS)
    try:
        assert env.output_spec == oracle.output_spec
        assert env.observation_spec["pixels"].shape[-1] == 3 and env.observation_spec["pixels"].ndim == 3
        actions = random_actions(env.unwrapped.single_action_space, 2, seed=2)
        got, want = _run(env, actions, seed=6), _run(oracle, actions, seed=6)
        assert got["next", "pixels"].dtype == torch.uint8 and got["next", "pixels"].any()
        _assert_equal_tds(got, want)
    finally:
        close_envs([env, oracle])


def test_reset_mask() -> None:
    env = ManiSkillEnv("PickCube-v1", batch_size=[], obs_mode="state")
    try:
        td = env.reset(TensorDict(_reset=torch.tensor([True])), seed=0)
        assert td["observation"].shape == (42,) and td["done"].shape == (1,)
        td = env.rand_step(td)
        # A no-op reset ("_reset" False) changes nothing and keeps the unbatched shapes.
        before = td["next"].clone()
        out = env.reset(td["next"].clone().set("_reset", torch.tensor([False])))
        assert out.batch_size == () and out["done"].shape == (1,)
        assert torch.equal(out["observation"], before["observation"])
    finally:
        env.close()


def test_serial_env_with_action_repeat_equals_cpu_unbatch_workers() -> None:
    """Stacked by SerialEnv under ActionRepeat (partial steps through "_step"): same data."""

    def stack(unbatched: bool):
        def make():
            if unbatched:
                return ManiSkillEnv("PickCube-v1", batch_size=[], obs_mode="state", max_episode_steps=MAX_STEPS)
            return TransformedEnv(
                ManiSkillEnv("PickCube-v1", obs_mode="state", max_episode_steps=MAX_STEPS), CPUUnbatch()
            )

        return TransformedEnv(SerialEnv(2, make), ActionRepeat(2))

    env, oracle = stack(True), stack(False)
    try:
        assert env.batch_size == oracle.batch_size == torch.Size([2])
        g = torch.Generator().manual_seed(0)
        actions = [torch.rand(2, 8, generator=g) * 2 - 1 for _ in range(MAX_STEPS)]
        got, want = _run(env, actions, seed=3), _run(oracle, actions, seed=3)
        assert got["next", "done"].any()
        _assert_equal_tds(got, want)
    finally:
        close_envs([env, oracle])


def test_transform_stack_equals_cpu_unbatch_stack() -> None:
    """make_env's worker stack (IgnoreTerminations, ActionRepeat(3), EpisodeMetrics) on the
    unbatched env gives the data of the same stack behind CPUUnbatch."""
    from torchrl.envs import Compose

    from maniskill_torchrl import EpisodeMetrics, IgnoreTerminations
    from maniskill_torchrl.pipeline import make_env

    kwargs = {"obs_mode": "state", "max_episode_steps": 2 * MAX_STEPS}
    env = make_env("PickCube-v1", repeat=3, ignore_terminations=True, **kwargs)
    oracle = TransformedEnv(
        ManiSkillEnv("PickCube-v1", **kwargs),
        Compose(CPUUnbatch(), IgnoreTerminations(), ActionRepeat(3), EpisodeMetrics()),
    )
    try:
        assert env.base_env.batch_size == () and env.output_spec == oracle.output_spec
        actions = random_actions(env.base_env.unwrapped.single_action_space, 2 * MAX_STEPS, seed=8)
        got, want = _run(env, actions, seed=2), _run(oracle, actions, seed=2)
        assert got["next", "done"].any() and got["next", "episode", "episode_len"].max() > 1
        _assert_equal_tds(got, want)
    finally:
        close_envs([env, oracle])


def test_wrapper_and_default_batch_size() -> None:
    env = ManiSkillWrapper(make_gym_env("PickCube-v1", obs_mode="state"), batch_size=())
    batched = ManiSkillEnv("PickCube-v1", obs_mode="state", batch_size=[1])  # the default, spelt out
    try:
        assert env.batch_size == () and env.action_spec.shape == (8,)
        assert batched.batch_size == (1,) and batched.action_spec.shape == (1, 8)
        assert "batch_size=[]" in repr(env)
    finally:
        close_envs([env, batched])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_envs": 2, "batch_size": []}, r"batch_size=\[\] does not fit .* num_envs=2.*with num_envs=1"),
        ({"batch_size": [3]}, r"batch_size=\[3\] does not fit .* num_envs=1"),
        ({"batch_size": 1}, r"batch_size=1 does not fit"),
    ],
)
def test_bad_batch_size_raises_before_building(kwargs: dict, match: str, monkeypatch) -> None:
    def no_env(*args, **kw):
        raise AssertionError("an env was built before the batch size was checked")

    monkeypatch.setattr(gym, "make", no_env)
    monkeypatch.setattr("maniskill_torchrl.envs.engine_env.CPUVectorEnv", no_env)
    with pytest.raises(ValueError, match=match):
        ManiSkillEnv("PickCube-v1", obs_mode="state", **kwargs)


def test_wrong_action_shape_says_what_is_expected() -> None:
    env = ManiSkillEnv("PickCube-v1", batch_size=[], obs_mode="state")
    try:
        td = env.reset(seed=0)
        with pytest.raises(ValueError, match=r"shape \(1, 8\), expected \(8,\)"):
            env.step(td.set("action", torch.zeros(1, 8)))
    finally:
        env.close()
