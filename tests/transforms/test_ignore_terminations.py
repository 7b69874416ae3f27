"""IgnoreTerminations: terminated forced False, done = truncated, at every level of done keys."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from maniskill_torchrl import CPUUnbatch, IgnoreTerminations, ManiSkillEnv
from maniskill_torchrl.transforms import IgnoreTerminations as IgnoreTerminationsFromTransforms
from support.toy_env import ToyEnv


def test_cartpole_runs_past_fail_to_time_limit():
    base = TransformedEnv(ManiSkillEnv("MS-CartpoleBalance-v1", obs_mode="state", max_episode_steps=40), CPUUnbatch())
    env = TransformedEnv(base.base_env, Compose(CPUUnbatch(), IgnoreTerminations()))
    try:
        assert env.output_spec == base.output_spec  # specs unchanged
        check_env_specs(env, seed=0)
        # Without the transform the episode terminates early on fail...
        base.set_seed(1)
        torch.manual_seed(0)  # the random actions
        short = base.rollout(100)
        assert short["next", "terminated"][-1].item() and short.shape[0] < 40
        assert short["next", "fail"][-1].item()
        # ...with it the same episode goes on to truncation, fail still reported along the way.
        env.set_seed(1)
        torch.manual_seed(0)
        roll = env.rollout(100)
        assert roll.shape == torch.Size([40])
        assert torch.equal(roll["next", "observation"][: short.shape[0]], short["next", "observation"])
        assert roll["next", "fail"][short.shape[0] - 1].item()
        assert not roll["next", "terminated"].any()
        assert torch.equal(roll["next", "done"], roll["next", "truncated"])
        assert roll["next", "truncated"].squeeze(-1).nonzero().squeeze(-1).tolist() == [39]
        # ManiSkill itself reports the termination: a long way before the end.
        assert roll["next", "fail"].squeeze(-1).nonzero()[0].item() < 39
    finally:
        base.close()


def test_nested_done_keys_multi_agent():
    env = TransformedEnv(ToyEnv([2, 4, 3], terminate=[True, False, True], multi_agent=True), IgnoreTerminations())
    assert env.output_spec == env.base_env.output_spec
    check_env_specs(env)
    roll = env.rollout(6, break_when_any_done=False)
    for prefix in ((), ("agents",)):
        term, trunc, done = (roll[("next", *prefix, k)] for k in ("terminated", "truncated", "done"))
        assert not term.any()
        assert torch.equal(done, trunc)
    # Only env 1 truncates (at its 4th step, then it is reset); the terminating envs never end.
    done = roll["next", "done"].squeeze(-1)
    assert done.nonzero().tolist() == [[1, 3]]
    assert roll["next", "fail"][0, 1:].all()  # the env still reports its fail


def test_done_is_not_an_alias_of_truncated():
    env = TransformedEnv(ToyEnv([1, 2], terminate=False), IgnoreTerminations())
    td = env.rand_step(env.reset())
    nxt = td["next"]
    assert nxt["done"].tolist() == [[True], [False]]
    assert nxt["done"].data_ptr() != nxt["truncated"].data_ptr()


def test_reset_and_standalone_forward():
    env = TransformedEnv(ToyEnv([1, 2]), IgnoreTerminations())
    td = env.reset()
    assert not td["terminated"].any() and not td["done"].any()
    # Without an env (e.g. on stored data): the root done keys.
    data = TensorDict(
        terminated=torch.tensor([[True], [False]]),
        truncated=torch.tensor([[False], [True]]),
        done=torch.tensor([[True], [True]]),
        batch_size=[2],
    )
    out = IgnoreTerminations()(data)
    assert out["terminated"].tolist() == [[False], [False]]
    assert out["done"].tolist() == [[False], [True]]
    assert IgnoreTerminations is IgnoreTerminationsFromTransforms
    assert repr(IgnoreTerminations()) == "IgnoreTerminations()"


def test_in_keys_default_to_the_envs_terminated_keys_and_can_be_chosen():
    """As TorchRL's transforms: ``in_keys`` (the terminated entries to clear) default to every
    terminated key of the env; given, only those groups change."""
    env = TransformedEnv(ToyEnv([2, 4], multi_agent=True), IgnoreTerminations())
    assert sorted(map(str, env.transform.in_keys)) == sorted(map(str, [("agents", "terminated"), "terminated"]))
    assert IgnoreTerminations().in_keys == ["terminated"]  # no env: the root flag
    env = TransformedEnv(ToyEnv([2, 4], multi_agent=True), IgnoreTerminations(in_keys=[("agents", "terminated")]))
    check_env_specs(env)
    roll = env.rollout(3, break_when_any_done=False)
    assert not roll["next", "agents", "terminated"].any()
    assert torch.equal(roll["next", "agents", "done"], roll["next", "agents", "truncated"])
    assert roll["next", "terminated"][0, 1].all() and roll["next", "done"][0, 1].all()  # the root group: as given
    assert repr(env.transform) == "IgnoreTerminations(in_keys=[('agents', 'terminated')])"


def test_forward_on_a_replay_buffer_sample_clears_the_next_flags():
    """On stored transitions (a replay buffer's transform runs ``forward`` on each sample) the
    flags that count are ``("next", "terminated")`` / ``("next", "done")``."""
    from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement

    roll = ToyEnv([2, 3], terminate=[True, False]).rollout(4, break_when_any_done=False)
    assert roll["next", "terminated"].any()
    rb = ReplayBuffer(
        storage=LazyTensorStorage(8), sampler=SamplerWithoutReplacement(), transform=IgnoreTerminations(), batch_size=8
    )
    rb.extend(roll.reshape(-1))
    sample = rb.sample()
    assert not sample["next", "terminated"].any() and not sample["terminated"].any()
    assert torch.equal(sample["next", "done"], sample["next", "truncated"])
    assert sample["next", "truncated"].any()  # env 1's time limit is kept


def test_as_truncations_ends_the_episode_where_it_terminates():
    """``as_truncations=True``: the Cartpole episode ends at ``fail`` as before (done, reset), as a
    truncation; TorchRL's GAE then bootstraps from its final observation (ManiSkill's baselines'
    ``bootstrap_at_done="always"``), where the plain env's termination ends the return."""
    from torchrl.objectives.value import GAE

    base = TransformedEnv(ManiSkillEnv("MS-CartpoleBalance-v1", obs_mode="state", max_episode_steps=40), CPUUnbatch())
    env = TransformedEnv(base.base_env, Compose(CPUUnbatch(), IgnoreTerminations(as_truncations=True)))
    try:
        assert env.output_spec == base.output_spec
        assert repr(env.transform[-1]) == "IgnoreTerminations(as_truncations=True)"
        base.set_seed(1)
        torch.manual_seed(0)
        short = base.rollout(100)
        env.set_seed(1)
        torch.manual_seed(0)
        roll = env.rollout(100)
        n = short.shape[0]
        assert n < 40 and short["next", "terminated"][-1].item()
        assert roll.shape == torch.Size([n])  # the episode still ends at the termination
        assert torch.equal(roll["next", "observation"], short["next", "observation"])
        assert not roll["next", "terminated"].any()
        assert torch.equal(roll["next", "done"], short["next", "done"])
        assert torch.equal(roll["next", "truncated"], short["next", "terminated"] | short["next", "truncated"])

        value = torch.nn.Linear(roll["observation"].shape[-1], 1)
        from tensordict.nn import TensorDictModule

        critic = TensorDictModule(value, in_keys=["observation"], out_keys=["state_value"])
        gae = GAE(gamma=0.9, lmbda=0.95, value_network=critic)
        with torch.no_grad():
            last_value = value(roll["next", "observation"][-1])
            ours, plain = gae(roll.clone())["value_target"][-1], gae(short.clone())["value_target"][-1]
        reward = roll["next", "reward"][-1]
        torch.testing.assert_close(ours, reward + 0.9 * last_value)  # bootstrapped
        torch.testing.assert_close(plain, reward)  # the termination ends the return
    finally:
        base.close()


def test_as_truncations_on_nested_keys_and_stored_data():
    env = TransformedEnv(
        ToyEnv([2, 4, 3], terminate=[True, False, True], multi_agent=True), IgnoreTerminations(as_truncations=True)
    )
    ref = ToyEnv([2, 4, 3], terminate=[True, False, True], multi_agent=True)
    check_env_specs(env)
    roll = env.rollout(6, break_when_any_done=False)
    expected = ref.rollout(6, break_when_any_done=False)
    for prefix in ((), ("agents",)):
        term, trunc, done = (roll[("next", *prefix, k)] for k in ("terminated", "truncated", "done"))
        ref_term, ref_trunc, ref_done = (expected[("next", *prefix, k)] for k in ("terminated", "truncated", "done"))
        assert ref_term.any() and not term.any()
        assert torch.equal(done, ref_done)
        assert torch.equal(trunc, ref_trunc | ref_term)
    data = TensorDict(
        terminated=torch.tensor([[True], [False]]),
        truncated=torch.tensor([[False], [True]]),
        done=torch.tensor([[True], [True]]),
        batch_size=[2],
    )
    out = IgnoreTerminations(as_truncations=True)(data.clone())
    assert out["terminated"].tolist() == [[False], [False]]
    assert out["truncated"].tolist() == [[True], [True]]
    assert out["done"].tolist() == [[True], [True]]
