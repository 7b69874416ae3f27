"""The pipelines ``bench_collection.py`` times, each run in a child process of its own.

``run_child`` builds one pipeline (``gym[:<options>]``, ``batched[:<options>]``,
``parallel[:<options>]``, ``multisync``, ``async[:auto]``; ``bench_collection.py``'s docstring
describes each), warms it up untimed, collects for the given seconds and reports frames, wall
time and CPU time to the parent (:func:`alternate.child_result`), with what it ran
(:data:`RAN_KEYS`): its torch threads and its workers', the autograd mode of its sims, the
frame rule. ``bench_ray.py`` reuses the worker env, the CPU meter and the collector timing.

Frames are agent steps for every contender: a sim step taken on an agent's action. A reset is
never a frame. TorchRL's collectors count agent steps (``step_and_maybe_reset`` resets an ended
episode in the same call, uncounted); ``AsyncBatchedCollector`` counts transitions, one per agent
step. Gymnasium's ``AsyncVectorEnv`` (default next-step autoreset) spends one ``step`` call of a
sub-env on its reset after each episode: ``child_gym`` counts ``N`` per call less the sub-envs
whose previous step ended their episode (``terminated | truncated``), and reports the ``N`` per
call it used to credit as ``credited_frames``.
"""

from __future__ import annotations

import os
import sys
import time
import warnings

from benchmarks.alternate import child_ready, child_result

#: The task: PickCube-v1, or ``$BENCH_ENV_ID`` (read by every process that imports this module, gym's
#: workers included), e.g. the many-core emulator's replay task (``bench_many_cores.py``).
ENV_ID = os.environ.get("BENCH_ENV_ID") or "PickCube-v1"
EPISODE = 50
SEED = 0
#: What each child reports it ran, besides its measurement (shown in bench_collection's table).
RAN_KEYS = ("main_threads", "worker_threads", "sims", "sub_env0", "frames_rule")
PROBE_DIR = "BENCH_PROBE_DIR"  # where TorchRL's worker envs write what they run (_worker_env)


def _maniskill_kwargs(rgb: int | None = None) -> dict:
    """The task's keywords: state observations, or with ``rgb=S`` its cameras' rgb at S x S pixels
    (``obs_mode="rgb"``, ManiSkill's PPO-from-rgb baseline's observations before flattening)."""
    # the CPU sim for every contender: with CUDA, ManiSkillEnv(num_envs>1) would pick the GPU sim
    kwargs = {"obs_mode": "state", "max_episode_steps": EPISODE, "sim_backend": "physx_cpu"}
    if rgb:
        kwargs.update(obs_mode="rgb", sensor_configs={"width": rgb, "height": rgb})
    return kwargs


def _rgb(opts: dict) -> int | None:
    """The ``rgb=S`` option's camera size, or None (state observations)."""
    return int(opts["rgb"]) if "rgb" in opts else None


def _quiet() -> None:
    import logging

    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore")


def _sim_mode(inference: bool) -> str:
    """How this thread's sim steps run: under inference mode, or autograd's ambient mode."""
    import torch

    return "inference" if inference else ("grad" if torch.is_grad_enabled() else "no_grad")


def _gym_probe(inference: bool) -> dict:
    """What a gym worker runs (``AsyncVectorEnv.call("bench_probe")``, in the worker's loop thread)."""
    import torch

    return {"threads": torch.get_num_threads(), "sims": _sim_mode(inference)}


def _gym_thunk(repeat: int, threads: int | None = None, inference: bool = False, rgb: int | None = None):
    import functools

    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    import torch
    from mani_skill.utils.wrappers import ActionRepeatWrapper, CPUGymWrapper

    _quiet()
    if threads is not None:  # the thread policy of the library's workers (gym:t1)
        torch.set_num_threads(threads)
    env = gym.make(ENV_ID, num_envs=1, **_maniskill_kwargs(rgb))
    if rgb:  # ManiSkill's ppo_rgb stack: its cameras' rgb and the state, flattened, first
        from mani_skill.utils.wrappers import FlattenRGBDObservationWrapper

        env = FlattenRGBDObservationWrapper(env, rgb=True, depth=False, state=True)
    if repeat > 1:
        env = ActionRepeatWrapper(env, repeat)
    env = CPUGymWrapper(env)
    if inference:  # gym:inf: each call under inference mode, as the library's workers decorate theirs

        class InferenceMode(gym.Wrapper):
            @torch.inference_mode()
            def step(self, action):
                return self.env.step(action)

            @torch.inference_mode()
            def reset(self, **kwargs):
                return self.env.reset(**kwargs)

        env = InferenceMode(env)
    env.bench_probe = functools.partial(_gym_probe, inference)  # an attribute: AsyncVectorEnv.call finds it
    return env


def env_options(opts: dict) -> dict:
    """The ``ManiSkillEnv`` keywords that the options ask for: ``noinf`` (``inference_mode=False``),
    ``unb`` (``batch_size=[]``: the workers' envs unbatched by ``ManiSkillEnv`` itself),
    ``workers`` (``in_process=False``: every sub-env of a batched CPU env in a worker process),
    ``inproc`` (``in_process=True``: sub-env 0 in this process; without either, the machine decides)."""
    out: dict = {}
    if "workers" in opts:
        out["in_process"] = False
    if "inproc" in opts:
        out["in_process"] = True
    if "noinf" in opts:
        out["inference_mode"] = False
    if "unb" in opts:
        out["batch_size"] = []
    return out


def _register_task() -> None:
    """A task named ``module:EnvId`` (gymnasium's form, e.g. the replay task's) registers itself when its
    module is imported: ``gym.make`` imports it, ``ManiSkillEnv``'s check of the id does not."""
    if ":" in ENV_ID:
        import importlib

        importlib.import_module(ENV_ID.partition(":")[0])


def _worker_env(repeat: int, **env_kwargs):
    """One ParallelEnv worker: ManiSkillEnv -> CPUUnbatch (-> ActionRepeat); without CPUUnbatch
    when ``env_kwargs`` has ``batch_size=[]`` (the env is unbatched already)."""
    from torchrl.envs import Compose, TransformedEnv

    from maniskill_torchrl import ActionRepeat, CPUUnbatch, ManiSkillEnv

    _quiet()
    _register_task()
    env = ManiSkillEnv(ENV_ID, **_maniskill_kwargs(), **env_kwargs)
    _record_worker(env)
    transforms = ([] if env.batch_size == () else [CPUUnbatch()]) + ([ActionRepeat(repeat)] if repeat > 1 else [])
    return TransformedEnv(env, Compose(*transforms)) if transforms else env


def _record_worker(env) -> None:
    """Writes this process's torch threads and its sim's mode to ``$BENCH_PROBE_DIR/<pid>.json``
    (read back by :func:`_workers_ran`). TorchRL's workers set their threads before they build
    the env (``ParallelEnv``, ``AsyncBatchedCollector``), so the count is the one they step with."""
    import json

    import torch

    where = os.environ.get(PROBE_DIR)
    if not where:
        return
    try:
        with open(os.path.join(where, f"{os.getpid()}.json"), "w") as f:
            json.dump({"threads": torch.get_num_threads(), "sims": _torchrl_sims(env)}, f)
    except OSError:
        pass


def _torchrl_sims(env) -> str:
    """The mode of a ``ManiSkillEnv``'s sims: the CPU engine runs ManiSkill under inference mode
    itself; otherwise ``inference_mode=`` says (False: the caller's mode, ``torch.no_grad`` under
    TorchRL's collectors)."""
    from torchrl.envs import TransformedEnv

    base = env.base_env if isinstance(env, TransformedEnv) else env  # a ManiSkillEnv's base_env is ManiSkill's
    engine = getattr(base, "_env", None)
    if getattr(engine, "runs_inference_mode", False) or getattr(base, "inference_mode", False):
        return "inference"
    return "not inference"


def _workers_ran() -> tuple[int | list[int] | None, str | None]:
    """The worker processes' threads and sim modes, from their :func:`_record_worker` files
    (this process's own files left out: an ``EnvCreator`` or a probe env built here)."""
    import json

    where = os.environ.get(PROBE_DIR)
    found = []
    for name in sorted(os.listdir(where)) if where else []:
        if name != f"{os.getpid()}.json":
            try:
                with open(os.path.join(where, name)) as f:
                    found.append(json.load(f))
            except (OSError, ValueError):
                pass
    return _one_or_all([r["threads"] for r in found]), _one_or_all([r["sims"] for r in found])


def _one_or_all(values: list):
    """One value when all are equal, else the sorted distinct values; None when there are none."""
    distinct = sorted(set(values))
    return None if not distinct else distinct[0] if len(distinct) == 1 else distinct


class _CPUMeter:
    """CPU time of this process, of its live descendants (the worker processes), and of the machine."""

    def __init__(self) -> None:
        import psutil

        self._me = psutil.Process()

    def workers(self) -> dict[int, float]:
        out = {}
        for p in self._me.children(recursive=True):
            try:
                t = p.cpu_times()
                out[p.pid] = t.user + t.system
            except Exception:  # noqa: BLE001 - a process that just exited
                pass
        return out

    def snapshot(self) -> tuple:
        return time.process_time(), self.workers(), _machine_jiffies(), time.perf_counter()

    @staticmethod
    def delta(a, b) -> tuple[float, float, float | None]:
        """(main CPU s, workers CPU s, cores kept busy by other processes meanwhile, or None)."""
        main = b[0] - a[0]
        workers = sum(t - a[1].get(pid, 0.0) for pid, t in b[1].items())
        others = None
        if a[2] is not None and b[2] is not None:
            busy_s = (b[2][0] - a[2][0]) / os.sysconf("SC_CLK_TCK")
            others = max(0.0, (busy_s - main - workers) / (b[3] - a[3]))
        return main, workers, others


def _machine_jiffies() -> tuple[int, int] | None:
    """Busy and total jiffies of all cores (Linux /proc/stat), or None."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    return sum(v) - v[3] - v[4], sum(v)


def _measured(frames: int, wall: float, a, b) -> dict:
    main_cpu, workers_cpu, others = _CPUMeter.delta(a, b)
    out = {"units": frames, "wall_s": wall, "cpu_s": main_cpu, "workers_cpu_s": workers_cpu}
    if others is not None:
        out["others_cores"] = round(others, 3)
    return out


def _parse_options(spec: str) -> tuple[str, dict[str, str]]:
    kind, _, rest = spec.partition(":")
    opts: dict[str, str] = {}
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        opts[k] = v or "1"
    return kind, opts


def _set_workers_policy(opts: dict) -> dict:
    """``sched=batch|other``: every thread of this process's descendants (the worker processes) put
    under Linux's ``SCHED_BATCH`` or ``SCHED_OTHER`` (a benchmark's override of what the library's
    workers set for themselves); the policies found, as ``workers_sched``."""
    import psutil

    names = {getattr(os, "SCHED_OTHER", 0): "other", getattr(os, "SCHED_BATCH", 3): "batch"}
    want = opts.get("sched")
    if want is not None and want not in ("batch", "other"):
        raise SystemExit(f"sched={want!r}: batch or other")
    found = set()
    for p in psutil.Process().children(recursive=True):
        try:
            tids = [int(t) for t in os.listdir(f"/proc/{p.pid}/task")]
        except OSError:
            continue
        for tid in tids:
            try:
                if want is not None:
                    os.sched_setscheduler(tid, getattr(os, f"SCHED_{want.upper()}"), os.sched_param(0))
                found.add(names.get(os.sched_getscheduler(tid), "?"))
            except OSError:
                pass
    return {"workers_sched": sorted(found)}


def _time_collector(collector, seconds: float, meter: _CPUMeter) -> dict:
    it = iter(collector)
    next(it)  # warm-up: first reset and one batch, untimed
    startup = child_ready()
    frames = 0
    a = meter.snapshot()
    t0 = time.perf_counter()
    while True:
        batch = next(it)
        frames += batch.numel()
        wall = time.perf_counter() - t0
        if wall >= seconds:
            break
    b = meter.snapshot()
    return {**_measured(frames, wall, a, b), "startup_s": startup}


def gym_vector_env(n: int, repeat: int, opts: dict | None = None):
    """The gym path's vector env, reset and its action space seeded. Options: ``t1`` (one torch
    thread in this process and in each worker, as the library's workers and README set;
    without it both keep torch's default, one thread per core), ``inf`` (each worker's
    ``step`` and ``reset`` under :func:`torch.inference_mode`, as the library's workers run
    theirs; without it the sims run in autograd's default grad mode), ``noshm``
    (``shared_memory=False``: observations pickled through the pipes; gymnasium's default is
    shared memory)."""
    import functools

    import gymnasium as gym

    opts = opts or {}
    threads = 1 if "t1" in opts else None
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    envs = gym.vector.AsyncVectorEnv(
        [functools.partial(_gym_thunk, repeat, threads, "inf" in opts, _rgb(opts))] * n,
        context="forkserver",
        shared_memory="noshm" not in opts,
    )
    envs.reset(seed=SEED)
    envs.action_space.seed(SEED)
    return envs


def child_gym(n: int, repeat: int, seconds: float, opts: dict) -> dict:
    """Frames: the sub-env steps that ran the sim. With gymnasium's default next-step autoreset,
    a sub-env whose step ended its episode spends its next ``step`` call on a reset (its action
    ignored): that call counts ``N`` less those sub-envs. ``credited_frames`` is the former count,
    ``N`` per call (25-step agent episodes: 26 credited per 25 agent steps, +4%)."""
    import numpy as np
    import torch

    meter = _CPUMeter()
    envs = gym_vector_env(n, repeat, opts)
    sample, step = envs.action_space.sample, envs.step
    mode = str(getattr(getattr(envs, "autoreset_mode", None), "value", "next_step"))
    next_step = mode.lower() in ("next_step", "nextstep")  # otherwise every call is N agent steps
    ended = np.zeros(n, dtype=bool)  # the sub-envs whose last step ended their episode
    for _ in range(EPISODE):  # warm-up
        _, _, terminated, truncated, _ = step(sample())
        ended = terminated | truncated
    probes = envs.call("bench_probe")
    startup = child_ready()
    calls = resets = 0
    a = meter.snapshot()
    t0 = time.perf_counter()
    while True:
        for _ in range(10):
            _, _, terminated, truncated, _ = step(sample())
            if next_step:
                resets += int(ended.sum())
                ended = terminated | truncated
        calls += 10
        wall = time.perf_counter() - t0
        if wall >= seconds:
            break
    b = meter.snapshot()
    out = {**_measured(calls * n - resets, wall, a, b), "startup_s": startup}
    out.update(
        main_threads=torch.get_num_threads(),
        worker_threads=_one_or_all([p["threads"] for p in probes]),
        sims=_one_or_all([p["sims"] for p in probes]),
        sub_env0="worker",
        frames_rule=f"sim steps: N per step() call less the sub-envs autoreset in it ({mode} autoreset)",
        credited_frames=calls * n,
        autoreset_steps=resets,
    )
    return out


def child_batched(n: int, repeat: int, seconds: float, opts: dict) -> dict:
    if "t1" in opts:
        import torch

        torch.set_num_threads(1)
    meter = _CPUMeter()
    try:
        collector = batched_collector(n, repeat, opts)
    except Exception as err:  # noqa: BLE001 - reported as a skip, e.g. no batched CPU env yet
        return {"skipped": f"ManiSkillEnv({ENV_ID!r}, num_envs={n}) raised {type(err).__name__}: {err}"}
    sched = _set_workers_policy(opts)
    out = _time_collector(collector, seconds, meter)
    out.update(sched)
    from torchrl.envs import TransformedEnv

    env = collector.env
    engine = getattr(env.base_env if isinstance(env, TransformedEnv) else env, "_env", None)
    in_process = getattr(engine, "in_process", None)  # a CPUVectorEnv (N > 1); None: one env, here
    # The engine's workers run one torch thread each (engines/_worker.py, MakeWorker); sub-env 0
    # in this process steps with this process's threads.
    out.update(_ran(None if in_process is None else 1, _torchrl_sims(env), in_process is not False, _AGENT_STEPS))
    return out


_AGENT_STEPS = "agent steps: the collector's frames (a reset is no frame)"


def _ran(worker_threads, sims, sub_env0_here: bool, frames_rule: str) -> dict:
    """The :data:`RAN_KEYS` of a child: this process's torch threads now, the rest as given."""
    import torch

    return {
        "main_threads": torch.get_num_threads(),
        "worker_threads": worker_threads,
        "sims": sims,
        "sub_env0": "main process" if sub_env0_here else "worker",
        "frames_rule": frames_rule,
    }


def batched_collector(n: int, repeat: int, opts: dict):
    """``Collector(ManiSkillEnv(id, num_envs=n) (-> ActionRepeat), ...)`` with the options' settings."""
    from torchrl.collectors import Collector
    from torchrl.envs import Compose, TransformedEnv

    from maniskill_torchrl import ActionRepeat, ManiSkillEnv

    env = ManiSkillEnv(ENV_ID, num_envs=n, **_maniskill_kwargs(_rgb(opts)), **env_options(opts))
    transforms = []
    if _rgb(opts):  # the rgb pipeline (examples/ppo_torchrl.py --obs rgb): FlattenRGBD first
        from maniskill_torchrl.transforms import FlattenRGBD

        transforms.append(FlattenRGBD(rgb=True, depth=False, state=True))
    if repeat > 1:
        transforms.append(ActionRepeat(repeat))
    if "em" in opts:  # the README's pipeline ends with EpisodeMetrics
        from maniskill_torchrl import EpisodeMetrics

        transforms.append(EpisodeMetrics())
    if "cr" in opts:  # resets from a cache of saved states (cr=K: K of them; default num_envs)
        from maniskill_torchrl.transforms import CachedReset

        transforms.append(CachedReset(num_resets=None if opts["cr"] == "1" else int(opts["cr"]), seed=SEED))
    if transforms:  # one transform bare, as before `em` existed: a Compose costs each step more
        env = TransformedEnv(env, transforms[0] if len(transforms) == 1 else Compose(*transforms))
    env.set_seed(SEED)
    policy, kwargs = collector_options(env, opts)
    return Collector(env, policy=policy, frames_per_batch=EPISODE * n, total_frames=-1, **kwargs)


def collector_options(env, opts: dict) -> tuple:
    """The policy and Collector keywords that ``batched``'s options ask for (docs/guides/torchrl.md)."""
    policy, kwargs = None, {}
    if "rp" in opts:  # the leaf action spec: RandomPolicy skips Composite.rand (root cause 4)
        from torchrl.modules import RandomPolicy

        policy = RandomPolicy(env.action_spec)
    if "dev" in opts:  # a parameterless policy has no device: without this the carrier is cast every step
        kwargs["device"] = env.device
    if "notraj" in opts:
        kwargs["track_traj_ids"] = False
    return policy, kwargs


def child_parallel(n: int, repeat: int, seconds: float, opts: dict) -> dict:
    import functools

    import torch
    from torchrl.collectors import Collector

    if "t1" in opts:
        torch.set_num_threads(1)
    kwargs: dict = {}
    if "nobuf" in opts:
        kwargs["use_buffers"] = False
    if "mp" in opts:
        kwargs["mp_start_method"] = opts["mp"]
    if "lib" in opts or "wait" in opts or "nobatch" in opts:
        from maniskill_torchrl.parallel import ManiSkillParallelEnv as ParallelEnv

        if "wait" in opts:
            kwargs["wait"] = opts["wait"]
    else:
        from torchrl.envs import ParallelEnv
    if "nobatch" in opts:
        kwargs["batch_workers"] = False
    meter = _CPUMeter()
    if opts:
        env = ParallelEnv(n, functools.partial(_worker_env, repeat, **env_options(opts)), **kwargs)
    else:  # as users write it: a lambda (TorchRL wraps it in an EnvCreator, which builds one env here)
        env = ParallelEnv(n, lambda: _worker_env(repeat))
    env.set_seed(SEED)
    policy, collector_kwargs = collector_options(env, opts)
    collector = Collector(env, policy=policy, frames_per_batch=EPISODE * n, total_frames=-1, **collector_kwargs)
    out = _time_collector(collector, seconds, meter)
    threads, sims = _workers_ran()
    out.update(_ran(threads, sims, False, _AGENT_STEPS))
    return out


def child_multisync(n: int, repeat: int, seconds: float, opts: dict) -> dict:
    """``Collector(make_env, backend="process", num_collectors=N)``: one env and one collector
    per process (TorchRL's ``MultiSyncCollector``), batches gathered per batch, not per step."""
    import functools

    from torchrl.collectors import Collector

    meter = _CPUMeter()
    collector = Collector(
        functools.partial(_worker_env, repeat, **env_options(opts)),
        policy=None,
        frames_per_batch=EPISODE * n,
        total_frames=-1,
        backend="process",
        num_collectors=n,
        sync=opts.get("sync", "1") == "1",
    )
    collector.set_seed(SEED)
    out = _time_collector(collector, seconds, meter)
    threads, sims = _workers_ran()
    out.update(_ran(threads, sims, False, _AGENT_STEPS))
    return out


def _async_policy(obs_dim: int, act_dim: int):
    """A batch-agnostic ``Linear -> Tanh`` policy, seeded (module level: a policy process rebuilds it)."""
    import torch
    from tensordict.nn import TensorDictModule

    torch.manual_seed(SEED)
    return TensorDictModule(
        torch.nn.Sequential(torch.nn.Linear(obs_dim, act_dim), torch.nn.Tanh()),
        in_keys=["observation"],
        out_keys=["action"],
    )


def child_async(n: int, repeat: int, seconds: float, opts: dict) -> dict:
    """``AsyncBatchedCollector([make_env] * N, policy=..., env_backend="multiprocessing")``: TorchRL's
    way past lockstep (docs/guides/cpu_performance.md, "Past lockstep"), each worker's env
    ``ManiSkillEnv(id, batch_size=[])`` (-> ActionRepeat), stepped as soon as its action is ready;
    the policy a batch-agnostic ``Linear -> Tanh`` (``RandomPolicy`` takes one fixed batch).
    ``async:lib[,...]`` is the library's path instead (:func:`child_async_lib`)."""
    if "lib" in opts:
        return child_async_lib(n, repeat, seconds, opts)
    import functools

    import torch
    from torchrl.collectors import AsyncBatchedCollector

    torch.set_num_threads(1)
    meter = _CPUMeter()
    make = functools.partial(_worker_env, repeat, batch_size=[])
    probe = make()
    obs_dim, act_dim = probe.observation_spec["observation"].shape[-1], probe.action_spec.shape[-1]
    probe.close()
    policy = functools.partial(_async_policy, obs_dim, act_dim)
    # auto: the workers reach a policy process directly (TorchRL's fast set-up for process workers)
    where = {"policy_factory": policy, "transport": "auto"} if "auto" in opts else {"policy": policy()}
    collector = AsyncBatchedCollector(
        create_env_fn=[make] * n, frames_per_batch=EPISODE * n, total_frames=-1, env_backend="multiprocessing", **where
    )
    out = _time_collector(collector, seconds, meter)
    threads, sims = _workers_ran()
    out.update(_ran(threads, sims, False, "agent steps: the collector's transitions (a reset is no frame)"))
    return out


def child_async_lib(n: int, repeat: int, seconds: float, opts: dict) -> dict:
    """``AsyncPoolCollector(ManiSkillAsyncEnvPool(id, N, repeat=r))``: the library's way past lockstep
    (docs/guides/cpu_performance.md, "Past lockstep"), one lean worker per env (the repeat inside it,
    no TorchRL there), the policy run on whichever envs are done. Options: ``min=K`` (``min_get``,
    the envs waited for before the policy runs; default 1), ``mlp`` (the ``Linear -> Tanh`` policy of
    ``async``; default: random actions, as ``gym`` and ``batched:rp``)."""
    import torch

    from maniskill_torchrl import AsyncPoolCollector, ManiSkillAsyncEnvPool

    torch.set_num_threads(1)
    meter = _CPUMeter()
    pool = ManiSkillAsyncEnvPool(ENV_ID, n, repeat=repeat, **_maniskill_kwargs())
    pool.set_seed(SEED)
    policy = None
    if "mlp" in opts:
        policy = _async_policy(pool.observation_spec["observation"].shape[-1], pool.action_spec.shape[-1])
    collector = AsyncPoolCollector(
        pool, policy, frames_per_batch=EPISODE * n, total_frames=-1, min_get=int(opts.get("min", 1))
    )
    sched = _set_workers_policy(opts)
    out = _time_collector(collector, seconds, meter)
    out.update(sched)
    out.update(_ran(1, "inference", False, "agent steps: the collector's transitions (a reset is no frame)"))
    return out


CHILDREN = {
    "gym": child_gym,
    "batched": child_batched,
    "parallel": child_parallel,
    "multisync": child_multisync,
    "async": child_async,
}


def run_child(spec: str, n: int, repeat: int, seconds: float) -> None:
    _quiet()
    kind, opts = _parse_options(spec)
    if kind not in CHILDREN:
        raise SystemExit(f"unknown pipeline {spec!r}; kinds: {sorted(CHILDREN)}")
    launch = os.environ.get("BENCH_LAUNCH_T")
    t0 = time.perf_counter()
    import tempfile

    # TorchRL's worker envs write what they run here (_record_worker); set before any worker starts
    os.environ[PROBE_DIR] = tempfile.mkdtemp(prefix="bench-probe-")
    # start-up, in parts: the interpreter and this script, then the heavy imports (all from a cold
    # start: the process is fresh), then the pipeline's build and warm-up (startup_s, the sum)
    interp = round(time.time() - float(launch), 2) if launch else None
    import gymnasium  # noqa: F401
    import mani_skill.envs  # noqa: F401
    import torch  # noqa: F401

    if kind != "gym":
        import torchrl.collectors  # noqa: F401

        import maniskill_torchrl  # noqa: F401

        _register_task()
    imports = round(time.perf_counter() - t0, 2)
    out = CHILDREN[kind](n, repeat, seconds, opts)
    import shutil

    shutil.rmtree(os.environ[PROBE_DIR], ignore_errors=True)
    out["interpreter_s"], out["imports_s"] = interp, imports
    out["child_s"] = round(time.perf_counter() - t0, 2)
    child_result(**out)
    sys.stdout.flush()
    # No teardown (closing SAPIEN in every worker takes seconds and is not measured): the parent
    # ends what is left of this process's session (alternate.alternate_processes).
    os._exit(0)
