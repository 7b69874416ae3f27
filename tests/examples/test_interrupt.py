"""Ctrl-C and SIGTERM keep the run: the examples, as users start them, stopped mid-run save their
checkpoint and metrics so far, close their workers (no leaked semaphores, no traceback) and exit with the
conventional status (130 after SIGINT, 143 after SIGTERM). Both runs go side by side (2 cores). The examples
that keep no checkpoint (``evaluate_gym.py``, ``migrate_from_maniskill.py``) say what they did so far, and leave
no process of their group; ``distributed_ray.py``'s case is in ``test_ray.py`` (it needs Ray)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from support.helpers import terminal_sigint

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

RUNS = {
    # a line per iteration: stopped after the third
    "ppo": (
        ["ppo_torchrl.py", "--device", "cpu", "--num-envs", "2", "--num-steps", "50"],
        ["--total-frames", "1000000", "--eval-every", "0"],
        "iter   3 |",
        signal.SIGINT,
        "ppo_checkpoint.pt",
    ),
    # progress lines between evaluations: stopped after the first
    "sac": (
        ["sac_torchrl.py", "--device", "cpu", "--num-envs", "2", "--learning-starts", "64"],
        ["--eval-every", "100000", "--eval-episodes", "2", "--progress-every", "0", "--batch-size", "32"],
        "f/s",
        signal.SIGTERM,
        "sac_checkpoint.pt",
    ),
}


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """Each run started, signalled once its marker line shows, and waited for: name -> (rc, out, folder)."""
    procs = {}
    for name, (script, extra, *_) in RUNS.items():
        folder = tmp_path_factory.mktemp(name)
        cmd = [sys.executable, str(EXAMPLES / script[0]), *script[1:], *extra, "--out", str(folder / "out")]
        log = (folder / "log.txt").open("w")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, cwd=folder, env=env, preexec_fn=terminal_sigint
        )
        procs[name] = (proc, folder)
    results, sent, deadline = {}, set(), time.monotonic() + 240
    while len(results) < len(procs) and time.monotonic() < deadline:
        for name, (proc, folder) in procs.items():
            if name in results:
                continue
            text = (folder / "log.txt").read_text()
            if name not in sent and RUNS[name][2] in text:
                proc.send_signal(RUNS[name][3])
                sent.add(name)
            if proc.poll() is not None:
                results[name] = (proc.returncode, (folder / "log.txt").read_text(), folder / "out")
        time.sleep(0.5)
    for name, (proc, folder) in procs.items():
        if name not in results:
            proc.kill()
            proc.wait()
            results[name] = (None, (folder / "log.txt").read_text(), folder / "out")
    return results


@pytest.mark.skipif(torch.cuda.is_available(), reason="the CPU-sim runs are sized for a CPU machine")
@pytest.mark.parametrize("name", sorted(RUNS))
def test_a_stopped_run_keeps_its_work_and_exits_conventionally(stopped, name):
    rc, out, folder = stopped[name]
    sig = RUNS[name][3]
    assert rc == 128 + sig, f"exit {rc}\n{out[-3000:]}"
    said = "SIGTERM" if sig == signal.SIGTERM else "Ctrl-C"
    assert f"{said} after" in out, out[-3000:]
    assert (folder / RUNS[name][4]).is_file() and (folder / "metrics.jsonl").is_file(), out[-3000:]
    assert "Traceback" not in out and "leaked" not in out, out[-3000:]
    ckpt = torch.load(folder / RUNS[name][4], map_location="cpu", weights_only=False)
    assert ckpt["frames"] > 0


# --------------------------------------------------------------- the examples that keep no checkpoint
# What they keep is what they print. Each starts in its own session, as a terminal starts a command:
# "group" signals the whole process group (Ctrl-C in a terminal: the vector env's workers and the
# forkserver get it too; a SIGTERM to every process, as a batch system may send), "process" the script alone
# (`kill PID`). name -> (argv, marker line, whom, signal, lines the output must hold after the stop).
STOPS = {
    "evaluate_gym_ctrl_c": (
        ["evaluate_gym.py", "--num-envs", "2", "--episodes", "100000", "--max-episode-steps", "5", "--policy", "zero"],
        "episode   4 (",
        "group",
        signal.SIGINT,
        [r"Ctrl-C after (\d+) of 100000 episodes: the averages so far", r"episodes: (\d+)", r"avg return: "],
    ),
    "evaluate_gym_sigterm": (
        ["evaluate_gym.py", "--num-envs", "1", "--episodes", "100000", "--max-episode-steps", "5"],
        "episode   2 (",
        "group",
        signal.SIGTERM,
        [r"SIGTERM after (\d+) of 100000 episodes: the averages so far", r"episodes: (\d+)", r"avg return: "],
    ),
    "migrate": (
        ["migrate_from_maniskill.py", "--steps", "2500", "--max-episode-steps", "10"],
        "run 2/2",
        "process",
        signal.SIGTERM,
        [
            r"SIGTERM in run 2/2 \(maniskill_torchrl.wrappers\): mani_skill.utils.wrappers reached step 2500 "
            r"of 2500, maniskill_torchrl.wrappers step (\d+)",
            r"identical so far: True \((\d+) records compared\)",
        ],
    ),
}
SETTLE_S = 3.0  # after the marker: the signal lands mid-run, not on the marker's line
FALLBACK_S = 150.0  # a script that never prints its marker is signalled anyway


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@pytest.fixture(scope="module")
def stopped_plain(tmp_path_factory):
    """Each script started in its own session, signalled SETTLE_S after its marker line and waited for:
    name -> (rc, output, whether a process of its group outlived it by 15 s)."""
    procs = {}
    for name, (script, *_rest) in STOPS.items():
        folder = tmp_path_factory.mktemp(name)
        cmd = [sys.executable, str(EXAMPLES / script[0]), *script[1:]]
        log = (folder / "log.txt").open("w")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            cmd,
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=folder,
            env=env,
            start_new_session=True,
            preexec_fn=terminal_sigint,
        )
        procs[name] = (proc, folder, time.monotonic())
    results, seen, sent, deadline = {}, {}, set(), time.monotonic() + 300
    while len(results) < len(procs) and time.monotonic() < deadline:
        for name, (proc, folder, t0) in procs.items():
            if name in results:
                continue
            _, marker, whom, sig, _ = STOPS[name]
            now = time.monotonic()
            if name not in seen and (marker in (folder / "log.txt").read_text() or now - t0 > FALLBACK_S):
                seen[name] = now
            if name in seen and name not in sent and now - seen[name] >= SETTLE_S:
                os.killpg(proc.pid, sig) if whom == "group" else proc.send_signal(sig)
                sent.add(name)
            if proc.poll() is not None:
                end = time.monotonic() + 15
                while _group_alive(proc.pid) and time.monotonic() < end:
                    time.sleep(0.2)
                results[name] = (proc.returncode, (folder / "log.txt").read_text(), _group_alive(proc.pid))
        time.sleep(0.2)
    for name, (proc, folder, _) in procs.items():
        if name not in results:
            proc.kill()
            proc.wait()
            results[name] = (None, (folder / "log.txt").read_text(), _group_alive(proc.pid))
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
    return results


@pytest.mark.parametrize("name", sorted(STOPS))
def test_a_stopped_evaluation_says_what_it_did_and_exits_conventionally(stopped_plain, name):
    import re

    rc, out, left = stopped_plain[name]
    sig, lines = STOPS[name][3], STOPS[name][4]
    assert rc == 128 + sig, f"exit {rc}\n{out[-3000:]}"
    assert "Traceback" not in out and "leaked" not in out and "Error" not in out, out[-3000:]
    assert not left, f"a process of the script's group outlived it\n{out[-3000:]}"
    found = [re.search(line, out) for line in lines]
    assert all(found), f"missing {[line for line, m in zip(lines, found) if not m]}\n{out[-3000:]}"
    if name.startswith("evaluate_gym"):
        # the averages are over every episode printed before the stop, and no fewer than the marker's
        n, n_again = int(found[0].group(1)), int(found[1].group(1))
        assert n == n_again >= int(STOPS[name][1].split()[1]), out[-3000:]
        assert f"episode {n:3d} (" in out and f"episode {n + 1:3d} (" not in out, out[-3000:]
    else:
        assert int(found[0].group(1)) > 0 and int(found[1].group(1)) > 1, out[-3000:]
