"""The gym shim's step, counted: what ``CPUGymWrapper(record_metrics=True)`` runs per step.

Counts, not timings (issue 44, item 5): the env's own step is replayed from a recording, so only
the shim and the episode statistics it shares with ``EpisodeMetrics`` are counted. The shim's
statistics run on numpy (``EpisodeStats(arrays="numpy")``): no tensor op, only the torch calls
that turn the env's outputs into numpy. On tensors (``EpisodeMetrics``'), a step of a one-env
batch makes no reshape or view of a tensor already so shaped and no ``TensorDict.get``.
"""

from __future__ import annotations

from collections import Counter

import gymnasium as gym
import pytest
import torch
from tensordict import TensorDictBase
from torch.overrides import TorchFunctionMode

from maniskill_torchrl._internal.episode_stats import EpisodeStats
from maniskill_torchrl.wrappers import CPUGymWrapper
from support.helpers import close_envs, make_gym_env

#: torch calls per metrics step on PickCube-v1 (attribute reads such as ``.shape`` not counted):
#: 8 to turn the env's observation, reward, flag and infos into numpy (as ManiSkill's wrapper), 2
#: to hand the reward and ``success`` to the episode statistics as numpy, none in the statistics
#: and none to hand ``info["episode"]`` out. Before issue 44 item 5: 30, among them 5 reshapes and
#: a view of tensors already so shaped, and 8 ``TensorDict.get`` calls.
MAX_TORCH_CALLS = 10
STEPS = 60


class _Replay(gym.Wrapper):
    """The wrapped env, its steps replayed from ``steps`` (the shim's work alone is counted)."""

    def __init__(self, env: gym.Env, steps: list) -> None:
        super().__init__(env)
        self._steps, self._i = steps, 0

    def step(self, action):
        out = self._steps[self._i % len(self._steps)]
        self._i += 1
        return out

    def reset(self, **kwargs):
        self._i = 0
        return self._steps[0][0], {}


class _Count(TorchFunctionMode):
    """Counts torch calls by name; attribute reads (``.shape``, ``.is_cpu``) apart."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: Counter[str] = Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", str(func))
        if name != "__get__":
            self.calls[name] += 1
        return func(*args, **(kwargs or {}))


@pytest.fixture(scope="module")
def replayed_shim():
    env = make_gym_env("PickCube-v1", obs_mode="state")
    env.reset(seed=0)
    space = env.unwrapped.single_action_space
    space.seed(0)
    steps = [env.step(torch.as_tensor(space.sample()[None])) for _ in range(10)]
    shim = CPUGymWrapper(_Replay(env, steps), ignore_terminations=True, record_metrics=True)
    yield shim, space.sample()
    close_envs([env])


def test_cpu_gym_wrapper_step_ops(replayed_shim, monkeypatch):
    shim, action = replayed_shim
    shim.reset()
    shim.step(action)  # the statistics made on the first step
    gets = Counter()
    get = TensorDictBase.get

    def counted_get(self, *args, **kwargs):
        gets["get"] += 1
        return get(self, *args, **kwargs)

    monkeypatch.setattr(TensorDictBase, "get", counted_get)
    with _Count() as count:
        for _ in range(STEPS):
            shim.step(action)
    per_step = {name: n / STEPS for name, n in count.calls.items()}
    assert set(per_step) == {"numpy"}, per_step  # no tensor op: only the env's outputs to numpy
    assert gets["get"] == 0
    assert sum(per_step.values()) <= MAX_TORCH_CALLS, per_step


def test_episode_stats_tensor_step_ops():
    """The statistics on tensors (``EpisodeMetrics``'), one env on the CPU: no reshape or view of
    a tensor already so shaped, no ``TensorDict.get``; the same entries as on numpy."""
    rewards = torch.linspace(-1, 1, 20)
    flags = torch.arange(20) % 7 == 3
    on_tensors = EpisodeStats((1,), has_success=True, has_fail=False)
    on_numpy = EpisodeStats((1,), has_success=True, has_fail=False, arrays="numpy")
    ep = on_tensors.update(None, rewards[:1], flags[:1])
    ep_np = on_numpy.update(None, rewards[:1].numpy(), flags[:1].numpy())
    gets = Counter()
    get = TensorDictBase.get

    def counted_get(self, *args, **kwargs):
        gets["get"] += 1
        return get(self, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(TensorDictBase, "get", counted_get)
        with _Count() as count:
            for i in range(1, 20):
                ep = on_tensors.update(ep, rewards[i : i + 1], flags[i : i + 1])
    assert not {"reshape", "view", "clone", "contiguous"} & count.calls.keys(), count.calls
    assert gets["get"] == 0
    for i in range(1, 20):
        ep_np = on_numpy.update(ep_np, rewards[i : i + 1].numpy(), flags[i : i + 1].numpy())
    assert list(ep.keys()) == list(ep_np)
    for name, value in ep_np.items():
        assert ep[name].numpy().dtype == value.dtype and ep[name].numpy().tobytes() == value.tobytes(), name
