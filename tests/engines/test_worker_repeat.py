"""ActionRepeat directly on the batched CPU env: the repeat runs inside the worker processes.

``TransformedEnv(ManiSkillEnv(env_id, num_envs=N), ActionRepeat(k))`` on the CPU sim hands
each outer step to the workers (``CPUVectorEnv.set_repeat``): one round trip per outer step,
and a sub-env whose episode ends mid-repeat is not stepped further. The oracle is ManiSkill's
own ``ActionRepeatWrapper`` over N independent raw envs with the same seeds and actions.

PushCube-v1 with ``max_episode_steps=5`` and ``repeat=3``: an episode ends at inner step 2
of its second outer step; a partial reset of sub-env 1 after the first outer step puts the
two sub-envs out of phase, so one ends mid-repeat while the other runs on.
"""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper
from torchrl.envs import Compose, StepCounter, TransformedEnv
from torchrl.envs.utils import step_mdp

from maniskill_torchrl import ActionRepeat, ManiSkillEnv
from support.helpers import assert_same, clone_tree, make_gym_env, random_actions, tensor_infos

N, REPEAT = 2, 3
PUSH = dict(obs_mode="state", max_episode_steps=5, sim_backend="cpu")
ACTIONS = random_actions(gym.spaces.Box(-1, 1, (N, 8)), 8, seed=2)


@pytest.fixture(scope="module")
def push():
    env = ManiSkillEnv("PushCube-v1", num_envs=N, **PUSH)
    yield env
    env.close()


class StepSpy:
    """Counts the round trips: ``CPUVectorEnv.step`` calls (one per AsyncVectorEnv step)."""

    def __init__(self, vec):
        self.vec, self.calls, self._step = vec, 0, vec.step

    def __enter__(self):
        def step(action):
            self.calls += 1
            return self._step(action)

        self.vec.step = step  # an instance attribute: ManiSkillWrapper calls self._env.step
        return self

    def __exit__(self, *exc):
        del self.vec.step


def worker_elapsed(env) -> list[int]:
    """Each sub-env's own ManiSkill ``elapsed_steps``: the physics steps it really took."""
    return [int(e) for e in env.unwrapped.call("elapsed_steps")]


def assert_sub_env(td, i, obs, info, what, reward=None, terminated=None, truncated=None):
    """Row ``i`` of ``td`` holds the raw env's data, bit for bit (dtypes included)."""
    assert_same(td["observation"][i], obs[0], f"{what}: observation")
    for key, want in tensor_infos(info).items():
        assert_same(td[key][i], want[0], f"{what}: {key}")
    if reward is not None:
        assert_same(td["reward"][i], reward, f"{what}: reward")
        assert_same(td["terminated"][i], terminated, f"{what}: terminated")
        assert_same(td["truncated"][i], truncated, f"{what}: truncated")
        assert_same(td["done"][i], terminated | truncated, f"{what}: done")


def run_schedule(env):
    """Seeded reset, a partial reset of sub-env 1 after the first outer step, and a seeded
    partial reset of every sub-env that ended; returns the step tensordicts."""
    out = []
    td = env.reset(seed=11)
    for t, action in enumerate(ACTIONS):
        td = env.step(td.set("action", action))
        out.append(td.clone())
        td = step_mdp(td)
        reset = td["done"].squeeze(-1).clone()
        if t == 0:
            reset[1] = True
        if reset.any():
            td = env.reset(td.set("_reset", reset.unsqueeze(-1)), seed=100 + t)
    return out


def test_each_sub_env_is_maniskills_action_repeat(push):
    env = TransformedEnv(push, ActionRepeat(REPEAT))
    oracles = [ActionRepeatWrapper(make_gym_env("PushCube-v1", **PUSH), REPEAT) for _ in range(N)]
    vec = push.unwrapped
    ends = []  # (outer step, sub-env, inner step at which its episode ended)
    try:
        td = env.reset(seed=11)
        for i, o in enumerate(oracles):
            obs, info = clone_tree(o.reset(seed=11 + i))
            assert_sub_env(td, i, obs, info, "reset")
        for t, action in enumerate(ACTIONS):
            before = [int(o.unwrapped.elapsed_steps) for o in oracles]
            with StepSpy(vec) as spy:
                td = env.step(td.set("action", action))
            assert spy.calls == 1, f"outer step {t}: {spy.calls} round trips, expected 1"
            assert vec.repeat == REPEAT
            for i, o in enumerate(oracles):
                obs, reward, terminated, truncated, info = clone_tree(o.step(action[i : i + 1]))
                assert_sub_env(td["next"], i, obs, info, f"outer step {t}, sub-env {i}", reward, terminated, truncated)
                if bool(terminated | truncated):
                    ends.append((t, i, int(info["elapsed_steps"]) - before[i]))
            # A sub-env that ended mid-repeat was not stepped after its end.
            assert worker_elapsed(push) == [int(o.unwrapped.elapsed_steps) for o in oracles], t
            td = step_mdp(td)
            reset = td["done"].squeeze(-1).clone()
            if t == 0:
                reset[1] = True  # out of phase: the sub-envs end at different outer steps
            if reset.any():
                seed = 100 + t
                td = env.reset(td.set("_reset", reset.unsqueeze(-1)), seed=seed)
                for i, o in enumerate(oracles):
                    if reset[i]:
                        obs, info = clone_tree(o.reset(seed=seed + i))
                        assert_sub_env(td, i, obs, info, f"reset after outer step {t}")
    finally:
        for o in oracles:
            o.close()
    mid = [(t, i) for t, i, inner in ends if inner < REPEAT]
    assert len(mid) >= 3, f"episodes should end mid-repeat: {ends}"
    assert len({t for t, _ in mid}) == len(mid), f"the sub-envs should end at different outer steps: {ends}"


def test_same_bits_as_the_inner_loop(push):
    """A transform before ActionRepeat keeps the TorchRL inner loop (one round trip per inner
    step, finished sub-envs stepped and discarded): same data, more round trips."""
    with StepSpy(push.unwrapped) as spy:
        fast = run_schedule(TransformedEnv(push, ActionRepeat(REPEAT)))
    assert spy.calls == len(ACTIONS)
    with StepSpy(push.unwrapped) as spy:
        loop = run_schedule(TransformedEnv(push, Compose(StepCounter(), ActionRepeat(REPEAT))))
    assert push.unwrapped.repeat == 1, "no worker repeat with a transform in between"
    assert spy.calls > 2 * len(ACTIONS), spy.calls
    for t, (a, b) in enumerate(zip(fast, loop)):
        b = b.exclude("step_count", ("next", "step_count"))
        assert set(a.keys(True, True)) == set(b.keys(True, True)), t
        for key in a.keys(True, True):
            assert_same(a[key], b[key], f"outer step {t}: {key}")


def test_removing_the_transform_restores_plain_steps(push):
    env = TransformedEnv(push, ActionRepeat(REPEAT))
    vec = push.unwrapped
    td = env.reset(seed=3)
    td = step_mdp(env.step(td.set("action", ACTIONS[0])))
    assert worker_elapsed(push) == [3, 3] and vec.repeat == REPEAT

    # The base env stepped directly, the transform still in place: one step.
    with StepSpy(vec) as spy:
        td = step_mdp(push.step(td.set("action", ACTIONS[1])))
    assert spy.calls == 1 and vec.repeat == 1
    assert worker_elapsed(push) == [4, 4] and td["elapsed_steps"].tolist() == [4, 4]

    env = TransformedEnv(push, Compose(ActionRepeat(REPEAT)))
    td = env.reset(seed=3)
    env.step(td.set("action", ACTIONS[0]))
    assert worker_elapsed(push) == [3, 3] and vec.repeat == REPEAT
    removed = env.transform.pop()
    assert isinstance(removed, ActionRepeat) and len(env.transform) == 0
    td = step_mdp(env.step(td.set("action", ACTIONS[0])))
    assert worker_elapsed(push) == [4, 4] and vec.repeat == 1

    env.append_transform(ActionRepeat(2))
    td = env.reset(seed=3)
    td = env.step(td.set("action", ACTIONS[0]))
    assert worker_elapsed(push) == [2, 2] and vec.repeat == 2
    assert td["next", "elapsed_steps"].tolist() == [2, 2]


def test_nested_repeats_never_double_repeat(push):
    """ActionRepeat(3) over ActionRepeat(2): the inner one runs in the workers, the outer one
    loops over it: up to 6 physics steps per outer step, 3 round trips."""
    env = TransformedEnv(push, Compose(ActionRepeat(2), ActionRepeat(3)))
    td = env.reset(seed=5)
    with StepSpy(push.unwrapped) as spy:
        td = env.step(td.set("action", ACTIONS[0]))
    # max_episode_steps=5: the third round trip ends the episodes at their first inner step.
    assert spy.calls == 3 and push.unwrapped.repeat == 2
    assert worker_elapsed(push) == [5, 5] and td["next", "elapsed_steps"].tolist() == [5, 5]
    assert td["next", "truncated"].all()


def test_outer_partial_step_keeps_the_inner_loop(push):
    """A ``"_step"`` mask that is not all True (ManiSkillWrapper does not honour it) is not
    handed to the workers: the inner loop keeps the skipped sub-env as it was."""
    env = TransformedEnv(push, ActionRepeat(REPEAT))
    td = env.reset(seed=7)
    td = step_mdp(env.step(td.set("action", ACTIONS[0])))  # delegated: repeat 3 in the workers
    with StepSpy(push.unwrapped) as spy:
        td = env.step(td.set("action", ACTIONS[1]).set("_step", torch.tensor([True, False])))
    # Both stepped together (batch-locked); sub-env 0 reaches its time limit at inner step 2.
    assert spy.calls == 2 and push.unwrapped.repeat == 1
    assert td["next", "elapsed_steps"].tolist() == [5, 4] and worker_elapsed(push) == [5, 5]
