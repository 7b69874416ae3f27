"""ManiSkillWrapper / ManiSkillEnv on real ManiSkill tasks (CPU sim).

- specs and dtypes for Box, nested Dict and image observations, Dict actions, infos;
  ``check_env_specs`` on five configurations;
- bit-for-bit equality with a raw ManiSkill loop (``gym.make`` + seeded ``reset`` /
  ``step``) over several episodes, seeded through ``set_seed`` and through
  ``reset(seed=...)``, with truncation at the time limit and early termination, and
  no aliasing between the tensordicts of successive steps;
- info entries in rollouts, ``from_pixels`` against ManiSkill's own ``render()``;
- partial resets under ``SerialEnv``, ``Collector`` and ``MultiSyncCollector``;
- errors for bad input, and why ``torchrl.envs.GymWrapper`` is not enough.

Envs are built once per module (about 0.4 s each) and shared; every comparison seeds
every reset, so the order in which tests use an env does not matter.
"""

from __future__ import annotations

import functools
from unittest import mock

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.data import Bounded
from torchrl.envs import GymWrapper, SerialEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from maniskill_torchrl import ManiSkillEnv, ManiSkillWrapper
from support.helpers import assert_same, clone_tree, close_envs, make_gym_env, random_actions, tensor_infos

SHORT = 6  # episode limit for the truncation tests: several episodes in a short rollout

# name -> (env id, gym.make kwargs, extra ManiSkillEnv kwargs)
CONFIGS = {
    "pick": ("PickCube-v1", {"obs_mode": "state", "max_episode_steps": SHORT}, {}),
    "pick_sd": ("PickCube-v1", {"obs_mode": "state_dict", "max_episode_steps": SHORT}, {}),
    "pick_rgb": ("PickCube-v1", {"obs_mode": "rgb", "max_episode_steps": SHORT}, {}),
    "cartpole": ("MS-CartpoleBalance-v1", {"obs_mode": "state"}, {}),
    "two_robot": ("TwoRobotPickCube-v1", {"obs_mode": "state", "max_episode_steps": SHORT}, {}),
    "pixels": (
        "PickCube-v1",
        {"obs_mode": "state", "max_episode_steps": SHORT, "render_mode": "rgb_array"},
        {"from_pixels": True},
    ),
}


class _Cache:
    """Builds each env on first use; closes them all at module teardown."""

    def __init__(self):
        self.envs: dict = {}

    def torchrl(self, name: str) -> ManiSkillEnv:
        key = ("torchrl", name)
        if key not in self.envs:
            env_id, kwargs, extra = CONFIGS[name]
            self.envs[key] = ManiSkillEnv(env_id, **kwargs, **extra)
        return self.envs[key]

    def raw(self, name: str) -> gym.Env:
        key = ("raw", name)
        if key not in self.envs:
            env_id, kwargs, _ = CONFIGS[name]
            self.envs[key] = make_gym_env(env_id, **kwargs)
        return self.envs[key]

    def close(self):
        close_envs(self.envs.values())
        self.envs.clear()


@pytest.fixture(scope="module")
def envs():
    cache = _Cache()
    yield cache
    cache.close()


# ============================================================================ helpers
def seeds_after_set_seed(seed: int, n: int) -> list[int]:
    """The seeds of the first ``n`` full resets after ``env.set_seed(seed)``, as documented:
    ``seed`` itself, then draws of ``numpy.random.RandomState(seed).randint(2**31)``."""
    rng = np.random.RandomState(seed)
    return [seed] + [int(rng.randint(2**31)) for _ in range(n - 1)]


def batched(action):
    """An unbatched action (tensor or dict of tensors) -> the [1, ...] form ManiSkill takes."""
    if isinstance(action, dict):
        return {k: v.unsqueeze(0) for k, v in action.items()}
    return action.unsqueeze(0)


def as_td_action(action):
    action = batched(action)
    if isinstance(action, dict):
        return TensorDict(action, batch_size=[1])
    return action


def obs_as_td(obs) -> TensorDictBase:
    """ManiSkill's observation as the entries ManiSkillEnv writes."""
    if isinstance(obs, dict):
        return TensorDict(obs, batch_size=[1])
    return TensorDict({"observation": obs}, batch_size=[1])


def assert_obs_equal(td: TensorDictBase, obs, what: str = ""):
    ref = obs_as_td(obs)
    for key in ref.keys(True, True):
        assert_same(td.get(key), ref.get(key), f"{what} {key}")


def raw_loop(genv: gym.Env, actions: list, seeds: list[int]) -> list[dict]:
    """Steps a gym ManiSkill env, resetting with the next seed whenever an episode ends.

    One record per step: the observation before it, then what ``step`` returned
    (cloned: ManiSkill reuses some buffers, e.g. ``elapsed_steps``).
    """
    seeds = iter(seeds)
    obs, _ = genv.reset(seed=next(seeds))
    prev = clone_tree(obs)
    records = []
    for a in actions:
        obs, reward, terminated, truncated, info = genv.step(batched(a))
        records.append(
            dict(
                prev=prev,
                obs=clone_tree(obs),
                reward=reward.clone(),
                terminated=terminated.clone(),
                truncated=truncated.clone(),
                info=clone_tree(tensor_infos(info)),
            )
        )
        if (terminated | truncated).any():
            obs, _ = genv.reset(seed=next(seeds))
        prev = clone_tree(obs)
    return records


def assert_step_matches(td: TensorDictBase, rec: dict, t: int):
    """``td`` is one step's tensordict (root = before, ``"next"`` = after) from ManiSkillEnv."""
    assert_obs_equal(td, rec["prev"], f"step {t} root")
    nxt = td["next"]
    assert_obs_equal(nxt, rec["obs"], f"step {t} next")
    assert_same(nxt["reward"], rec["reward"].unsqueeze(-1), f"step {t} reward")
    assert_same(nxt["terminated"], rec["terminated"].unsqueeze(-1), f"step {t} terminated")
    assert_same(nxt["truncated"], rec["truncated"].unsqueeze(-1), f"step {t} truncated")
    assert_same(nxt["done"], (rec["terminated"] | rec["truncated"]).unsqueeze(-1), f"step {t} done")
    for key, value in rec["info"].items():
        assert_same(nxt[key], value, f"step {t} info {key}")


# ============================================================================ specs
def test_specs_state(envs):
    env, raw = envs.torchrl("pick"), envs.raw("pick")
    obs_space = raw.unwrapped.single_observation_space
    act_space = raw.unwrapped.single_action_space

    obs = env.observation_spec["observation"]
    assert obs.shape == (1, *obs_space.shape) == (1, 42)
    assert obs.dtype == torch.float32

    action = env.action_spec
    assert isinstance(action, Bounded)
    assert action.shape == (1, 8) and action.dtype == torch.float32
    assert torch.equal(action.space.low, torch.as_tensor(act_space.low).expand(1, 8))
    assert torch.equal(action.space.high, torch.as_tensor(act_space.high).expand(1, 8))

    assert env.reward_spec.shape == (1, 1) and env.reward_spec.dtype == torch.float32
    assert set(env.done_keys) == {"done", "terminated", "truncated"}
    for key in ("done", "terminated", "truncated"):
        spec = env.full_done_spec[key]
        assert spec.shape == (1, 1) and spec.dtype == torch.bool, key

    # Infos are declared as observations, with ManiSkill's own dtypes and shapes.
    infos = tensor_infos(raw.unwrapped.get_info())
    assert {"success", "elapsed_steps"} <= set(infos)
    for key, value in infos.items():
        spec = env.observation_spec[key]
        assert spec.dtype == value.dtype and spec.shape == value.shape, key
    assert env.observation_spec["success"].dtype == torch.bool
    assert env.observation_spec["elapsed_steps"].dtype == torch.int32
    assert env.batch_size == (1,) and env.device == torch.device("cpu")


def test_specs_fail_info(envs):
    env = envs.torchrl("cartpole")
    assert env.observation_spec["fail"].dtype == torch.bool
    assert env.observation_spec["fail"].shape == (1,)
    assert env.observation_spec["elapsed_steps"].dtype == torch.int32
    assert env.action_spec.shape == (1, 1)


def test_specs_state_dict_nested(envs):
    env, raw = envs.torchrl("pick_sd"), envs.raw("pick_sd")
    spec = env.observation_spec
    assert spec["agent", "qpos"].shape == (1, 9) and spec["agent", "qpos"].dtype == torch.float32
    assert spec["extra", "is_grasped"].shape == (1,) and spec["extra", "is_grasped"].dtype == torch.bool
    # Every leaf of the Dict space is declared at its key path, with its dtype.
    space = raw.unwrapped.single_observation_space

    def leaves(sp, prefix=()):
        for k, v in sp.spaces.items():
            if isinstance(v, gym.spaces.Dict):
                yield from leaves(v, prefix + (k,))
            else:
                yield prefix + (k,), v

    n = 0
    for key, sub in leaves(space):
        leaf = spec[key]
        assert leaf.shape == (1, *sub.shape), key
        assert leaf.dtype == torch.from_numpy(np.zeros((), sub.dtype)).dtype, key
        n += 1
    assert n >= 5
    # And the data has them too.
    td = env.reset(seed=0)
    assert td["agent", "qpos"].dtype == torch.float32
    assert td["extra", "is_grasped"].dtype == torch.bool


@pytest.mark.pictures
def test_specs_rgb(envs):
    env = envs.torchrl("pick_rgb")
    rgb = env.observation_spec["sensor_data", "base_camera", "rgb"]
    assert rgb.shape == (1, 128, 128, 3) and rgb.dtype == torch.uint8
    td = env.reset(seed=0)
    assert td["sensor_data", "base_camera", "rgb"].dtype == torch.uint8
    assert td["sensor_data", "base_camera", "rgb"].shape == (1, 128, 128, 3)


def test_specs_dict_action(envs):
    env, raw = envs.torchrl("two_robot"), envs.raw("two_robot")
    agents = list(raw.unwrapped.single_action_space.spaces)
    assert agents == ["panda_wristcam-0", "panda_wristcam-1"]
    assert set(env.action_keys) == {("action", a) for a in agents}
    for agent in agents:
        spec = env.full_action_spec["action", agent]
        sub = raw.unwrapped.single_action_space[agent]
        assert isinstance(spec, Bounded) and spec.shape == (1, 8)
        assert torch.equal(spec.space.low, torch.as_tensor(sub.low).expand(1, 8))
        assert torch.equal(spec.space.high, torch.as_tensor(sub.high).expand(1, 8))


@pytest.mark.parametrize(
    "name", ["pick", "pick_sd", pytest.param("pick_rgb", marks=pytest.mark.pictures), "cartpole", "two_robot"]
)
def test_check_env_specs(envs, name):
    check_env_specs(envs.torchrl(name), seed=0)


def test_info_keys_subset():
    env = ManiSkillEnv("PickCube-v1", obs_mode="state", info_keys=["success"])
    try:
        assert "success" in env.observation_spec.keys()
        assert "elapsed_steps" not in env.observation_spec.keys()
        td = env.rand_step(env.reset(seed=0))
        assert "elapsed_steps" not in td["next"].keys()
        assert td["next", "success"].dtype == torch.bool
    finally:
        env.close()


# ============================================================================ equality with raw ManiSkill
@pytest.mark.parametrize(
    "name, n_steps, min_episodes",
    [("pick", 3 * SHORT + 2, 3), ("pick_sd", 2 * SHORT + 1, 2), ("cartpole", 40, 2), ("two_robot", SHORT + 2, 1)],
)
def test_equal_to_raw_loop_set_seed(envs, name, n_steps, min_episodes):
    """set_seed(s): first reset seeded with s, later (auto) resets with RandomState(s) draws."""
    env, raw = envs.torchrl(name), envs.raw(name)
    actions = random_actions(raw.unwrapped.single_action_space, n_steps, seed=7)
    seed = 123
    records = raw_loop(raw, actions, seeds_after_set_seed(seed, n_steps + 1))

    env.set_seed(seed)
    td = env.reset()
    steps = []
    for a in actions:
        td.set("action", as_td_action(a))
        td, td_next = env.step_and_maybe_reset(td)
        steps.append(td)  # kept as is: a later step must not change an earlier td
        td = td_next
    # Compared only now, after all steps: this also checks that nothing is aliased.
    for t, (td, rec) in enumerate(zip(steps, records)):
        assert_step_matches(td, rec, t)

    ended = [bool((r["terminated"] | r["truncated"]).any()) for r in records]
    assert sum(ended) >= min_episodes, "the rollout should span several episodes"
    if name == "cartpole":
        assert any(bool(r["terminated"].any()) for r in records), "CartpoleBalance should fail early"
        assert any(bool(r["info"]["fail"].any()) for r in records)
    else:
        assert any(bool(r["truncated"].any()) for r in records), "the time limit should truncate"


def test_equal_to_raw_loop_rollout_with_set_seed(envs):
    """env.rollout (auto-reset, stacked output) gives the same data as the raw loop."""
    env, raw = envs.torchrl("pick"), envs.raw("pick")
    n = 2 * SHORT + 3
    actions = random_actions(raw.unwrapped.single_action_space, n, seed=3)
    records = raw_loop(raw, actions, seeds_after_set_seed(42, n + 1))
    it = iter(actions)

    def policy(td):
        return td.set("action", as_td_action(next(it)))

    env.set_seed(42)
    rollout = env.rollout(n, policy, break_when_any_done=False)
    assert rollout.shape == (1, n)
    for t, rec in enumerate(records):
        assert_step_matches(rollout[:, t], rec, t)


@pytest.mark.parametrize("name", ["pick", "cartpole"])
def test_equal_to_raw_loop_reset_seed(envs, name):
    """reset(seed=s) seeds that reset; episodes run until done or k steps."""
    env, raw = envs.torchrl(name), envs.raw(name)
    k = SHORT + 2 if name == "pick" else 25
    actions = random_actions(raw.unwrapped.single_action_space, k, seed=11)
    for seed in (5, 17, 2**31 - 1):
        obs, _ = raw.reset(seed=seed)
        td = env.reset(seed=seed)
        assert_obs_equal(td, obs, f"reset seed={seed}")
        assert not td["done"].any()
        kept = []
        raw_recs = []
        for a in actions:
            obs, reward, terminated, truncated, info = raw.step(batched(a))
            raw_recs.append(
                (clone_tree(obs), reward.clone(), terminated.clone(), truncated.clone(), clone_tree(tensor_infos(info)))
            )
            td.set("action", as_td_action(a))
            td = env.step(td)
            kept.append(td["next"])
            if td["next", "done"].any():
                break
            td = step_mdp(td)
        assert len(kept) == len(raw_recs)
        for t, (nxt, (o, r, te, tr, info)) in enumerate(zip(kept, raw_recs)):
            assert_obs_equal(nxt, o, f"seed={seed} step {t}")
            assert_same(nxt["reward"], r.unsqueeze(-1), "reward")
            assert_same(nxt["terminated"], te.unsqueeze(-1), "terminated")
            assert_same(nxt["truncated"], tr.unsqueeze(-1), "truncated")
            for key, value in info.items():
                assert_same(nxt[key], value, f"seed={seed} step {t} {key}")


def test_same_seed_same_episode(envs):
    """Two runs from the same seed give identical data (and reset(seed) restarts the draws)."""
    env = envs.torchrl("pick")
    actions = [as_td_action(a) for a in random_actions(env.unwrapped.single_action_space, 2 * SHORT)]

    def run():
        env.set_seed(9)
        td = env.reset()
        out = []
        for a in actions:
            td, td_ = env.step_and_maybe_reset(td.set("action", a))
            out.append(td)
            td = td_
        return torch.stack(out, 1)

    a, b = run(), run()
    assert (a == b).all()


def test_outputs_not_aliased(envs):
    """ManiSkill updates elapsed_steps in place: earlier tensordicts must keep their values."""
    env = envs.torchrl("pick")
    td = env.reset(seed=0)
    first_reset = td.clone()
    outs = []
    for a in random_actions(env.unwrapped.single_action_space, 4, seed=1):
        td = env.step(td.set("action", as_td_action(a)))
        outs.append(td["next"])
        td = step_mdp(td)
    assert [int(o["elapsed_steps"]) for o in outs] == [1, 2, 3, 4]
    assert int(first_reset["elapsed_steps"]) == 0
    # Observations of successive steps are distinct tensors.
    assert outs[0]["observation"].data_ptr() != outs[1]["observation"].data_ptr()


# ============================================================================ infos, pixels, render
def test_rollout_info_entries(envs):
    env = envs.torchrl("pick")
    env.set_seed(0)
    rollout = env.rollout(SHORT)
    assert rollout.shape == (1, SHORT)
    for key in ("success", "elapsed_steps", "is_grasped"):
        assert key in rollout.keys() and ("next", key) in rollout.keys(True)
    assert rollout["next", "success"].dtype == torch.bool
    assert rollout["next", "elapsed_steps"][0].tolist() == list(range(1, SHORT + 1))
    assert rollout["elapsed_steps"][0].tolist() == list(range(0, SHORT))
    assert rollout["next", "truncated"][0, -1].item() and not rollout["next", "truncated"][0, :-1].any()


@pytest.mark.pictures
def test_from_pixels_equals_maniskill_render(envs):
    env, raw = envs.torchrl("pixels"), envs.raw("pixels")
    spec = env.observation_spec["pixels"]
    assert spec.dtype == torch.uint8 and spec.shape == (1, 512, 512, 3)
    assert "observation" in env.observation_spec.keys()  # pixels are added, not substituted

    actions = random_actions(raw.unwrapped.single_action_space, 2, seed=4)
    raw.reset(seed=21)
    td = env.reset(seed=21)
    # raw references on env.device: on a CUDA machine ManiSkill renders the CPU sim on the GPU
    assert_same(td["pixels"], raw.render().to(env.device), "reset pixels")
    for t, a in enumerate(actions):
        raw.step(batched(a))
        td = env.step(td.set("action", as_td_action(a)))
        assert_same(td["next", "pixels"], raw.render().to(env.device), f"step {t} pixels")
        td = step_mdp(td)
    # render() is ManiSkill's render: a batched uint8 frame, the same as the last "pixels".
    frame = env.render()
    assert frame.shape == (1, 512, 512, 3) and frame.dtype == torch.uint8
    assert_same(frame, td["pixels"], "render()")
    check_env_specs(env, seed=0)


# ============================================================================ inference mode
class _ModeProbe(gym.Wrapper):
    """Records, for each call into the ManiSkill env, whether torch's inference mode was on."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.modes: list[tuple[str, bool]] = []

    def step(self, action):
        self.modes.append(("step", torch.is_inference_mode_enabled()))
        return self.env.step(action)

    def reset(self, **kwargs):
        self.modes.append(("reset", torch.is_inference_mode_enabled()))
        return self.env.reset(**kwargs)

    def render(self):
        self.modes.append(("render", torch.is_inference_mode_enabled()))
        return self.env.render()


def _inference_leaves(td: TensorDictBase) -> list:
    return [k for k, v in td.items(True, True) if v.is_inference()]


@pytest.mark.pictures
@pytest.mark.parametrize("inference_mode", [None, True, False])
def test_inference_mode_calls_and_values(inference_mode):
    """The wrapper calls ManiSkill under inference mode when asked (not by default: the caller
    holds the gym env); the data are the raw loop's either way (the raw loop runs in grad mode)."""
    env_id, kwargs, _ = CONFIGS["pixels"]
    probe = _ModeProbe(make_gym_env(env_id, **kwargs))
    extra = {} if inference_mode is None else {"inference_mode": inference_mode}
    env = ManiSkillWrapper(probe, from_pixels=True, **extra)
    expected = bool(inference_mode)
    assert env.inference_mode is expected
    raw = make_gym_env(env_id, **kwargs)
    try:
        n = SHORT + 2
        actions = random_actions(raw.unwrapped.single_action_space, n, seed=5)
        records = raw_loop(raw, actions, seeds_after_set_seed(8, n + 1))
        env.set_seed(8)
        td = env.reset()
        for t, (a, rec) in enumerate(zip(actions, records)):
            td, td_next = env.step_and_maybe_reset(td.set("action", as_td_action(a)))
            assert_step_matches(td, rec, t)
            td = td_next
        env.render()
        assert {kind for kind, _ in probe.modes} == {"step", "reset", "render"}
        assert all(mode == expected for _, mode in probe.modes), probe.modes
    finally:
        close_envs([env, raw])


@pytest.mark.pictures
def test_inference_mode_outputs_are_normal_tensors(envs):
    """ManiSkillEnv runs a CPU-sim env in inference mode by default; what it returns can be
    modified in place (as TorchRL's partial resets and users' transforms do): copies, not
    inference tensors."""
    for name in ("pick", "pick_sd", "pixels"):
        env = envs.torchrl(name)
        assert env.inference_mode
        td = env.reset(seed=3)
        assert not _inference_leaves(td), name
        td = env.rand_step(td)
        assert not _inference_leaves(td), name
        td.apply_(lambda x: x.zero_() if x.dtype != torch.bool else x.logical_not_())
    frame = envs.torchrl("pixels").render()
    assert not frame.is_inference()
    frame.zero_()


# ============================================================================ batched envs, collectors
def test_serial_env_partial_reset(envs):
    env_id, kwargs, _ = CONFIGS["pick"]
    senv = SerialEnv(2, functools.partial(ManiSkillEnv, env_id, **kwargs))
    try:
        assert senv.batch_size == (2, 1)  # two sub-envs of ManiSkill's batch of one

        def steps(td):
            return td["elapsed_steps"].reshape(-1).tolist()

        senv.set_seed(0)
        td = senv.reset()
        assert steps(td) == [0, 0]
        for _ in range(3):
            td = step_mdp(senv.rand_step(td))
        assert steps(td) == [3, 3]
        obs_before = td["observation"].clone()

        # As maybe_reset does: the current data with a "_reset" mask; entries of the envs
        # not reset are kept from it.
        td.set("_reset", torch.tensor([True, False]).view(2, 1, 1))
        reset = senv.reset(td)
        assert steps(reset) == [0, 3]
        assert torch.equal(reset["observation"][1], obs_before[1])  # untouched
        assert not torch.equal(reset["observation"][0], obs_before[0])
        # Sub-env 0 was seeded 0 by set_seed: its second full reset uses the first draw.
        raw = envs.raw("pick")
        obs, _ = raw.reset(seed=seeds_after_set_seed(0, 2)[1])
        assert_same(reset["observation"][0], obs, "partially reset sub-env")
        assert not reset["done"].any()
        # And the batch steps on from there.
        td = step_mdp(senv.rand_step(reset))
        assert steps(td) == [1, 4]
    finally:
        senv.close()


def _pick_env_fn():
    env_id, kwargs, _ = CONFIGS["pick"]
    return functools.partial(ManiSkillEnv, env_id, **kwargs)


def _check_batch(batch: TensorDictBase, n_frames: int):
    assert batch.numel() == n_frames
    for key in ("success", "elapsed_steps", "is_grasped"):
        assert ("next", key) in batch.keys(True), key
        assert key in batch.keys(), key
    assert batch["next", "success"].dtype == torch.bool
    steps = batch["next", "elapsed_steps"].reshape(-1)
    assert steps.min() >= 1 and steps.max() <= SHORT
    # After SHORT steps the collector resets: elapsed steps restart.
    assert batch["next", "truncated"].any()


def test_collector(envs):
    frames = 2 * SHORT + 2
    collector = Collector(_pick_env_fn(), policy=None, frames_per_batch=frames, total_frames=2 * frames)
    try:
        batches = [b.clone() for b in collector]
    finally:
        collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        _check_batch(batch, frames)


@pytest.mark.slow
def test_multi_sync_collector(envs):
    """The env in a MultiSyncCollector's worker process: one worker (each spawned one imports
    torch, TorchRL and ManiSkill), several episodes per batch."""
    frames = 2 * (SHORT + 2)
    collector = MultiSyncCollector([_pick_env_fn()], policy=None, frames_per_batch=frames, total_frames=frames)
    try:
        batches = [b.clone() for b in collector]
    finally:
        collector.shutdown()
    assert len(batches) == 1
    _check_batch(batches[0], frames)


# ============================================================================ bad input
@pytest.fixture(scope="module")
def spare_gym_env():
    """A ManiSkill gym env only used where construction fails (a failed wrapper may close it)."""
    env = make_gym_env("PickCube-v1", obs_mode="state")
    yield env
    env.close()


def test_unknown_env_id():
    with pytest.raises(ValueError, match="available_envs"):
        ManiSkillEnv("PickCub-v1")
    assert "PickCube-v1" in ManiSkillEnv.available_envs


def test_non_maniskill_env():
    env = gym.make("CartPole-v1")
    with pytest.raises(TypeError, match="GymWrapper"):
        ManiSkillWrapper(env)
    with pytest.raises(TypeError, match="ManiSkill"):
        ManiSkillWrapper()


def test_wrong_action_shape(envs):
    env = envs.torchrl("pick")
    td = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(1, 7\)"):
        env.step(td.set("action", torch.zeros(1, 7)))
    two = envs.torchrl("two_robot")
    td = two.reset(seed=0)
    bad = TensorDict({"panda_wristcam-0": torch.zeros(1, 8), "panda_wristcam-1": torch.zeros(1, 7)}, [1])
    with pytest.raises(ValueError, match="panda_wristcam-1"):
        two.step(td.set("action", bad))


def test_step_without_action_says_what_to_pass(envs):
    env = envs.torchrl("pick")
    td = env.reset(seed=0)
    with pytest.raises(KeyError, match=r"no action at 'action'.*'observation'.*rand_action"):
        env.step(td)
    env.step(env.rand_action(td))  # the env is still usable
    two = envs.torchrl("two_robot")
    td = two.reset(seed=0)
    with pytest.raises(KeyError, match=r"no action at 'action'.*\('action', 'panda_wristcam-0'\)"):
        two.step(td)
    half = TensorDict({"panda_wristcam-0": torch.zeros(1, 8)}, [1])
    with pytest.raises(KeyError, match=r"no action at \('action', 'panda_wristcam-1'\)"):
        two.step(td.set("action", half))


def test_step_or_reset_after_close_says_closed():
    env = ManiSkillEnv("PickCube-v1", obs_mode="state")
    td = env.rand_action(env.reset(seed=0))
    env.close()
    assert env.is_closed and "closed" in repr(env)
    for call in (lambda: env.step(td), lambda: env.reset(), lambda: env.rand_step(td), env.render):
        with pytest.raises(RuntimeError, match=r"ManiSkillEnv\(PickCube-v1\) is closed.*new env"):
            call()
    env.close(raise_if_closed=False)  # closing again is harmless


@pytest.mark.parametrize("kwargs", [{}, {"sim_backend": "cpu"}, {"sim_backend": "physx_cpu"}])
def test_num_envs_on_cpu_sim(kwargs):
    if not kwargs and torch.cuda.is_available():
        pytest.skip("sim_backend='auto' picks the GPU sim when CUDA is available")

    # On the CPU sim, num_envs > 1 builds a CPUVectorEnv of N workers (tests/test_cpu_vector.py).
    class Built(Exception):
        pass

    with mock.patch("maniskill_torchrl.envs.engine_env.CPUVectorEnv", side_effect=Built) as built:
        with pytest.raises(Built):
            ManiSkillEnv("PickCube-v1", num_envs=2, **kwargs)
    (env_id, n), kw = built.call_args
    assert (env_id, n, kw["sim_backend"]) == ("PickCube-v1", 2, "physx_cpu")
    with pytest.raises(ValueError, match="positive"):
        ManiSkillEnv("PickCube-v1", num_envs=0, **kwargs)


def test_device_cuda_without_cuda_is_refused(spare_gym_env, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # also on a machine with CUDA
    with pytest.raises(ValueError, match=r"device='cuda:0', but torch.cuda.is_available\(\) is False"):
        ManiSkillWrapper(spare_gym_env, device="cuda")


def test_from_pixels_needs_render_mode(spare_gym_env):
    with pytest.raises(ValueError, match="render_mode"):
        ManiSkillWrapper(spare_gym_env, from_pixels=True)
    with pytest.raises(ValueError, match="from_pixels"):
        ManiSkillWrapper(spare_gym_env, pixels_only=True)


def test_unknown_info_key():
    with pytest.raises(ValueError, match="available info keys"):
        ManiSkillEnv("PickCube-v1", obs_mode="state", info_keys=["nope"])


def test_torchrl_gym_wrapper_fails_on_maniskill():
    """Why this library exists: TorchRL's GymWrapper takes ManiSkill's batched single env
    (num_envs=1, outputs [1, ...]) for an unbatched one and rejects its specs."""
    env = make_gym_env("PickCube-v1", obs_mode="state")
    try:
        with pytest.raises(ValueError, match="batch size"):
            GymWrapper(env)
    finally:
        env.close()


def test_gpu_sim_without_cuda_says_what_to_do(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="needs CUDA.*sim_backend='cpu'"):
        ManiSkillEnv("PushCube-v1", num_envs=4, sim_backend="gpu")


def test_physx_gpu_download_failure_says_what_to_do(monkeypatch):
    import requests
    import sapien.physx

    from maniskill_torchrl._internal.sim import enable_physx_gpu

    def offline():
        raise requests.exceptions.ConnectionError("Failed to resolve 'github.com'")

    monkeypatch.setattr(sapien.physx, "is_gpu_enabled", lambda: False)
    monkeypatch.setattr(sapien.physx, "enable_gpu", offline)
    with pytest.raises(RuntimeError, match=r"libPhysXGpu_64\.so.*Failed to resolve.*sim_backend='cpu'") as info:
        enable_physx_gpu()
    assert isinstance(info.value.__cause__, requests.exceptions.ConnectionError)


def test_pickling_says_what_to_pickle_instead():
    """A ManiSkillEnv pickles (and deep-copies) as its constructor: a new env of the same arguments (issue 62). A
    ManiSkillWrapper around a gym env holds a live sim nothing can rebuild: pickling it (a collector given an
    instance, deepcopy) names the factories that pickle, instead of an error about a local lambda."""
    import copy
    import functools
    import pickle

    env = ManiSkillEnv("PickCube-v1", obs_mode="state")
    wrapper = ManiSkillWrapper(make_gym_env("PickCube-v1", obs_mode="state"))
    try:
        for dump in (pickle.dumps, copy.deepcopy):
            with pytest.raises(TypeError, match=r"cannot pickle 'ManiSkillWrapper'.*functools.partial\(ManiSkillEnv"):
                dump(wrapper)
        copied = copy.deepcopy(env)
        assert type(copied) is ManiSkillEnv and copied is not env and copied.batch_size == env.batch_size
        copied.close()
        make = pickle.loads(pickle.dumps(functools.partial(ManiSkillEnv, "PickCube-v1", obs_mode="state")))
        assert make.func is ManiSkillEnv
    finally:
        env.close()
        wrapper.close()
