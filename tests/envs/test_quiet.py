"""Quiet by default: building and stepping the library's envs prints no warning the library can
rule out (ManiSkill's "sapien_cuda ... CUDA device was not found" fallback on a machine without
CUDA, in this process and in the CPU workers), and the demo's Collector does not warn about its
parameterless policy."""

from __future__ import annotations

import logging
import warnings

import pytest

from maniskill_torchrl._internal import rendering as _maniskill
from maniskill_torchrl._internal.rendering import default_render_backend


def _no_warnings(recwarn) -> None:
    # DeprecationWarnings raised inside libraries are hidden by Python's default filters: not printed
    shown = [w for w in recwarn.list if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning))]
    assert [f"{w.category.__name__}: {w.message}" for w in shown] == []


@pytest.fixture
def maniskill_log():
    """ManiSkill's log records of this process, WARNING and above (the workers' go to capfd)."""
    from mani_skill.utils.logging_utils import logger

    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = records.append
    logger.addHandler(handler)
    yield records
    logger.removeHandler(handler)


@pytest.mark.parametrize("num_envs", [1, 2])
def test_default_env_builds_without_warnings(num_envs, capfd, recwarn, maniskill_log):
    from maniskill_torchrl import ManiSkillEnv

    warnings.simplefilter("always")
    env = ManiSkillEnv("PickCube-v1", num_envs=num_envs, obs_mode="state", sim_backend="cpu")
    try:
        env.rollout(2)
    finally:
        env.close()
    err = capfd.readouterr().err
    assert "CUDA device was not found" not in err, err
    assert "WARNING" not in err, err
    assert [r.getMessage() for r in maniskill_log] == []
    _no_warnings(recwarn)


def test_demo_prints_no_warning(tmp_path, capfd, recwarn):
    from maniskill_torchrl.cli import main

    warnings.simplefilter("always")
    main(["demo", "--frames", "8", "--workers", "2", "--no-video", "--no-progress", "--out", str(tmp_path)])
    out, err = capfd.readouterr()
    assert "Warning" not in out + err and "WARNING" not in out + err, err
    _no_warnings(recwarn)


def test_render_backend_default(monkeypatch):
    kwargs = {"obs_mode": "state"}
    monkeypatch.setattr(_maniskill, "_no_cuda_render_device", lambda: True)
    assert default_render_backend(kwargs) == {"obs_mode": "state", "render_backend": "cpu"}
    assert kwargs == {"obs_mode": "state"}  # not changed in place
    # a user's choice stays, and so does ManiSkill's default on a machine with CUDA
    assert default_render_backend({"render_backend": "sapien_cuda"}) == {"render_backend": "sapien_cuda"}
    monkeypatch.setattr(_maniskill, "_no_cuda_render_device", lambda: False)
    assert default_render_backend(kwargs) == {"obs_mode": "state"}
