"""``env.to(device)`` and the copies of a step, on a stand-in CUDA machine (``tests/support/cuda_double.py``).

Not collected by ``pytest tests``: ``tests/gpu/test_cuda_machine.py`` runs this file with
``tests/gpu/cuda_machine_cases.py`` in one subprocess under the double.

- ``env.to(device)`` at any time, both ways, keeps the device rule: every leaf of every output
  (steps, resets, ``"pixels"``, ``render()``, infos, saved states) on the new device, actions taken
  there, the same values; at batch ``[1]``, ``[]`` and N (the batched CPU env), with transforms,
  through ``SerialEnv.to``, ``ParallelEnv.to`` and ``Collector(env, policy, device=...)``.
- A CPU-sim step with ``device="cuda"`` makes one host-to-device copy (pictures already on the
  device copied there), no host sync, and ``EpisodeMetrics`` on top one more copy up, nothing down.
"""

from __future__ import annotations

import functools
import os

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import SerialEnv, TransformedEnv
from torchrl.envs.utils import step_mdp

if os.environ.get("MANISKILL_TORCHRL_CUDA_DOUBLE") != "1":
    pytest.skip("runs under the CUDA double only (tests/gpu/test_cuda_machine.py)", allow_module_level=True)

from maniskill_torchrl import EpisodeMetrics, ManiSkillEnv  # noqa: E402
from maniskill_torchrl.parallel import ManiSkillParallelEnv  # noqa: E402
from maniskill_torchrl.testing import assert_on_device, assert_tensordict_equal  # noqa: E402
from support import cuda_double  # noqa: E402
from support.cuda_double import DEVICE  # noqa: E402
from support.helpers import closed_after_test  # noqa: E402, F401  (closed_after_test: the envs fixture)

CPU = torch.device("cpu")
ENV_ID = "PickCube-v1"
STATE = dict(obs_mode="state", max_episode_steps=4, sim_backend="cpu")
PIXELS = dict(
    STATE,
    render_mode="rgb_array",
    from_pixels=True,
    human_render_camera_configs=dict(width=16, height=16),
)
RGB = dict(STATE, obs_mode="rgb", sensor_configs=dict(width=16, height=16))
STEPS = 5  # 4-step episodes: a done and a reset inside


def _make(envs: list, **kwargs):
    env = ManiSkillEnv(ENV_ID, **kwargs)
    envs.append(env)
    return env


def _policy(env):
    """Zero-ish actions made on the env's device (as a GPU policy's), one fixed sequence."""
    gen = torch.Generator().manual_seed(0)

    def policy(td):
        action = torch.rand(env.action_spec.shape, generator=gen) * 2 - 1
        return td.set("action", action.to(env.device))

    return policy


def _run(env) -> list:
    """Every kind of output of ``env``, after a seeded reset: a rollout, a saved state, the reset
    to it, render() where it renders."""
    env.set_seed(5)
    td = env.rollout(STEPS, _policy(env), break_when_any_done=False)
    state = env.get_state()
    out = [td, state, env.reset_to_state(state)]
    if "pixels" in td.keys():
        out.append(env.render())
    return out


def _same(got: list, want: list) -> None:
    for a, b in zip(got, want):
        if isinstance(a, torch.Tensor):
            assert torch.equal(a.cpu(), b.cpu())
        else:
            assert_tensordict_equal(a.cpu(), b.cpu())


@pytest.mark.parametrize(
    "kwargs",
    [dict(PIXELS), dict(STATE, batch_size=[]), dict(STATE, num_envs=2, device=DEVICE)],
    ids=["batch1-pixels", "unbatched", "batched-cpu-env-from-device"],
)
def test_to_and_back(envs, kwargs):
    """Built on one device, moved to the other and back: every output follows each move."""
    env = _make(envs, **kwargs)
    first = env.device
    other = CPU if first == DEVICE else DEVICE
    want = _run(env)
    assert_on_device(want, first)
    assert env.to(other) is env and env.device == other
    got = _run(env)
    assert_on_device(got, other)
    _same(got, want)
    env.to(first)
    td = env.reset(seed=1)  # actions made from the moved spec, on the env's device
    out = [td, env.step(td.set("action", env.action_spec.zero())), env.get_state()]
    if "pixels" in td.keys():
        out.append(env.render())
    assert_on_device(out, first)


def test_transformed_serial_parallel_and_collector(envs):
    """TransformedEnv.to, SerialEnv.to, ParallelEnv.to and a collector's device= move the env."""
    from torchrl.collectors import Collector

    make = functools.partial(ManiSkillEnv, ENV_ID, batch_size=[], **STATE)
    transformed = TransformedEnv(make(), EpisodeMetrics())
    serial, parallel = SerialEnv(2, make), ManiSkillParallelEnv(2, make)
    envs.extend([transformed, serial, parallel])
    assert_on_device(transformed.rollout(2), CPU)  # EpisodeMetrics' statistics made, then moved
    for env in (transformed, serial, parallel):
        env.to(DEVICE)
        td = env.rollout(STEPS, _policy(env), break_when_any_done=False)
        assert_on_device(td, DEVICE, msg=type(env).__name__)
    collector = Collector(
        TransformedEnv(make(), EpisodeMetrics()), _policy_on(DEVICE), frames_per_batch=3, total_frames=6, device=DEVICE
    )
    try:
        for batch in collector:
            assert_on_device(batch, DEVICE, msg="collector")
            assert batch["next", "episode", "episode_len"].shape == (3,)
    finally:
        collector.shutdown()


def _policy_on(device):
    def policy(td):
        return td.set("action", torch.zeros(td.batch_size + (8,), device=device))

    return policy


def _per_step(step, n: int = 4) -> dict:
    """What one call of ``step`` copies and waits for, after two calls that fill both host buffers."""
    step(), step()
    before = dict(cuda_double.TRANSFERS)
    for _ in range(n):
        step()
    after = cuda_double.TRANSFERS
    keys = ("h2d", "d2h", "d2d", "sync", "event_record", "event_wait")
    return {k: (after[k] - before.get(k, 0)) / n for k in keys}


@pytest.mark.parametrize(
    "kwargs, d2d",
    [(STATE, 0), (dict(RGB), 1), (dict(STATE, num_envs=2), 0)],
    ids=["state-batch1", "rgb-batch1", "state-batched-cpu-env"],
)
def test_one_transfer_per_step(envs, kwargs, d2d):
    """device="cuda" on the CPU sim: one copy up per step (from a host buffer guarded by an event),
    sapien_cuda pictures copied on the device, no sync but the action's; EpisodeMetrics adds one
    copy up and no read."""
    env = _make(envs, device=DEVICE, **kwargs)
    td = env.reset(seed=0).set("action", env.action_spec.zero())
    counts = _per_step(lambda: env.step(td))
    # Up: one copy. Down: the action, which the CPU sim needs on the host (its one sync).
    assert counts == dict(h2d=1, d2h=1, d2d=d2d, sync=1, event_record=1, event_wait=1), counts
    metrics = TransformedEnv(env, EpisodeMetrics())
    root = metrics.reset(seed=0)

    def step():
        nonlocal root
        out = metrics.step(root.set("action", env.action_spec.zero()))
        root = step_mdp(out)

    counts = _per_step(step, n=3)
    assert counts == dict(h2d=2, d2h=1, d2d=d2d, sync=1, event_record=2, event_wait=2), counts
    assert_on_device(root, DEVICE)


def test_outputs_never_alias_the_host_buffer(envs):
    """Steps kept by the user keep their values when later steps reuse the host buffers."""
    env = _make(envs, device=DEVICE, **STATE)
    td = env.reset(seed=0)
    kept = []
    for i in range(4):
        td = env.step(td.set("action", torch.full(env.action_spec.shape, 0.5 - i / 4, device=DEVICE)))
        kept.append((td["next"].copy(), td["next"].cpu()))  # the leaves handed out, and their values
        td = step_mdp(td)
    for device_td, snapshot in kept:
        assert_tensordict_equal(device_td.cpu(), snapshot)
    partial = TensorDict({"_reset": torch.ones(1, 1, dtype=torch.bool, device=DEVICE)}, batch_size=[1], device=DEVICE)
    assert_on_device(env.reset(partial), DEVICE)
