"""The machine a benchmark runs on: what it is (CPU, cores, library versions), how busy other
processes keep it, and results saved as JSON with its description.

Used by the in-process harness (``common.py``) and the process-alternation harness
(``alternate.py``) alike; imports neither.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
import time

__all__ = ["machine_info", "machine_line", "save_json", "busy_cores", "wait_for_quiet"]


def _cpu_model() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """CPU model, usable cores, python and library versions."""
    info = {
        "cpu": _cpu_model(),
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "python": platform.python_version(),
        "date": _dt.date.today().isoformat(),
    }
    for mod in ("torch", "tensordict", "torchrl", "mani_skill", "sapien", "gymnasium", "numpy"):
        try:
            info[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001 - a missing library is just not reported
            pass
    try:
        import torch

        info["torch_threads"] = torch.get_num_threads()
    except ImportError:
        pass
    return info


def machine_line(info: dict | None = None) -> str:
    """One line describing the machine and versions, for RESULTS.md."""
    info = info or machine_info()
    libs = ", ".join(f"{k} {info[k]}" for k in ("torch", "tensordict", "torchrl", "mani_skill", "sapien") if k in info)
    return f"{info['cpu']}, {info['cores']} cores, Python {info['python']}; {libs}"


def save_json(path: str, payload: dict) -> None:
    """Writes ``payload`` (with machine info added) as JSON, creating the folder."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    payload = {"machine": machine_info(), **payload}
    with open(path, "w") as f:
        json.dump(payload, f, indent=2, default=str)


def _cpu_jiffies() -> tuple[int, int] | None:
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    return sum(fields[:8]), idle  # user..steal; guest time is already in user


def busy_cores(interval: float = 1.0) -> float | None:
    """Cores kept busy on this machine over ``interval`` seconds (all processes; Linux ``/proc/stat``).

    ``None`` where ``/proc/stat`` cannot be read."""
    a = _cpu_jiffies()
    time.sleep(interval)
    b = _cpu_jiffies()
    if a is None or b is None or b[0] == a[0]:
        return None
    cores = os.cpu_count() or 1
    return cores * (1.0 - (b[1] - a[1]) / (b[0] - a[0]))


def wait_for_quiet(
    max_busy: float = 0.3, max_wait: float = 120.0, interval: float = 0.5, verbose: bool = False
) -> float | None:
    """Waits until other processes keep fewer than ``max_busy`` cores busy (sampled every
    ``interval`` s), at most ``max_wait`` seconds; returns the last reading (``None`` if unknown).

    For timings on a machine shared with other jobs: call it before each timed run (not while
    this process's own workers are running) and record the reading next to the result."""
    t0 = time.perf_counter()
    warned = False
    while True:
        busy = busy_cores(interval)
        if busy is None or busy < max_busy or time.perf_counter() - t0 >= max_wait:
            return busy
        if verbose and not warned:
            print(f"  (machine busy: {busy:.2f} cores used by others; waiting up to {max_wait:.0f} s)", flush=True)
            warned = True
