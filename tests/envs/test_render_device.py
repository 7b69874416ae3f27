"""One render device per process: SAPIEN keeps one render engine per process and refuses a
``RenderSystem`` on another device while it lives (``"cpu"`` and ``"cuda"`` are two devices). The
library says so with the fix, and a closed env lets its scene go.

No test here mixes render devices in this process: the refusal is SAPIEN's own exact error raised
by a stand-in for ``sapien.render.RenderSystem``, and the real mix (a CPU render then a CUDA one)
runs in a subprocess, on machines with CUDA only.
"""

from __future__ import annotations

import gc
import subprocess
import sys
import textwrap
import weakref

import pytest
import sapien
import torch

from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl._internal.rendering import _device_name, render_device_message, render_devices_in_use
from maniskill_torchrl.errors import RenderDeviceError
from support.helpers import ROOT, TIMEOUT_S

KW = dict(obs_mode="state", max_episode_steps=5)
SAPIEN_SAYS = "current SAPIEN version only supports single-GPU rendering."  # SAPIEN 3's words


def _sapien_refuses(device: str):
    """A stand-in for ``sapien.render.RenderSystem`` raising SAPIEN's exact error for ``device``."""

    def render_system(*args, **kwargs):
        raise RuntimeError(f'failed to create renderer on device "{device}": {SAPIEN_SAYS}')

    return render_system


def _other(device: str) -> str:
    return "cuda:0" if device == "cpu" else "cpu"


@pytest.fixture
def env():
    """A ManiSkill env on this process's render device (the default: the CPU here, CUDA on a GPU machine)."""
    env = ManiSkillEnv("PickCube-v1", **KW)
    yield env
    env.close()


def _in_use(env) -> str:
    """The render device that the library remembers for ``env``: its own."""
    device = _device_name(env.unwrapped.backend.render_device)
    assert "PickCube-v1" in render_devices_in_use()[device]
    return device


def test_second_render_device_is_refused_with_the_fix(env, monkeypatch):
    in_use = _in_use(env)
    asked = _other(in_use)
    with monkeypatch.context() as m:
        m.setattr(sapien.render, "RenderSystem", _sapien_refuses(asked))
        with pytest.raises(RenderDeviceError) as info:
            ManiSkillEnv("MS-CartpoleBalance-v1", **KW)
    message = str(info.value)
    assert f"'MS-CartpoleBalance-v1' asks SAPIEN to render on \"{asked}\"" in message
    held = message.split(f'already renders on "{in_use}" (render_backend=')[1].split(")")[0]
    assert "PickCube-v1" in held  # and any other env of this process that renders
    assert "the same render_backend for every ManiSkill env of this process: 'cpu' for all, or 'gpu' for all" in message
    assert "env.close(); del env" in message and "another process" in message
    assert "in_process=False" not in message  # the batched env's fix only
    assert isinstance(info.value, RuntimeError) and "single-GPU rendering" in str(info.value.__cause__)
    # The env in use is untouched, and a new env on its device is made as before.
    env.rand_step(env.reset(seed=0))


def test_batched_cpu_env_sub_env_zero_is_refused_with_the_fix(env, monkeypatch):
    """The batched CPU-sim env makes sub-env 0 in this process: the same error, plus its own fix
    (``in_process=False``); its workers (which render on their own) are stopped."""
    asked = _other(_in_use(env))
    with monkeypatch.context() as m:
        m.setattr(sapien.render, "RenderSystem", _sapien_refuses(asked))
        with pytest.raises(RenderDeviceError, match=r"in_process=False\) makes every sub-env in a worker"):
            ManiSkillEnv("PickCube-v1", num_envs=2, sim_backend="cpu", **KW)


def test_message_without_a_known_device_in_use():
    message = render_device_message("PickCube-v1", "cuda:0", {})
    assert 'render on "cuda:0", but this process already renders on another device' in message
    assert "the same render_backend for every ManiSkill env of this process ('gpu'" in message
    message = render_device_message("PickCube-v1", "cpu", {"cuda:1": ["A-v1", "B-v1", "A-v1"]}, batched=True)
    assert "of this process: 'cpu' for all, or 'cuda:1' for all" in message
    assert "already renders on \"cuda:1\" (render_backend='cuda:1', for A-v1, B-v1)" in message
    assert "in_process=False" in message


def test_closed_env_lets_its_scene_go():
    """A closed env that is still referenced holds neither its ManiSkill env nor its scene (with
    the scene goes SAPIEN's render engine, once no other env renders)."""
    env = ManiSkillEnv("PickCube-v1", **KW)
    base, scene = weakref.ref(env.unwrapped), weakref.ref(env.unwrapped.scene)
    env.close()
    gc.collect()
    assert base() is None and scene() is None
    assert "PickCube-v1" not in sum(render_devices_in_use().values(), [])
    with pytest.raises(RuntimeError, match="is closed"):
        env.reset()


REAL_MIX = """
import gc
import torch
from maniskill_torchrl import ManiSkillEnv
from maniskill_torchrl.errors import RenderDeviceError

from maniskill_torchrl._internal.rendering import _no_cuda_render_device

if _no_cuda_render_device():
    raise SystemExit("NO SAPIEN CUDA DEVICE")
kw = dict(obs_mode="state", max_episode_steps=5)
cpu = ManiSkillEnv("PickCube-v1", render_backend="cpu", **kw)
for make in (lambda: ManiSkillEnv("PickCube-v1", **kw),
             lambda: ManiSkillEnv("PickCube-v1", num_envs=2, sim_backend="cpu", **kw)):
    try:
        make()
    except RenderDeviceError as e:
        assert '"cpu"' in str(e) and "cuda" in str(e) and "del env" in str(e), e
    else:
        raise AssertionError("a second render device was not refused")
cpu.close()
del cpu
gc.collect()
env = ManiSkillEnv("PickCube-v1", **kw)  # the CPU engine is gone: CUDA renders now
assert env.unwrapped.backend.render_device.is_cuda()
env.rand_step(env.reset(seed=0))
env.close()
print("REAL MIX OK")
"""


@pytest.mark.skipif(not torch.cuda.is_available(), reason="a second render device needs CUDA")
def test_real_second_render_device_in_a_subprocess():
    """On a machine with CUDA: a CPU render, then the default (CUDA) one, refused with the fix; once
    the CPU env is closed and deleted, the CUDA one is made."""
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(REAL_MIX)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    if "NO SAPIEN CUDA DEVICE" in proc.stderr:
        pytest.skip("torch sees CUDA, but SAPIEN finds no CUDA device to render with")
    assert proc.returncode == 0 and "REAL MIX OK" in proc.stdout, f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
