"""ManiSkill's documented usage of its two wrappers runs with a one-word change of its imports.

ManiSkill documents ``from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper`` and
``from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper``. The same text with
``mani_skill.utils.wrappers`` replaced by ``maniskill_torchrl.wrappers`` (nothing else) imports the
shim's classes and gives ManiSkill's episode bit for bit.
"""

from __future__ import annotations

import pytest

from support.helpers import assert_same

# ManiSkill's documented lines (its wrappers' pages), then a seeded episode with seeded actions.
DOCUMENTED = """
import gymnasium as gym
import mani_skill.envs
from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper
from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

env = gym.make("PickCube-v1", num_envs=1, obs_mode="state", max_episode_steps=12)
env = ActionRepeatWrapper(env, repeat=2)
env = CPUGymWrapper(env, ignore_terminations=True, record_metrics=True)
env.action_space.seed(0)
trace = [env.reset(seed=3)]
for _ in range(8):
    trace.append(env.step(env.action_space.sample()))
trace.append(env.reset(seed=4))
trace.append(env.step(env.action_space.sample()))
env.close()
"""


def _run(source: str) -> dict:
    namespace: dict = {}
    exec(compile(source, "<documented usage>", "exec"), namespace)
    return namespace


@pytest.mark.filterwarnings("ignore:.*precision lowered by casting")
def test_documented_usage_with_one_word_changed_is_bit_for_bit_maniskills():
    changed = DOCUMENTED.replace("mani_skill.utils.wrappers", "maniskill_torchrl.wrappers")
    assert changed.count("maniskill_torchrl.wrappers") == 2
    ours, theirs = _run(changed), _run(DOCUMENTED)
    assert ours["CPUGymWrapper"].__module__ == "maniskill_torchrl.wrappers.gymnasium"
    assert ours["ActionRepeatWrapper"].__module__ == "maniskill_torchrl.wrappers.action_repeat"
    assert theirs["CPUGymWrapper"].__module__ == "mani_skill.utils.wrappers.gymnasium"
    assert "episode" in ours["trace"][8][4]  # the metrics were recorded, and compared below
    assert_same(theirs["trace"], ours["trace"], "trace")


def test_package_level_imports_are_the_same_classes():
    from maniskill_torchrl import wrappers
    from maniskill_torchrl.wrappers.action_repeat import ActionRepeatWrapper
    from maniskill_torchrl.wrappers.gymnasium import CPUGymWrapper

    assert wrappers.CPUGymWrapper is CPUGymWrapper
    assert wrappers.ActionRepeatWrapper is ActionRepeatWrapper
