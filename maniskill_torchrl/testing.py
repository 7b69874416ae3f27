"""Assertions for tests of ManiSkill tasks and pipelines run through this library: the library's
own suite uses them, and so can yours (a task you registered with ``@register_env``, a pipeline).

- :func:`assert_tensordict_equal`: two TensorDicts equal to the bit, with an error that names the
  first differing entry and what differs.
- :func:`assert_on_device`: every leaf of a TensorDict (or a tensor, a nested mapping, a tuple
  or list of them) on one device, with an error that lists the leaves elsewhere.
- :func:`check_maniskill_env`: a task through :class:`~maniskill_torchrl.ManiSkillEnv` against
  raw ManiSkill (and, for one env, the gym shim against ManiSkill's ``CPUGymWrapper``), with the
  same seeds and actions, resets included, and every output against the env's specs and device.

The two assertions are written in ``maniskill_torchrl._internal.assertions`` (no TorchRL or ManiSkill
import); this module exports them beside the env check.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from maniskill_torchrl._internal.assertions import (
    assert_on_device,
    assert_tensordict_equal,
    leaf_keys,
    tensor_difference,
)

__all__ = ["assert_on_device", "assert_tensordict_equal", "check_maniskill_env"]


def check_maniskill_env(
    env_id: str,
    *,
    steps: int = 50,
    seed: int = 0,
    num_envs: int = 1,
    **maniskill_kwargs: Any,
) -> None:
    """Checks a ManiSkill task through this library against ManiSkill itself, to the bit, and
    every output against the env's specs.

    1. A ``ManiSkillEnv(env_id, num_envs=..., **maniskill_kwargs)`` and raw ManiSkill
       (``gym.make``; on the CPU sim with ``num_envs > 1``, one raw env per sub-env, sub-env
       ``i`` seeded ``s + i`` as the library does) take ``steps`` steps with the same random
       actions; whenever an env is done, all of them are reset with the next seed, on both sides.
       At every reset and step:

       - every leaf of the output is on ``env.device`` (:func:`assert_on_device`);
       - every observation entry has its spec's dtype and shape and is in it
         (``observation_spec[key].is_in``), and so do the reward and done entries (reward and
         done specs); the task's raw reward must hold one value per env;
       - the observation, reward (as float32), ``terminated``, ``truncated``, ``done`` and tensor
         infos equal raw ManiSkill's.
    2. :func:`torchrl.envs.utils.check_env_specs` on the same env, after the comparison (it steps
       its env).
    3. With ``num_envs=1`` (CPU sim): the gym shim's ``CPUGymWrapper`` against ManiSkill's, the
       same way: observations, rewards, flags and infos equal in value, dtype and Python type.

    Works for any registered task, your own included: register it (``@register_env``) before
    calling. Raises an :class:`AssertionError` at the first difference, naming the entry, the
    step (``step t``) or reset (``reset k with seed s``) and, for a spec violation, the spec.

    Args:
        env_id: a registered ManiSkill task.

    Keyword Args:
        steps (int): steps per comparison (resets included).
        seed (int): the first reset's seed; reset ``k`` uses ``seed + 1000 * k``.
        num_envs (int): the batch.
        **maniskill_kwargs: passed to ``gym.make`` on every side (``obs_mode``, ``sim_backend``...).
    """
    import gymnasium as gym
    from torchrl.envs.utils import check_env_specs

    from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv
    from maniskill_torchrl.envs.engine_env import ManiSkillEnv

    where = f"check_maniskill_env({env_id!r}, num_envs={num_envs})"
    env = ManiSkillEnv(env_id, num_envs=num_envs, **maniskill_kwargs)
    raws: list = []
    try:
        per_sub_env = isinstance(env.unwrapped, CPUVectorEnv)
        on_gpu = env.gpu_sim_enabled
        gym_kwargs = dict(maniskill_kwargs)
        if per_sub_env:
            gym_kwargs["sim_backend"] = "physx_cpu"
            raws = [gym.make(env_id, num_envs=1, **gym_kwargs) for _ in range(num_envs)]
        else:
            raws = [gym.make(env_id, num_envs=num_envs, **gym_kwargs)]
        _compare_with_raw(env, raws, steps, seed, per_sub_env, where)
        for raw in raws:
            raw.close()
        raws = []
        check_env_specs(env, seed=seed)  # after the comparison, which its steps would have shifted
    finally:
        env.close()
        for raw in raws:
            raw.close()
    if num_envs == 1 and not on_gpu:
        _compare_shim(env_id, steps, seed, maniskill_kwargs, where)


def _spec_text(spec: Any) -> str:
    return f"{type(spec).__name__}(shape={list(spec.shape)}, dtype={spec.dtype}, device={spec.device})"


class _SpecCheck:
    """An env's observation, reward and done specs, leaf by leaf, against its outputs."""

    def __init__(self, env: Any) -> None:
        self.device = env.device
        self.batch_dims = len(env.batch_size)
        self.observations = list(env.observation_spec.items(True, True))
        self.rewards = list(env.full_reward_spec.items(True, True))
        self.dones = list(env.full_done_spec.items(True, True))

    def __call__(self, td: TensorDictBase, where: str, *, step: bool) -> None:
        """Raises an AssertionError naming the first entry of ``td`` (a reset's output, or a
        step's ``"next"``) off its spec or off the env's device."""
        assert_on_device(td, self.device, msg=where)
        for group, specs in (("observation", self.observations), ("reward", self.rewards), ("done", self.dones)):
            if group == "reward" and not step:
                continue
            for key, spec in specs:
                value = td.get(key, None)
                if value is None:
                    if group == "done" and not step:  # a reset may leave its done flags out
                        continue
                    raise AssertionError(f"{where}: {key!r} is missing; the {group} spec declares {_spec_text(spec)}")
                if not isinstance(value, torch.Tensor):
                    continue
                if value.dtype != spec.dtype or value.shape != spec.shape:
                    raise AssertionError(
                        f"{where}: {key!r} has dtype {value.dtype} and shape {list(value.shape)}, "
                        f"off its {group} spec {_spec_text(spec)}"
                    )
                if not spec.is_in(value):
                    raise AssertionError(
                        f"{where}: {key!r} is not in its {group} spec {spec!r} (a value out of its bounds)"
                    )

    def raw_reward(self, reward: Any, batch: int, where: str) -> None:
        """Raw ManiSkill's reward must hold as many values per env as the reward spec."""
        (key, spec), *_ = self.rewards
        per_env = spec.shape[self.batch_dims :].numel()
        got = torch.as_tensor(reward)
        if got.numel() != batch * per_env:
            raise AssertionError(
                f"{where}: {key!r}: the task's reward has shape {list(got.shape)} "
                f"({got.numel() // max(batch, 1)} values per env), but the reward spec "
                f"{_spec_text(spec)} holds {per_env} per env. A ManiSkill task returns one reward "
                "per env: compute_dense_reward (and compute_normalized_dense_reward) must return "
                "shape [num_envs]."
            )


def _seeds(seed: int):
    k = 0
    while True:
        yield seed + 1000 * k
        k += 1


def _as_tensordict(tree: Mapping, batch: int) -> TensorDict:
    return TensorDict(
        {k: _as_tensordict(v, batch) if isinstance(v, Mapping) else v for k, v in tree.items()},
        batch_size=[batch],
    )


def _raw_step_tensordict(env: Any, obs: Any, info: Mapping, reward=None, terminated=None, truncated=None) -> TensorDict:
    """What the library's env must return for one raw ManiSkill step (or reset: no reward), on
    ``env.device`` (raw ManiSkill may return pictures on CUDA and the rest on the CPU: where the
    library's outputs are is checked on its own, by :func:`assert_on_device`)."""
    n = env.batch_size.numel() if env.batch_size else 1
    entries: dict = {}
    if isinstance(obs, Mapping):
        entries.update(_as_tensordict(obs, n).to_dict())
    else:
        entries["observation"] = obs
    for key, td_key in env.info_entries.items():
        entries[td_key] = info[key]
    if reward is not None:
        entries["reward"] = reward.to(torch.float32).reshape(n, 1)
        entries["terminated"] = terminated.reshape(n, 1)
        entries["truncated"] = truncated.reshape(n, 1)
        entries["done"] = (terminated | truncated).reshape(n, 1)
    return _as_tensordict(entries, n).to(env.device)


def _cat(parts: list) -> Any:
    """One raw env's outputs, or several single envs' joined along the batch (what the batched
    CPU env returns); entries without a batch dim (0-d tensors, python values) from the first."""
    if len(parts) == 1:
        return parts[0]
    if isinstance(parts[0], Mapping):
        return {k: _cat([p[k] for p in parts]) for k in parts[0]}
    if isinstance(parts[0], torch.Tensor) and parts[0].ndim > 0:
        return torch.cat(parts)
    return parts[0]


def _raw_reset(raws: list, seed: int, per_sub_env: bool) -> tuple:
    outs = [raw.reset(seed=seed + i if per_sub_env else seed) for i, raw in enumerate(raws)]
    return _cat([o[0] for o in outs]), _cat([o[1] for o in outs])


def _raw_step(raws: list, action: Any) -> tuple:
    def plain(a: Any) -> Any:  # ManiSkill takes a dict of tensors for several agents
        return a.to_dict() if isinstance(a, TensorDictBase) else a

    if len(raws) == 1:
        return raws[0].step(plain(action))
    outs = [raw.step(plain(action[i : i + 1])) for i, raw in enumerate(raws)]
    return tuple(_cat([o[j] for o in outs]) for j in range(5))


def _compare_with_raw(env: Any, raws: list, steps: int, seed: int, per_sub_env: bool, where: str) -> None:
    seeds = _seeds(seed)
    check = _SpecCheck(env)
    n = env.batch_size.numel() if env.batch_size else 1
    g = torch.Generator().manual_seed(seed)

    def reset(k: int) -> TensorDictBase:
        s = next(seeds)
        at = f"{where}, reset {k} with seed {s}"
        td = env.reset(seed=s)
        check(td, at, step=False)
        obs, info = _raw_reset(raws, s, per_sub_env)
        expected = _raw_step_tensordict(env, obs, info)
        assert_tensordict_equal(td.select(*leaf_keys(expected)), expected, msg=at)
        return td

    resets = 0
    td = reset(resets)
    for t in range(steps):
        at = f"{where}, step {t}"
        td = td.set("action", _random_action(env, g))
        action = td.get("action")
        obs, reward, terminated, truncated, info = _raw_step(raws, action.clone())
        check.raw_reward(reward, n, at)
        td = env.step(td)
        check(td["next"], at, step=True)
        expected = _raw_step_tensordict(env, obs, info, reward, terminated, truncated)
        assert_tensordict_equal(td["next"].select(*leaf_keys(expected)), expected, msg=at)
        td = td["next"].exclude("reward", "terminated", "truncated", "done")
        if expected["done"].any():
            resets += 1
            td = reset(resets)


def _random_action(env: Any, g: torch.Generator) -> Any:
    spec = env.full_action_spec["action"]

    def draw(s):
        low, high = s.space.low, s.space.high
        return (low + (high - low) * torch.rand(s.shape, generator=g)).to(s.dtype)

    if hasattr(spec, "keys") and not hasattr(spec, "space"):
        return TensorDict({k: draw(spec[k]) for k in spec.keys()}, batch_size=env.batch_size)
    return draw(spec)


def _compare_shim(env_id: str, steps: int, seed: int, maniskill_kwargs: dict, where: str) -> None:
    import gymnasium as gym
    from mani_skill.utils.wrappers import CPUGymWrapper as Theirs

    from maniskill_torchrl.wrappers.gymnasium import CPUGymWrapper as Ours

    kwargs = dict(maniskill_kwargs, num_envs=1)
    theirs = Theirs(gym.make(env_id, **kwargs), record_metrics=True)
    ours = Ours(gym.make(env_id, **kwargs), record_metrics=True)
    try:
        seeds = _seeds(seed)
        space = theirs.action_space
        rng = np.random.default_rng(seed)
        s = next(seeds)
        _same(ours.reset(seed=s), theirs.reset(seed=s), f"{where}, gym shim reset with seed {s}")
        for t in range(steps):
            action = _space_sample(space, rng)
            out = ours.step(action)
            _same(out, theirs.step(action), f"{where}, gym shim step {t}")
            if out[2] or out[3]:
                s = next(seeds)
                _same(ours.reset(seed=s), theirs.reset(seed=s), f"{where}, gym shim reset with seed {s}")
    finally:
        theirs.close()
        ours.close()


def _space_sample(space: Any, rng: np.random.Generator) -> Any:
    import gymnasium as gym

    if isinstance(space, gym.spaces.Dict):
        return {k: _space_sample(v, rng) for k, v in space.spaces.items()}
    return rng.uniform(space.low, space.high).astype(space.dtype)


def _same(a: Any, b: Any, where: str) -> None:
    """Equal in value, dtype and Python type, through dicts and tuples."""
    if type(a) is not type(b):
        raise AssertionError(f"{where}: {type(a).__name__} != expected {type(b).__name__}")
    if isinstance(a, Mapping):
        if list(a) != list(b):
            raise AssertionError(f"{where}: keys {list(a)} != expected {list(b)}")
        for k in a:
            _same(a[k], b[k], f"{where}[{k!r}]")
    elif isinstance(a, (tuple, list)):
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, (np.ndarray, np.generic)):
        if a.dtype != b.dtype or a.shape != b.shape or a.tobytes() != b.tobytes():
            raise AssertionError(f"{where}: {a!r} != expected {b!r}")
    elif isinstance(a, torch.Tensor):
        difference = tensor_difference(a, b)
        if difference is not None:
            raise AssertionError(f"{where}: {difference}")
    elif a != b and not (isinstance(a, float) and np.isnan(a) and np.isnan(b)):
        raise AssertionError(f"{where}: {a!r} != expected {b!r}")
