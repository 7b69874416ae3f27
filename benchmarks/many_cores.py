"""What ``bench_many_cores.py`` runs and computes: its child processes (the collection pipelines of
``collection_pipelines.py`` on the replay task, and raw replay envs alone, independent or in
lockstep), the emulated ideal, and the spread of the step times fitted to the H200's lockstep.

Every child runs with ``$BENCH_ENV_ID`` set to the replay task (``collection_pipelines`` reads it,
in gym's workers too), ``$MANISKILL_REPLAY_STEP_MS`` and ``$MANISKILL_REPLAY_SPREAD`` (read by each
replay env where it is made). It sets the start method to ``"forkserver"`` and has the forkserver
import torch, gymnasium, ManiSkill's tasks, the replay task and the library's worker module once,
for every contender alike, so that 64 workers start in seconds and share those pages (each gym
worker would import them itself otherwise). Start-up is not timed.
"""

from __future__ import annotations

import os
import statistics
import sys
import time

import numpy as np

EPISODE = 50  # sim steps per recorded episode (the time limit)
REAL_ID = "PickCube-v1"
#: The many-core record (DESIGN.md, "Facts about the world"; lent H200 host, 16 cores, 2026-11-28).
H200 = {
    "raw_steps_per_s": 484.0,  # one raw PickCube-v1 env, inference mode
    "independent_15": 5623.0,  # 15 raw envs, each in its own process, at its own pace
    "lockstep_15": 3774.0,  # 15 raw envs on a spin barrier
    "gym_15_r2": 1728.0,  # collection frames/s at N=15, repeat 2
    "readme_15_r2_x_gym": 0.89,  # the lockstep README pipeline, against gym
    "torchrl_async_15_r2_x_gym": 0.97,  # TorchRL's AsyncBatchedCollector over single envs, against gym
}
PRELOAD = (
    "torch",
    "gymnasium",
    "mani_skill.envs",
    "benchmarks.replay_task",
    "maniskill_torchrl.engines._worker",
)
#: The contenders of the sweep: name -> (pipeline spec of collection_pipelines at N=1, at N>1, label).
#: The README pipeline at N>1 runs every sub-env in a worker (``workers``): what the library picks by
#: itself on a machine with more cores than sub-envs, the machine emulated (on 2 cores it would put
#: sub-env 0 in the main process).
CONTENDERS = {
    "gym": ("gym", "gym", "gym (AsyncVectorEnv of CPUGymWrapper + ActionRepeatWrapper)"),
    "gym-nograd": ("gym", "gym", "gym, its sleeps without the grad-mode factor"),
    "readme": (
        "batched:t1,rp,dev,em",
        "batched:t1,rp,dev,em,workers",
        "README pipeline (lockstep ManiSkillEnv + ActionRepeat + EpisodeMetrics, Collector)",
    ),
    "async": ("async:lib", "async:lib", "asynchronous path (ManiSkillAsyncEnvPool + AsyncPoolCollector)"),
}
#: Calibration only: TorchRL's AsyncBatchedCollector over single envs (the H200 record has it at N=15).
TORCHRL_ASYNC = ("async:auto", "async:auto", "TorchRL AsyncBatchedCollector over single envs")


#: The contenders whose sims step in autograd's grad mode (gymnasium's worker loop): their sleeps carry
#: the grad-mode factor measured in the run, ``gym-nograd``'s none (``replay_task.GRAD_FACTOR_ENV``).
GRAD_MODE = ("gym",)


def spec_for(contender: str, n: int) -> str:
    """The pipeline spec of ``contender`` at ``n``; ``name+options`` adds options to its spec (e.g.
    ``async+sched=other``: collection_pipelines' options, comma-separated)."""
    name, _, extra = contender.partition("+")
    one, many, _ = TORCHRL_ASYNC if name == "torchrl-async" else CONTENDERS[name]
    spec = one if n == 1 else many
    return f"{spec}{',' if ':' in spec else ':'}{extra}" if extra else spec


# ----------------------------------------------------------------------------- the emulated machine
def scaled_times(step_ms: float | str | None, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """The replay's step and reset times (seconds; [passes, episodes, steps] and [passes, episodes])
    as the replay env sleeps them for this target and spread."""
    from benchmarks.replay_task import load_recording, shrink_times, time_scale

    rec = load_recording()
    scale = time_scale(step_ms, rec)
    return shrink_times(rec["step_s"], spread) * scale, shrink_times(rec["reset_s"], spread) * scale


def ideal_fps(n: int, repeat: int, step_s: float, reset_s: float) -> float:
    """Frames/s of ``n`` envs that never wait for anything: each agent episode is ``EPISODE`` sim steps
    of ``step_s`` and one reset of ``reset_s``, for ``ceil(EPISODE / repeat)`` frames (agent steps)."""
    agent_steps = -(-EPISODE // repeat)
    return n * agent_steps / (EPISODE * step_s + reset_s)


def lockstep_share(
    step_times: np.ndarray, n: int, spread: float = 1.0, sims: int = 1, trials: int = 20000, seed: int = 0
) -> float:
    """What ``n`` envs in lockstep reach of ``n`` independent ones with these step times (``[passes,
    episodes, steps]``, each shrunk by ``spread`` around their mean): the mean lockstep unit (``sims``
    consecutive sim steps, one draw of a pass each) over the mean of the slowest of ``n`` envs, each
    on its own episode, at one step index (``n`` distinct episodes, as the replay's envs play them; past
    the recorded episodes, each as often as the others). No overhead, no resets: the ceiling the times
    allow."""
    mean = float(step_times.mean())
    times = mean + spread * (step_times - mean)
    passes, episodes, steps = times.shape
    rng = np.random.default_rng(seed)
    k = rng.integers(steps - sims + 1, size=(trials, 1))
    e = rng.permuted(np.tile(np.arange(episodes), (trials, -(-n // episodes))), axis=1)[:, :n]
    unit = sum(times[rng.integers(passes, size=(trials, n)), e, k + j] for j in range(sims))
    return sims * mean / float(unit.max(axis=1).mean())


def fit_spread(step_times: np.ndarray, target: float, n: int = 15) -> float:
    """The spread whose :func:`lockstep_share` at ``n`` is ``target`` (bisection; 1 when even the
    recorded spread gives more than ``target``)."""
    if lockstep_share(step_times, n, 1.0) >= target:
        return 1.0
    lo, hi = 0.0, 1.0  # share falls as the spread grows
    for _ in range(30):
        mid = (lo + hi) / 2
        if lockstep_share(step_times, n, mid) > target:
            lo = mid
        else:
            hi = mid
    return round((lo + hi) / 2, 4)


# ----------------------------------------------------------------------------- children
def prepare_child() -> None:
    """The start method and the forkserver's imports of every child (module docstring)."""
    import multiprocessing as mp

    from maniskill_torchrl._internal.mp import preload_forkserver

    mp.set_start_method("forkserver", force=True)
    preload_forkserver(PRELOAD)
    import benchmarks.replay_task  # noqa: F401  (registers the task in this process)


def run_child(spec: str, n: int, repeat: int, seconds: float) -> None:
    """One measurement in this fresh process: ``ceiling:<raw|independent|lockstep|real>``, ``grad``
    (:func:`grad_factor`) or a pipeline of ``collection_pipelines`` (which reports it and ends the
    process)."""
    prepare_child()
    if spec.startswith("ceiling:") or spec == "grad":
        from benchmarks.alternate import child_result

        out = grad_factor(seconds) if spec == "grad" else ceiling(spec.split(":", 1)[1], n, seconds)
        child_result(**out)
        sys.stdout.flush()
        os._exit(0)
    from benchmarks import collection_pipelines

    collection_pipelines.run_child(spec, n, repeat, seconds)


def _ceiling_worker(env_id: str, index: int, n: int, lockstep: bool, seconds: float, barrier, go, stop, result) -> None:
    """One raw env (the replay, or the real task) in its own process, under inference mode: random
    actions, a reset at each episode's end; with ``lockstep``, a barrier after each step (a sleeping
    wait: on 2 cores a spinning one would take the cores the emulation needs)."""
    import gymnasium as gym
    import torch

    torch.set_num_threads(1)
    with torch.inference_mode():
        kwargs = {"render_backend": "none"} if env_id == REAL_ID else {}
        env = gym.make(env_id, num_envs=1, obs_mode="state", sim_backend="physx_cpu", max_episode_steps=50, **kwargs)
        env.reset(seed=index)
        actions = [torch.as_tensor(env.action_space.sample()) for _ in range(64)]
        env.step(actions[0])
        result.put(("ready", index))
        go.wait()
        frames, began = 0, time.perf_counter()
        end = began + seconds
        while True:
            _, _, term, trunc, _ = env.step(actions[frames & 63])
            frames += 1
            if bool(term[0]) or bool(trunc[0]):
                env.reset()
            if lockstep:
                if index == 0 and time.perf_counter() >= end:
                    stop.value = 1  # read by all after the barrier: they stop at the same step
                barrier.wait(timeout=60)
                if stop.value:
                    break
            elif time.perf_counter() >= end:
                break
        elapsed = time.perf_counter() - began
    result.put(("done", index, frames, elapsed))


def ceiling(kind: str, n: int, seconds: float) -> dict:
    """``raw`` (one replay env), ``independent`` (``n`` at their own pace), ``lockstep`` (``n`` on a
    barrier), or ``real`` (one real PickCube-v1 env: this machine's speed now): sim steps per second,
    summed over the processes' own windows."""
    import multiprocessing as mp

    from benchmarks.alternate import child_ready
    from benchmarks.replay_task import REPLAY_ID

    if kind not in ("raw", "independent", "lockstep", "real"):
        raise SystemExit(f"unknown ceiling {kind!r}: raw, independent, lockstep or real")
    n = 1 if kind in ("raw", "real") else n
    env_id = REAL_ID if kind == "real" else REPLAY_ID
    ctx = mp.get_context("forkserver")
    barrier, go, stop, result = ctx.Barrier(n), ctx.Event(), ctx.Value("i", 0), ctx.Queue()
    procs = [
        ctx.Process(target=_ceiling_worker, args=(env_id, i, n, kind == "lockstep", seconds, barrier, go, stop, result))
        for i in range(n)
    ]
    for p in procs:
        p.start()

    def gather(deadline: float) -> list:
        """``n`` messages of the workers; a worker that died (its traceback printed) ends the run."""
        import queue

        got = []
        while len(got) < n:
            try:
                got.append(result.get(timeout=1.0))
            except queue.Empty:
                dead = [i for i, p in enumerate(procs) if p.exitcode not in (None, 0)]
                if dead or time.perf_counter() > deadline:
                    for p in procs:
                        p.kill()
                    raise RuntimeError(f"ceiling {kind}: workers {dead} died, or the run hung") from None
        return got

    gather(time.perf_counter() + 300)
    startup = child_ready()
    go.set()
    rows = gather(time.perf_counter() + seconds + 120)
    for p in procs:
        p.join(timeout=30)
    fps = sum(r[2] / r[3] for r in rows)
    frames = sum(r[2] for r in rows)
    return {
        "units": frames,
        "wall_s": frames / fps,
        "cpu_s": 0.0,
        "startup_s": startup,
        "per_env_steps_per_s": statistics.median(r[2] / r[3] for r in rows),
    }


def grad_factor(seconds: float) -> dict:
    """What a real PickCube-v1 episode (a seeded reset and 50 steps of random actions, one torch
    thread) costs in autograd's grad mode over inference mode, on this machine now: two envs in this
    process, one made and stepped under :func:`torch.inference_mode` (the library's workers), one in
    grad mode (gymnasium's worker loop), play the same episodes with the same actions, alternating,
    for ``2 * seconds``; the factor is the ratio of their medians (``pairs``: each grad-mode episode
    over the inference-mode one before it, min and max)."""
    import gymnasium as gym
    import torch

    from benchmarks.alternate import child_ready

    torch.set_num_threads(1)
    kwargs = {"num_envs": 1, "obs_mode": "state", "sim_backend": "physx_cpu", "render_backend": "none"}
    with torch.inference_mode():
        inference = gym.make(REAL_ID, **kwargs)
    grad = gym.make(REAL_ID, **kwargs)
    rng = np.random.default_rng(0)
    low, high = grad.action_space.low, grad.action_space.high
    actions = [torch.as_tensor(rng.uniform(low, high).astype(low.dtype)) for _ in range(EPISODE)]

    def episode(env, seed: int) -> float:
        t0 = time.perf_counter()
        env.reset(seed=seed)
        for a in actions:
            env.step(a)
        return time.perf_counter() - t0

    with torch.inference_mode():
        episode(inference, 0)
    episode(grad, 0)  # warm-up, both
    startup = child_ready()
    times: dict[bool, list[float]] = {False: [], True: []}
    began = time.perf_counter()
    while time.perf_counter() - began < 2 * seconds or len(times[True]) < 3:
        seed = len(times[True])
        with torch.inference_mode():
            times[False].append(episode(inference, seed))
        times[True].append(episode(grad, seed))
    wall = time.perf_counter() - began
    pairs = [g / i for i, g in zip(times[False], times[True])]
    return {
        "units": len(pairs),
        "wall_s": wall,
        "cpu_s": 0.0,
        "startup_s": startup,
        "grad_factor": statistics.median(times[True]) / statistics.median(times[False]),
        "pairs_min": min(pairs),
        "pairs_max": max(pairs),
        "inference_steps_per_s": (EPISODE + 1) / statistics.median(times[False]),
    }
