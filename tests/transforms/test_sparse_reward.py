"""``SparseReward``: ManiSkill's sparse reward (``success - fail``) written from the step's infos,
on stored data and on an env, equal to what ManiSkill's ``reward_mode="sparse"`` gives."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.testing import assert_tensordict_equal
from maniskill_torchrl.transforms import SparseReward
from support.helpers import seeded_rollout


def test_stored_transitions_get_success_minus_fail():
    steps = TensorDict(
        {
            "next": {
                "success": torch.tensor([False, True, True, False]),
                "fail": torch.tensor([False, False, True, True]),
                "reward": torch.full((4, 1), 7.0),  # a dense reward the file recorded: replaced
            }
        },
        [4],
    )
    out = SparseReward()(steps)
    assert out["next", "reward"].dtype == torch.float32
    assert out["next", "reward"].tolist() == [[0.0], [1.0], [0.0], [-1.0]]


def test_one_info_is_enough_and_none_is_an_error():
    only_success = TensorDict({"next": {"success": torch.tensor([True, False])}}, [2])
    assert SparseReward()(only_success)["next", "reward"].tolist() == [[1.0], [0.0]]
    only_fail = TensorDict({"next": {"fail": torch.tensor([True])}}, [1])
    assert SparseReward()(only_fail)["next", "reward"].tolist() == [[-1.0]]
    with pytest.raises(KeyError, match="success"):
        SparseReward()(TensorDict({"next": {"done": torch.zeros(2, 1, dtype=torch.bool)}}, [2]))


def test_on_a_dense_env_it_gives_maniskills_sparse_reward():
    """A dense-reward env with the transform steps as the same env made with reward_mode="sparse"."""
    rollouts = []
    for reward_mode, transform in (("normalized_dense", SparseReward()), ("sparse", None)):
        env = ManiSkillEnv("PushCube-v1", obs_mode="state", sim_backend="physx_cpu", reward_mode=reward_mode)
        env = TransformedEnv(env, transform) if transform is not None else env
        rollouts.append(seeded_rollout(env, 5, seed=0))
    got, want = rollouts
    assert_tensordict_equal(got, want)


def test_against_torchrls_success_reward():
    """TorchRL 0.14.1's ``SuccessReward`` (``torchrl.envs.transforms``) is the success term alone: the same values
    where no step fails, none of the fail term (-1) and a reward shaped as the success entry ([N], not the env's
    [N, 1]). What ManiSkill's ``reward_mode="sparse"`` gives is ``SparseReward``'s (the docstring says so)."""
    from torchrl.envs.transforms import SuccessReward

    success = torch.tensor([False, True, True, False])
    fail = torch.tensor([False, False, True, True])
    ours = SparseReward()(TensorDict({"success": success, "fail": fail}, [4]))["reward"]
    theirs = SuccessReward()(TensorDict({"success": success, "fail": fail}, [4]))["reward"]
    assert ours.shape == (4, 1) and theirs.shape == (4,)
    assert ours.squeeze(-1).tolist() == [0.0, 1.0, 0.0, -1.0]
    assert theirs.tolist() == [0.0, 1.0, 1.0, 0.0]  # no fail term
    no_fail = ~fail
    assert torch.equal(ours.squeeze(-1)[no_fail], theirs[no_fail].to(ours.dtype))
