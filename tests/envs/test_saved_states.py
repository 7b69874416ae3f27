"""Saved states are checked before anything reaches the sim (issue 33): their batch, keys, shapes
and dtypes against ``env.get_state()``'s layout, with an error naming what differs. A bad state
never leaves the batched CPU env unusable, and a worker's own error closes the env with an error
that says so, after which a new env can be made.

Oracle: the env's own ``get_state()`` rows, and observations after ``reset_to_state`` against those
of the seeded resets the states were taken at.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from maniskill_torchrl import ManiSkillEnv
from support.helpers import close_envs


@pytest.fixture(scope="module")
def pair():
    """A 2-env batched CPU env (one worker) and a single env of the same task."""
    envs = (
        ManiSkillEnv("PickCube-v1", num_envs=2, obs_mode="state", sim_backend="cpu"),
        ManiSkillEnv("PickCube-v1", obs_mode="state", sim_backend="cpu"),
    )
    yield envs
    close_envs(envs)


def test_a_state_of_another_batch_is_refused_and_the_env_goes_on(pair):
    batched, single = pair
    start = batched.reset(seed=3)
    with pytest.raises(
        ValueError, match=r"scene_state\['actors'\]\['cube'\] has shape \[1, 13\]; this env takes \[2, 13\]"
    ):
        batched.reset_to_state(single.get_state())  # a batch-[1] state: killed a worker before
    with pytest.raises(
        ValueError, match=r"has shape \[2, 13\]; this env takes \[1, 13\] \(one row per env\) or \[13\]"
    ):
        single.reset_to_state(batched.get_state())  # was accepted, row 0 used
    # the batched env is still usable, and resets to its own states
    state = batched.get_state()
    batched.rollout(3)
    assert torch.equal(batched.reset_to_state(state)["observation"], start["observation"])


def test_a_state_that_lacks_an_entry_is_refused(pair):
    _, single = pair
    state = single.get_state()
    with pytest.raises(ValueError, match=r"missing \[\('actors', 'cube'\)"):
        single.reset_to_state(state.exclude("actors"))  # the cube would not be restored
    with pytest.raises(ValueError, match=r"unknown \[\('actors', 'other'\)\]"):
        single.reset_to_state(state.clone().set(("actors", "other"), state["actors", "cube"]))


def test_a_misshaped_or_mistyped_entry_is_named(pair):
    _, single = pair
    state = single.get_state()
    cube = state["actors", "cube"]
    bad = state.to_dict()
    bad["actors"]["cube"] = cube[:, :7]
    with pytest.raises(
        ValueError, match=r"scene_state\['actors'\]\['cube'\] has shape \[1, 7\]; this env takes \[1, 13\]"
    ):
        single.reset_to_state(bad)
    as_int = state.clone()
    as_int["actors", "cube"] = cube.to(torch.int64)
    with pytest.raises(ValueError, match=r"scene_state\['actors'\]\['cube'\] has dtype torch.int64"):
        single.reset_to_state(as_int)
    with pytest.raises(TypeError, match="scene_state must be a TensorDict or a dict of tensors"):
        single.reset_to_state([1, 2, 3])


def test_one_envs_row_resets_every_env(pair):
    """One env's state without a batch dim (a trajectory file's row), as a TensorDict or a plain dict:
    every env being reset takes it, on batch [N] and [1]."""
    batched, single = pair
    want = single.reset(seed=8)["observation"][0]
    row = single.get_state()[0]
    single.rollout(2)
    assert torch.equal(single.reset_to_state(row.to_dict())["observation"][0], want)
    obs = batched.reset_to_state(row)["observation"]
    assert obs.shape[0] == 2 and all(torch.equal(o, want) for o in obs)
    # a partial reset reads the rows of the envs being reset only
    other = single.reset(seed=9)["observation"][0]
    both = batched.get_state()
    both[1] = single.get_state()[0]
    mask = TensorDict({"_reset": torch.tensor([[False], [True]])}, batch_size=[2])
    assert torch.equal(batched.reset(mask, set_state=True, scene_state=both)["observation"][1], other)


def test_a_worker_error_closes_the_env_with_a_clear_error():
    """A worker's own exception (here: asked for a method it lacks) is reported as such, the env
    is then closed with an error that says why, and a new env can be made."""
    env = ManiSkillEnv("PickCube-v1", num_envs=2, obs_mode="state", sim_backend="cpu")
    try:
        env.reset(seed=0)
        with pytest.raises(RuntimeError, match=r"worker\(s\) of sub-env\(s\) \[1\] raised AttributeError"):
            env.unwrapped.call("no_such_method")
        with pytest.raises(RuntimeError, match=r"is closed \(worker\(s\) of sub-env\(s\) \[1\] raised"):
            env.rollout(2)  # was: AttributeError: 'NoneType' object has no attribute 'send'
    finally:
        env.close()
    again = ManiSkillEnv("PickCube-v1", num_envs=2, obs_mode="state", sim_backend="cpu")
    try:
        assert again.rollout(2)["next", "observation"].shape[:2] == (2, 2)
    finally:
        again.close()
