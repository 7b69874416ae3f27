"""The CPU engine's per-step trace (``CPUVectorEnv(..., trace_steps=T)``, ``engines/_trace.py``):
timestamps that the parent and every sub-env write in shared memory, in causal order."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from maniskill_torchrl import CPUVectorEnv
from maniskill_torchrl.engines._trace import COLLECT_END, HERE_END, SEND, summarize


def test_each_step_is_stamped_in_causal_order_by_every_process():
    env = CPUVectorEnv("PickCube-v1", 2, obs_mode="state", trace_steps=4)
    try:
        env.reset(seed=0)
        action = torch.zeros(2, *env.single_action_space.shape)
        for _ in range(6):  # more steps than the ring holds: the last 4 are kept
            env.step(action)
        rows = env.trace()["rows"]
    finally:
        env.close()
    assert rows.shape == (4, 3 + 2 * 2)
    assert not np.isnan(rows).any()
    wake, sim_end = rows[:, 3::2], rows[:, 4::2]
    # The parent sends before any sub-env wakes; each sub-env's sim ends after it woke; the
    # parent has every result after the last sim end; sub-env 0 (in the parent) before here_end.
    assert (rows[:, [SEND]] <= wake).all() and (wake <= sim_end).all()
    assert (sim_end.max(axis=1) <= rows[:, COLLECT_END]).all()
    assert (sim_end[:, 0] <= rows[:, HERE_END]).all()
    assert (np.diff(rows[:, SEND]) > 0).all()  # oldest first
    # Still readable once closed, and summarised from the same rows.
    summary = env.trace()["summary"]
    assert summary == summarize(rows) and summary["steps"] == 4
    assert sum(summary["straggler_share"]) == pytest.approx(1.0)
    assert 0.0 <= summary["lockstep_wait_share"] < 1.0


def test_no_trace_unless_asked():
    with pytest.raises(RuntimeError, match="trace_steps"):
        env = CPUVectorEnv("PickCube-v1", 1, obs_mode="state")
        try:
            env.trace()
        finally:
            env.close()
