"""``maniskill_torchrl.pipeline.make_env``, the one recipe of the transform stack, and the
docstring examples of the core modules it rests on."""

from __future__ import annotations

import doctest

import pytest
import torch

import maniskill_torchrl._internal.assertions as assertions_module
import maniskill_torchrl._internal.episode_stats as episode_stats_module
import maniskill_torchrl.pipeline as pipeline_module
import maniskill_torchrl.transforms.action_repeat as action_repeat_module
import maniskill_torchrl.transforms.env_states as env_states_module
import maniskill_torchrl.transforms.flatten_action_space as flatten_action_space_module
from maniskill_torchrl import ActionRepeat, EpisodeMetrics, IgnoreTerminations, ManiSkillEnv
from maniskill_torchrl.pipeline import make_env


def _names(env) -> list[str]:
    return [type(t).__name__ for t in env.transform]


def test_single_cpu_worker_stack():
    env = make_env("PickCube-v1", repeat=3, ignore_terminations=True, obs_mode="state", max_episode_steps=10)
    try:
        assert _names(env) == ["IgnoreTerminations", "ActionRepeat", "EpisodeMetrics"]
        assert env.batch_size == torch.Size([]) and env.base_env.batch_size == torch.Size([])
        assert not env.base_env.gpu_sim_enabled
        t = list(env.transform)
        assert isinstance(t[0], IgnoreTerminations)
        assert isinstance(t[1], ActionRepeat) and t[1].repeat == 3 and isinstance(t[2], EpisodeMetrics)
        env.set_seed(0)
        td = env.rollout(4)
        assert td["next", "elapsed_steps"].tolist() == [3, 6, 9, 10]  # the last repeat cut by the time limit
        assert td["next", "episode", "episode_len"].tolist() == [1, 2, 3, 4]  # agent steps
        assert not td["next", "terminated"].any()
    finally:
        env.close()


def test_repeat_one_and_no_metrics_is_the_bare_unbatched_env():
    env = make_env("PickCube-v1", metrics=False, obs_mode="state")
    try:
        assert _names(env) == [] and type(env.base_env) is ManiSkillEnv
        assert env.batch_size == env.base_env.batch_size == torch.Size([])
    finally:
        env.close()


@pytest.mark.parametrize(("bad", "error"), [(0, ValueError), (2.5, TypeError)])
def test_bad_repeat_raises_before_building(bad, error):
    with pytest.raises(error, match="repeat must be"):
        make_env("PickCube-v1", repeat=bad, obs_mode="state")


@pytest.mark.parametrize(
    "module",
    [
        pipeline_module,
        action_repeat_module,
        episode_stats_module,
        assertions_module,
        env_states_module,
        flatten_action_space_module,
    ],
)
def test_docstring_examples(module):
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0, module.__name__
