"""The many-core emulator's arithmetic (``benchmarks/bench_many_cores.py``, ``many_cores.py``): the
prediction for real cores with the main process as a server, and the lockstep share over distinct
episodes. No process is started."""

from __future__ import annotations

import numpy as np
import pytest

bench = pytest.importorskip("benchmarks.bench_many_cores")
many_cores = pytest.importorskip("benchmarks.many_cores")


def test_prediction_counts_the_main_process_and_its_queue():
    env_s = (50 * 2.555e-3 + 5.65e-3) / 25  # the ideal's time per frame (2026-11-29's run, 187 f/s)
    # one env: its cycle is its sims, its worker's CPU and the main process's time for its frame
    assert bench.predicted_fps(1, env_s, 0.75e-3, 0.787e-3) == pytest.approx(1 / (env_s + 0.75e-3 + 0.787e-3))
    # issue 59's figures from 2026-11-29's costs: 145 / 599 f/s at N = 1 / 4 (measured 150 / 599);
    # the former model's 163 / 666
    assert round(bench.predicted_fps(1, env_s, 0.750e-3, 0.787e-3)) == 145
    assert round(bench.predicted_fps(4, env_s, 0.526e-3, 0.673e-3)) == 599
    assert round(bench.predicted_fps_no_queue(4, env_s, 0.526e-3, 0.673e-3)) == 666
    # many envs: bounded by the main process, approached from below
    many = [bench.predicted_fps(n, env_s, 1e-3, 0.5e-3) for n in (8, 16, 64, 256)]
    assert many == sorted(many) and 0.95e3 < many[-1] <= 1e3


def test_lockstep_share_over_distinct_episodes():
    # 2 passes x 2 episodes x 3 steps: episode 0 always fast, episode 1 always slow
    times = np.array([[[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]]] * 2)
    # two envs on distinct episodes: every unit waits for the slow one (with replacement, a quarter of
    # the draws would have both on the fast one)
    assert many_cores.lockstep_share(times, 2, trials=2000) == pytest.approx(2.0 / 3.0)
    # past the recorded episodes each is played alike: 4 envs, each episode twice
    assert many_cores.lockstep_share(times, 4, trials=2000) == pytest.approx(2.0 / 3.0)
    assert many_cores.lockstep_share(times, 1, trials=20000) == pytest.approx(1.0, rel=0.02)
