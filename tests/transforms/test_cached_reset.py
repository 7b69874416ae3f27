"""``CachedReset`` against ManiSkill 3.0.1's ``CachedResetWrapper`` on the CPU sim, bit for bit:
observations after each reset and step, its cache's seeded construction, its draws from torch's
global RNG, the cached observations (rgb included), and partial resets of the batched CPU env
against raw ManiSkill's ``reset_to_env_states`` per sub-env (ManiSkill's wrapper itself needs
``num_envs`` envs in one sim, which the CPU sim cannot hold).

Each comparison runs raw ManiSkill first, then the library, doing the same sequence of calls.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.testing import assert_tensordict_equal
from maniskill_torchrl.transforms import CachedReset
from support.helpers import close_envs, make_gym_env
from support.toy_env import ToyEnv

TASK = "PickCube-v1"
STEPS = 4


def _actions(n: int, dim: int = 8, seed: int = 0) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [torch.rand(1, dim, generator=g) * 2 - 1 for _ in range(n)]


def _sequence(reset, step, actions, resets: int = 3) -> list:
    """``resets`` episodes of ``len(actions)`` steps, torch's global RNG seeded before each reset
    (the cache's draws): what each reset and step returned."""
    out = []
    for k in range(resets):
        torch.manual_seed(100 + k)
        out.append(reset())
        out.extend(step(a) for a in actions)
    return out


def _library_play(env):
    now = {}

    def reset():
        now["td"] = env.reset()
        return now["td"]

    def step(a):
        now["td"] = env.step(now["td"].set("action", a.clone()))["next"]
        return now["td"]

    return reset, step


def _raw_play(raw):
    # Copies: ManiSkill's reset with cached observations writes them into its last observation, the
    # tensors its last step returned (an alias the library's outputs never have).
    def reset():
        return _copied(raw.reset()[0])

    def step(a):
        obs, reward = raw.step(a.clone())[:2]
        return _copied(obs), reward.clone()

    return reset, step


def _copied(obs):
    return obs.clone() if isinstance(obs, torch.Tensor) else TensorDict(obs, batch_size=[1]).clone()


def _assert_same(ours, theirs, obs=lambda td: td["observation"]):
    for t, (mine, theirs_t) in enumerate(zip(ours, theirs)):
        if isinstance(theirs_t, tuple):  # a step: (obs, reward)
            theirs_t, reward = theirs_t
            assert torch.equal(mine["reward"][:, 0], reward.float()), t
        expected = theirs_t if isinstance(theirs_t, torch.Tensor) else TensorDict(theirs_t, batch_size=[1])
        got = obs(mine)
        if isinstance(expected, torch.Tensor):
            assert torch.equal(got, expected), t
        else:
            assert_tensordict_equal(got, expected, msg=f"call {t}")


def _rng_seeds(base_env) -> tuple:
    """ManiSkill's main and episode seeds: what a seeded reset sets and an unseeded one keeps."""
    return list(base_env._main_seed), [int(x) for x in base_env._episode_seed]


def test_built_cache_equals_maniskills_wrapper():
    """The cache ManiSkill's wrapper builds (``CachedResetsConfig(num_resets=1, seed=5)``), then
    three cached resets and their steps: the same observations and rewards, to the bit."""
    from mani_skill.utils.wrappers import CachedResetWrapper

    actions = _actions(STEPS)
    raw = CachedResetWrapper(
        make_gym_env(TASK, obs_mode="state", max_episode_steps=50), config=dict(num_resets=1, seed=5)
    )
    try:
        theirs = _sequence(*_raw_play(raw), actions)
        their_seeds = _rng_seeds(raw.unwrapped)
    finally:
        close_envs([raw])
    env = TransformedEnv(ManiSkillEnv(TASK, obs_mode="state", max_episode_steps=50), CachedReset(num_resets=1, seed=5))
    try:
        ours = _sequence(*_library_play(env), actions)
        assert env.transform.env_states.batch_size == torch.Size([1])
        # Cached resets are unseeded, as the wrapper's: ManiSkill's RNGs end where the wrapper's do.
        assert _rng_seeds(env.base_env.unwrapped) == their_seeds
    finally:
        env.close()
    _assert_same(ours, theirs)
    # Every reset returns the one cached start, and the episodes after it repeat.
    assert torch.equal(ours[0]["observation"], ours[STEPS + 1]["observation"])
    assert ours[STEPS]["elapsed_steps"].item() == STEPS and ours[STEPS + 1]["elapsed_steps"].item() == 0


@pytest.mark.pictures  # renders: make test-pictures
def test_given_states_and_cached_rgb_observations_equal_maniskills_wrapper():
    """Three saved starts with their rgb observations (ManiSkill's ``reset_to_env_states``): the
    draws among them (torch's global RNG) and the observations after reset (the cached images) and
    after each step (rendered), as ManiSkill's wrapper gives them."""
    from mani_skill.utils.wrappers import CachedResetWrapper

    kwargs = dict(obs_mode="rgb", sensor_configs=dict(width=32, height=32), max_episode_steps=50)
    actions = _actions(2)
    seeds = (3, 4, 5)
    raw = make_gym_env(TASK, **kwargs)
    try:
        states, obs = [], []
        for s in seeds:
            o, _ = raw.reset(seed=s)
            obs.append(TensorDict(o, batch_size=[1]).clone())
            states.append(TensorDict(raw.unwrapped.get_state_dict(), batch_size=[1]).clone())
        raw = CachedResetWrapper(
            raw, reset_to_env_states={"env_states": torch.cat(states).to_dict(), "obs": torch.cat(obs).to_dict()}
        )
        theirs = _sequence(*_raw_play(raw), actions, resets=4)
    finally:
        close_envs([raw])
    env = ManiSkillEnv(TASK, **kwargs)
    try:
        states, obs = [], []
        for s in seeds:
            obs.append(env.reset(seed=s))
            states.append(env.get_state())
        env = TransformedEnv(env, CachedReset(env_states=torch.cat(states), obs=torch.cat(obs)))
        ours = _sequence(*_library_play(env), actions, resets=4)
    finally:
        env.close()
    pictures = lambda td: td.select("agent", "extra", "sensor_param", "sensor_data")  # noqa: E731
    _assert_same(ours, theirs, obs=pictures)
    starts = {ours[k * 3]["sensor_data", "base_camera", "rgb"].float().sum().item() for k in range(4)}
    assert len(starts) > 1  # the draws picked more than one of the starts


def test_batched_cpu_env_partial_resets_equal_maniskills_state_resets():
    """``ManiSkillEnv(num_envs=2)``: the cache from one seeded reset (sub-env ``i`` seeded ``11 + i``),
    then a full and a partial cached reset, each env reset to the row torch's RNG drew, with its
    cached observation; against two raw envs reset to the same rows by ManiSkill's own
    ``reset_to_env_states``, and the env not reset running on."""
    actions = [torch.cat([a, b]) for a, b in zip(_actions(STEPS, seed=1), _actions(STEPS, seed=2))]
    raws = [make_gym_env(TASK, obs_mode="state", max_episode_steps=50) for _ in range(2)]
    theirs = []
    try:
        cache_obs, cache_states = [], []
        for i, raw in enumerate(raws):
            cache_obs.append(raw.reset(seed=11 + i)[0].clone())
            cache_states.append(TensorDict(raw.unwrapped.get_state_dict(), batch_size=[1]).clone())
        cache_obs, cache_states = torch.cat(cache_obs), torch.cat(cache_states)

        def reset_to(envs, seed):
            torch.manual_seed(seed)
            ids = torch.randint(0, 2, (len(envs),))
            for i, k in zip(envs, ids.tolist()):
                state = {"env_states": cache_states[k : k + 1].to_dict(), "obs": cache_obs[k : k + 1]}
                raws[i].reset(options={"reset_to_env_states": state})

        def play():
            for a in actions:
                steps = [raw.step(a[i : i + 1].clone()) for i, raw in enumerate(raws)]
                theirs.append(torch.cat([s[0] for s in steps]))

        reset_to([0, 1], 7)
        play()
        reset_to([1], 8)
        play()
    finally:
        close_envs(raws)
    env = TransformedEnv(
        ManiSkillEnv(TASK, num_envs=2, sim_backend="cpu", obs_mode="state", max_episode_steps=50),
        CachedReset(seed=11),
    )
    ours = []
    try:
        torch.manual_seed(7)
        td = env.reset()
        assert torch.equal(env.transform.obs["observation"], cache_obs)
        for a in actions:
            td = env.step(td.set("action", a))["next"]
            ours.append(td["observation"])
        before = td["observation"].clone()
        torch.manual_seed(8)
        td = env.reset(td.clone().set("_reset", torch.tensor([[False], [True]])))
        assert torch.equal(td["observation"][0], before[0])  # env 0 runs on
        assert td["elapsed_steps"].tolist() == [STEPS, 0]
        for a in actions:
            td = env.step(td.set("action", a))["next"]
            ours.append(td["observation"])
    finally:
        env.close()
    for t, (mine, expected) in enumerate(zip(ours, theirs)):
        assert torch.equal(mine, expected), t


def test_cache_rounds_after_the_first_follow_the_envs_seed_stream():
    """``num_resets`` above ``num_envs``: one reset per round, the first seeded with ``seed``, the
    next ones the env's next seeds (as ``reset()`` after ``reset(seed=5)`` draws them); a reset of
    no env leaves no request behind."""
    env = TransformedEnv(ManiSkillEnv("PushCube-v1", obs_mode="state"), CachedReset(num_resets=3, seed=5))
    try:
        env.reset()
        cached = env.transform.env_states
        assert cached.batch_size == torch.Size([3])
        base = env.base_env
        for k in range(3):
            base.reset(seed=5) if k == 0 else base.reset()
            assert_tensordict_equal(base.get_state(), cached[k : k + 1], msg=f"row {k}")
        env.reset(env.reset().set("_reset", torch.tensor([[False]])))
        assert base._next_states is None
    finally:
        env.close()


def test_arguments_and_envs_are_checked():
    with pytest.raises(ValueError, match="num_resets"):
        CachedReset(num_resets=0)
    with pytest.raises(ValueError, match="give both"):
        CachedReset(obs=TensorDict({"observation": torch.zeros(2, 3)}, batch_size=[2]))
    with pytest.raises(ValueError, match="one per state"):
        CachedReset(env_states={"x": torch.zeros(2, 1)}, obs=TensorDict({"o": torch.zeros(3)}, batch_size=[3]))
    # An env without the library's hooks (any TorchRL env, a ParallelEnv) is refused, saying where it goes.
    with pytest.raises(TypeError, match="ManiSkillEnv"):
        TransformedEnv(ToyEnv([2]), CachedReset()).reset()
    assert "num_resets=4" in repr(CachedReset(4))
