"""What the CPU sim allows on this machine, before any engine is judged (issue 37, item 1).

Raw ManiSkill envs (``gym.make(env_id, num_envs=1, sim_backend="physx_cpu")``, random actions,
a reset at each episode's end), each in its own process with one torch thread, no IPC but a
start signal and the final count:

- ``topology``: logical CPUs, threads per core, cores, sockets (``lscpu`` / sysfs);
- ``single_grad`` / ``single_inference``: one env stepping in grad mode, and under
  :func:`torch.inference_mode`;
- ``independent``: N envs stepping each at its own pace: the ceiling for N envs;
- ``lockstep``: N envs in lockstep on a shared-memory spin barrier (each waits until all N have
  finished the step before it takes the next), with no main-process work: the ceiling for any
  engine that returns all N results of a step together.

Processes are forked from a forkserver that imported torch and ManiSkill once (no renderer is
made there: importing is fork-safe, a renderer is not), so a fresh process costs no re-import;
its start-up is measured and reported apart from the timed window. Frames are counted over a
window of ``--seconds`` that starts when every process has built its env and passed one step.
Contenders alternate in rotated order over ``--rounds``; medians with min and max.

    python -m benchmarks.bench_ceilings --n 1 2 --seconds 10 --rounds 5 --out outputs/ceilings.json
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import subprocess
import time
from multiprocessing import shared_memory

import numpy as np

from benchmarks.machine import machine_info

_PRELOAD = ["torch", "gymnasium", "mani_skill.envs", "maniskill_torchrl._internal.rendering"]


def topology() -> dict:
    """Logical CPUs, threads per core, cores per socket and sockets, as ``lscpu`` says."""
    out = {"logical_cpus": os.cpu_count(), "usable_cpus": len(os.sched_getaffinity(0))}
    keys = {
        "Thread(s) per core": "threads_per_core",
        "Core(s) per socket": "cores_per_socket",
        "Socket(s)": "sockets",
        "Model name": "model",
        "Hypervisor vendor": "hypervisor",
    }
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return out
    for line in text.splitlines():
        name, _, value = line.partition(":")
        if name.strip() in keys:
            value = value.strip()
            out[keys[name.strip()]] = int(value) if value.isdigit() else value
    return out


def _worker(
    index: int, n: int, env_id: str, inference: bool, lockstep: bool, shm_name: str, seconds: float, result
) -> None:
    """One raw env: build, signal ready, wait for go, step for ``seconds``, report the count."""
    t0 = time.perf_counter()
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    import torch

    from maniskill_torchrl._internal.rendering import default_render_backend

    torch.set_num_threads(1)
    shm = shared_memory.SharedMemory(name=shm_name)
    # Per worker: [0] ready flag, [1] step generation; [2*n] the go flag.
    block = np.ndarray((2 * n + 1,), np.int64, buffer=shm.buf)
    gen = block[1 : 2 * n : 2]
    ctx = torch.inference_mode() if inference else torch.enable_grad()
    with ctx:
        # The render device the library's envs get here (sapien_cuda on a CUDA machine).
        kwargs = default_render_backend({"obs_mode": "state", "sim_backend": "physx_cpu"})
        env = gym.make(env_id, num_envs=1, **kwargs)
        env.reset(seed=index)
        space = env.action_space
        actions = [torch.as_tensor(space.sample()) for _ in range(64)]
        env.step(actions[0])
        startup = time.perf_counter() - t0
        block[2 * index] = 1
        while block[2 * n] == 0:
            time.sleep(0.0005)
        frames, k = 0, 0
        began = time.perf_counter()
        end = began + seconds
        while True:
            _, _, term, trunc, _ = env.step(actions[k & 63])
            k += 1
            frames += 1
            if bool(term[0]) or bool(trunc[0]):
                env.reset()
            if lockstep:
                # Publish this step, then spin until every env has finished it.
                g = gen[index] + 1
                gen[index] = g
                while gen.min() < g:
                    pass
                # Stop together: whoever sees the time first decides for the generation.
                if block[2 * n] == 2 or time.perf_counter() >= end:
                    block[2 * n] = 2
                    # One more barrier so no env waits on a gone one.
                    gen[index] = g + 1
                    break
            elif time.perf_counter() >= end:
                break
        elapsed = time.perf_counter() - began
        env.close()
    result.put((index, frames, startup, elapsed))
    shm.close()


def run_group(ctx, n: int, env_id: str, *, inference: bool, lockstep: bool, seconds: float, timeout: float) -> dict:
    """N processes of one raw env each; frames/s over the window, start-up per process."""
    shm = shared_memory.SharedMemory(create=True, size=8 * (2 * n + 1))
    block = np.ndarray((2 * n + 1,), np.int64, buffer=shm.buf)
    block[:] = 0
    result = ctx.Queue()
    t0 = time.perf_counter()
    procs = [
        ctx.Process(target=_worker, args=(i, n, env_id, inference, lockstep, shm.name, seconds, result), daemon=True)
        for i in range(n)
    ]
    for p in procs:
        p.start()
    try:
        while block[0 : 2 * n : 2].sum() < n:
            if time.perf_counter() - t0 > timeout or any(p.exitcode not in (None, 0) for p in procs):
                raise RuntimeError(f"{n} env processes not ready after {time.perf_counter() - t0:.0f} s")
            time.sleep(0.005)
        ready = time.perf_counter() - t0
        start = time.perf_counter()
        block[2 * n] = 1
        rows = [result.get(timeout=seconds + timeout) for _ in range(n)]
        wall = time.perf_counter() - start
        for p in procs:
            p.join(timeout=timeout)
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
        shm.close()
        shm.unlink()
    # Each process's own rate over its own window (they start within a poll of each other).
    fps = sum(r[1] / r[3] for r in rows)
    return {
        "fps": fps,
        "frames": sum(r[1] for r in rows),
        "wall_s": wall,
        "ready_s": ready,
        "startup_s": [r[2] for r in rows],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env-id", default="PickCube-v1")
    p.add_argument("--n", type=int, nargs="+", default=[1, 2])
    p.add_argument("--seconds", type=float, default=10.0, help="timed window per run")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--timeout", type=float, default=120.0, help="start-up limit per run, seconds")
    p.add_argument("--budget", type=float, default=None, help="stop starting runs after this many seconds")
    p.add_argument("--out", default=None)
    args = p.parse_args()

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(_PRELOAD)
    began = time.perf_counter()
    cases = [("single_grad", 1, False, False), ("single_inference", 1, True, False)]
    for n in args.n:
        cases += [(f"independent_{n}", n, True, False), (f"lockstep_{n}", n, True, True)]
    runs: dict[str, list[dict]] = {name: [] for name, *_ in cases}
    stopped = None
    for r in range(args.rounds):
        shift = r % len(cases)
        for name, n, inference, lockstep in cases[shift:] + cases[:shift]:
            if args.budget is not None and time.perf_counter() - began > args.budget:
                stopped = f"budget of {args.budget:.0f} s spent in round {r + 1}"
                break
            runs[name].append(
                run_group(
                    ctx,
                    n,
                    args.env_id,
                    inference=inference,
                    lockstep=lockstep,
                    seconds=args.seconds,
                    timeout=args.timeout,
                )
            )
        if stopped:
            break

    def summary(rows: list[dict]) -> dict:
        fps = [row["fps"] for row in rows]
        return {
            "median_fps": statistics.median(fps) if fps else None,
            "min_fps": min(fps, default=None),
            "max_fps": max(fps, default=None),
            "rounds": len(fps),
            "max_startup_s": max((s for row in rows for s in row["startup_s"]), default=None),
        }

    table = {name: summary(rows) for name, rows in runs.items()}
    one = table["single_inference"]["median_fps"]
    print(f"{'case':<20} {'median f/s':>11} {'min':>9} {'max':>9} {'vs N x one':>10} {'start-up s':>10}")
    for name, row in table.items():
        n = int(name.rsplit("_", 1)[1]) if name.rsplit("_", 1)[1].isdigit() else 1
        ratio = row["median_fps"] / (n * one) if row["median_fps"] and one else None
        row["vs_n_times_one"] = ratio
        print(
            f"{name:<20} {row['median_fps'] or 0:>11.1f} {row['min_fps'] or 0:>9.1f} {row['max_fps'] or 0:>9.1f} "
            f"{ratio or 0:>10.2f} {row['max_startup_s'] or 0:>10.1f}"
        )
    if stopped:
        print(f"stopped early: {stopped}")
    payload = {
        "machine": machine_info(),
        "topology": topology(),
        "args": vars(args),
        "summary": table,
        "runs": runs,
        "stopped": stopped,
        "wall_s": time.perf_counter() - began,
    }
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(payload, f, indent=1)
    print(json.dumps({"topology": payload["topology"], "wall_s": round(payload["wall_s"], 1)}))


if __name__ == "__main__":
    main()
