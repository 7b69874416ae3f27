"""Ctrl-C and SIGTERM keep the run: the examples, as users start them, stopped mid-run save their
checkpoint and metrics so far, close their workers (no leaked semaphores, no traceback) and exit with the
conventional status (130 after SIGINT, 143 after SIGTERM). Both runs go side by side (2 cores)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

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
        procs[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=folder, env=env), folder)
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
