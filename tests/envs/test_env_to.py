"""``env.to(device)`` on a machine without CUDA: a device that does not exist is refused with the
fix and leaves the env as it was; the env's own device changes nothing. The moves between the CPU
and an accelerator run under the CUDA double (``tests/gpu/cuda_device_cases.py``)."""

from __future__ import annotations

import pytest
import torch

from maniskill_torchrl import ManiSkillEnv
from support.helpers import close_envs


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is there: .to('cuda') is a real move")
def test_to_a_missing_device_is_refused_and_changes_nothing():
    env = ManiSkillEnv("PickCube-v1", obs_mode="state", sim_backend="cpu")
    try:
        assert env.to("cpu") is env and env.device == torch.device("cpu")
        with pytest.raises(ValueError, match="torch.cuda.is_available"):
            env.to("cuda")
        assert env.device == torch.device("cpu") and env.observation_spec.device == torch.device("cpu")
        td = env.reset(seed=0)
        out = env.step(td.set("action", env.action_spec.zero()))
        assert out["next", "observation"].device == torch.device("cpu")
    finally:
        close_envs([env])
