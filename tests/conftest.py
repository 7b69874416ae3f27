"""Shared fixtures (the shared helper functions live in helpers.py): ManiSkill envs on the CPU
sim are costly to build (about 0.4 s), so module-scoped fixtures share them where a test allows;
every comparison seeds every reset."""

from __future__ import annotations

import warnings

import mani_skill.envs  # noqa: F401  (registers the tasks)
import pytest
import torch

warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")
warnings.filterwarnings("ignore", module="mani_skill")


@pytest.fixture(scope="session")
def torch_single_thread():
    torch.set_num_threads(1)
