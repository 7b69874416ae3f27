"""Ctrl-C over the library's CPU engine, as a terminal sends it (issue 59, item 1): the whole process group gets
SIGINT, workers included. A collector's ``KeyboardInterrupt`` reaches the user's handler with the pool drained and
idle; an interrupted lockstep step leaves the engine in step. Each script runs in a subprocess of its own process
group (tens of seconds each: here, in ``make test-examples``, not in ``make test``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from support.helpers import terminal_sigint

REPO = Path(__file__).resolve().parents[2]


CTRL_C = textwrap.dedent(
    """
    import faulthandler
    import signal
    import sys

    faulthandler.register(signal.SIGUSR1, all_threads=True)  # a hang: the test asks where (err.txt)
    from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool

    if __name__ == "__main__":
        pool = ManiSkillAsyncEnvPool("PickCube-v1", 2, obs_mode="state", max_episode_steps=4)
        collector = AsyncPoolCollector(pool, frames_per_batch=10**5)  # never yields here
        try:
            print("collecting", flush=True)
            for _ in collector:
                pass
        except KeyboardInterrupt:
            print("checkpoint saved", flush=True)
            print("idle:", pool._current_step_reset == 0, flush=True)
            pool.close()
            print("closed", flush=True)
            sys.exit(0)
    """
)


LOCKSTEP_CTRL_C = textwrap.dedent(
    """
    import faulthandler
    import signal
    import sys

    faulthandler.register(signal.SIGUSR1, all_threads=True)
    import torch
    from maniskill_torchrl import ManiSkillEnv
    from maniskill_torchrl.testing import assert_tensordict_equal

    KW = dict(num_envs=3, sim_backend="cpu", obs_mode="state", max_episode_steps=5, in_process=False)

    def policy(td):
        return td.set("action", torch.full((3, 8), 0.3))

    def seeded(env):
        return env.rollout(4, policy, auto_reset=False, tensordict=env.reset(seed=5))

    if __name__ == "__main__":
        env = ManiSkillEnv("PickCube-v1", **KW)  # every sub-env in a worker: a lockstep wait
        try:
            print("collecting", flush=True)
            while True:
                env.rollout(10**6, policy, break_when_any_done=False)
        except KeyboardInterrupt:
            # still in lockstep: the next seeded episode is a fresh env's, to the bit
            after = seeded(env)
            fresh = ManiSkillEnv("PickCube-v1", **KW)
            assert_tensordict_equal(after, seeded(fresh))
            print("in lockstep", flush=True)
            fresh.close()
            env.close()
            print("closed", flush=True)
            sys.exit(0)
    """
)


def _interrupted(tmp_path, script_text: str) -> tuple[str, str]:
    """Runs ``script_text`` in its own process group, sends the group SIGINT (a terminal's Ctrl-C reaches
    every process of it, workers included) once it is well inside its loop, and checks that it exits 0 and
    leaves no process behind. Returns what it printed and its stderr."""
    script = tmp_path / "ctrl_c.py"
    script.write_text(script_text)
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(REPO))
    with open(out, "w") as stdout, open(err, "w") as stderr:
        proc = subprocess.Popen(
            [sys.executable, str(script)],
            cwd=tmp_path,
            env=env,
            stdout=stdout,
            stderr=stderr,
            start_new_session=True,
            preexec_fn=terminal_sigint,
        )
    try:
        deadline = time.monotonic() + 240
        while "collecting" not in out.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(2.0)  # well inside the loop
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGUSR1)  # where it hangs, every thread, into err.txt
            time.sleep(3)
            pytest.fail(f"no exit 120 s after Ctrl-C; where the script was:\n{err.read_text()[-6000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    printed, errors = out.read_text(), err.read_text()
    assert proc.returncode == 0, f"{printed}\n{errors[-3000:]}"
    assert "died" not in errors and "leaked" not in errors, errors[-3000:]
    deadline = time.monotonic() + 20  # no worker (or forkserver) of the group is left
    while time.monotonic() < deadline:
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            return printed, errors
        time.sleep(0.2)
    pytest.fail("processes of the script's group outlived it")


def test_ctrl_c_is_a_keyboard_interrupt_and_leaves_nothing(tmp_path):
    """Ctrl-C reaches the whole process group, workers included: the main process gets its
    KeyboardInterrupt (the user's handler runs), the pool drains and closes, nothing is left."""
    printed, _ = _interrupted(tmp_path, CTRL_C)
    assert "checkpoint saved" in printed and "idle: True" in printed and "closed" in printed, printed


def test_ctrl_c_leaves_the_lockstep_engine_in_step(tmp_path):
    """Ctrl-C in the middle of a lockstep step of ``ManiSkillEnv(num_envs=3)``'s workers: the next call
    reads the answers the cut step left owed (``WorkerPool.catch_up``), so the next seeded episode is a
    fresh env's, to the bit, instead of reading the interrupted step's answers as its own."""
    printed, _ = _interrupted(tmp_path, LOCKSTEP_CTRL_C)
    assert "in lockstep" in printed and "closed" in printed, printed
