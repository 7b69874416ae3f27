"""Collection on Ray through TorchRL's own distributed collector, with weight updates.

``Collector(make_env, policy, backend="ray", num_collectors=K, sync=True)`` (TorchRL 0.14;
it builds a :class:`torchrl.collectors.distributed.RayCollector`) starts ``K`` Ray actors,
each running a TorchRL ``Collector`` over one env of this library:

- ``--num-envs 1`` (default): ``ManiSkillEnv(env_id, obs_mode="state", batch_size=[]) ->
  EpisodeMetrics`` (unbatched), one CPU-sim env in the actor process;
- ``--num-envs N``: ``ManiSkillEnv(env_id, num_envs=N) -> EpisodeMetrics``, one batched env
  (on the CPU sim, one process per env: sub-env 0 in the actor, N - 1 workers under it).

Both stay on the CPU sim (``sim_backend="physx_cpu"``) on nodes with a GPU too.

The policy is a small MLP actor (``TensorDictModule``). Between batches its weights are
changed here (a random perturbation; a learner would take an optimiser step) and pushed to
every remote collector with ``collector.update_policy_weights_()``. The policy also writes a
``"policy_version"`` entry, read from a buffer that travels with the weights, so every
batch shows which weights the remote side used; the script also recomputes the actions of
each batch locally from the batch's observations and checks that they match.

Usage::

    python examples/distributed_ray.py                       # local Ray, ray.init(num_cpus=2)
    python examples/distributed_ray.py --collectors 2 --batches 4 --frames-per-batch 200
    python examples/distributed_ray.py --address auto        # join a running cluster (ray start)

Without ``--address`` a local Ray instance is started with ``ray.init(num_cpus=...)``; with
``--address auto`` TorchRL calls ``ray.init(address="auto")`` through
``ray_init_config`` and the actors go wherever the cluster has room. On a cluster every
node needs this package (and ManiSkill's assets) installed, as Ray ships the env factory
and the policy by pickle, not the code they import.

A remote collector that crashes (its env factory raises, or its process dies) makes the
iteration raise a Ray error naming the actor (``ActorDiedError``/``RayTaskError``);
``--crash`` demonstrates it (tests/test_ray.py checks it under a time limit).

Ctrl-C and SIGTERM stop the collection: the script prints the frames (and episodes) collected so far,
shuts the collector and Ray down (its actors and the env workers under them: nothing is left running)
and exits 130 (SIGINT) or 143 (SIGTERM), without a traceback. (``ray.init`` replaces the process's SIGTERM
handler with one that exits 15: the script puts its own back.)
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import signal
import sys
import time
import warnings

import torch
from torch import nn

import stopping

ENV_ID = "PushCube-v1"


def make_env(
    env_id: str = ENV_ID, num_envs: int = 1, max_episode_steps: int | None = None, crash_after: int | None = None
):
    """The env of one remote collector (runs inside the Ray actor).

    ``crash_after=k`` makes the actor's process exit abruptly (``os._exit``) at its k-th step:
    a stand-in for a worker that segfaults or is OOM-killed, to show the error it gives."""
    warnings.filterwarnings("ignore")
    logging.getLogger("mani_skill").setLevel(logging.ERROR)
    from maniskill_torchrl.pipeline import make_env as make_pipeline

    # The CPU sim on every node: with CUDA there, sim_backend="auto" would pick the GPU sim for N > 1.
    kwargs = {"obs_mode": "state", "sim_backend": "physx_cpu"}
    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = max_episode_steps
    # num_envs=None: ManiSkillEnv(batch_size=[]) -> EpisodeMetrics; N: ManiSkillEnv(num_envs=N) -> EpisodeMetrics
    env = make_pipeline(env_id, num_envs=None if num_envs == 1 else num_envs, **kwargs)
    if crash_after is not None:
        env.append_transform(_CrashAfter(crash_after))
    return env


def failing_env():
    """An env factory that raises: the remote collector cannot even start."""
    raise RuntimeError("env factory failed on purpose (failing_env)")


class _CrashAfter:  # built lazily: a Transform subclass defined at import would import torchrl early
    def __new__(cls, steps: int):
        from torchrl.envs import Transform

        class CrashAfter(Transform):
            def __init__(self, steps: int) -> None:
                super().__init__()
                self.left = steps

            def _step(self, td, next_td):
                self.left -= 1
                if self.left <= 0:
                    os._exit(3)  # no exception, no cleanup: the process is just gone
                return next_td

        return CrashAfter(steps)


class VersionedMLP(nn.Module):
    """A small MLP actor whose weights carry a version number (a buffer, synced with them)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int = 32) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, act_dim), nn.Tanh())
        self.register_buffer("version", torch.zeros((), dtype=torch.int64))

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        action = self.net(obs)
        return action, self.version.expand(obs.shape[:-1]).clone()


def make_policy(obs_dim: int, act_dim: int, seed: int = 0):
    from tensordict.nn import TensorDictModule

    torch.manual_seed(seed)
    return TensorDictModule(
        VersionedMLP(obs_dim, act_dim), in_keys=["observation"], out_keys=["action", "policy_version"]
    )


def env_dims(env_id: str) -> tuple[int, int]:
    """Observation and action sizes of one state-obs env (built here once, then closed)."""
    env = make_env(env_id)
    try:
        return env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    finally:
        env.close()


@torch.no_grad()
def new_weights(policy, version: int, scale: float = 0.5) -> None:
    """Stands in for a learner step: perturbs every weight and bumps the version."""
    module = policy.module
    for p in module.net.parameters():
        p.add_(scale * torch.randn_like(p))
    module.version.fill_(version)


def make_collector(
    policy,
    *,
    collectors: int,
    frames_per_batch: int,
    total_frames: int,
    env_fn,
    address: str | None = None,
    num_cpus: int = 2,
    remote_configs=None,
    worker_logs: bool = False,
):
    from torchrl.collectors import Collector

    # TorchRL calls ray.init(**ray_init_config) unless Ray is already initialised, and shuts Ray
    # down again with the collector when it started it.
    ray_init_config = {"address": address} if address is not None else {"num_cpus": num_cpus}
    # Ray prefixes every forwarded worker line with the actor's repr, and a Collector's repr is
    # a whole page: off by default (a worker's error still reaches us as an exception).
    ray_init_config["log_to_driver"] = worker_logs
    if remote_configs is None:
        # One CPU per actor; TorchRL's default also asks for 2 GiB of Ray "memory" per actor.
        remote_configs = {"num_cpus": 1}
    return Collector(
        [env_fn] * collectors,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        backend="ray",
        sync=True,  # every batch: one slice per remote collector, same weights
        backend_options={"ray_init_config": ray_init_config, "remote_configs": remote_configs},
    )


def summarize(batch) -> dict:
    done = batch["next", "done"].squeeze(-1)
    episodes = batch["next", "episode"][done]
    return {
        "frames": batch.numel(),
        "episodes": int(done.sum()),
        "successes": int(episodes["success_once"].sum()) if done.any() else 0,
        "returns": episodes["return"].tolist() if done.any() else [],
    }


def main(argv: list[str] | None = None) -> int:
    with stopping.interruptible():  # SIGTERM as Ctrl-C: the frames so far are printed, then exit 143 (130)
        return _main(argv)


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--env-id", default=ENV_ID, help="ManiSkill task")
    p.add_argument("--collectors", type=int, default=2, help="remote collectors (Ray actors)")
    p.add_argument(
        "--num-envs",
        type=int,
        default=1,
        help="envs per remote collector: 1 = ManiSkillEnv(batch_size=[]); N = ManiSkillEnv(num_envs=N)",
    )
    p.add_argument("--frames-per-batch", type=int, default=200, help="over all collectors")
    p.add_argument("--batches", type=int, default=4, help="batches to collect")
    p.add_argument(
        "--max-episode-steps",
        type=int,
        default=25,
        help="time limit, so that episodes end within a few batches (default 25)",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join ('auto' after `ray start`); default: a local ray.init(num_cpus=...)",
    )
    p.add_argument("--num-cpus", type=int, default=2, help="CPUs of the local Ray instance")
    p.add_argument("--seed", type=int, default=0, help="seed of the policy and the envs")
    p.add_argument("--worker-logs", action="store_true", help="forward the actors' stdout/stderr here")
    p.add_argument(
        "--crash",
        choices=["factory", "exit"],
        default=None,
        help="demonstrate a failing remote collector: its env factory raises, or its process exits",
    )
    args = p.parse_args(argv)
    from maniskill_torchrl._internal.extras import require

    require("ray", "examples/distributed_ray.py")  # the distributed extra, named when missing
    if args.frames_per_batch % args.collectors:
        p.error("--frames-per-batch must be a multiple of --collectors (sync=True splits it evenly)")

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    try:
        obs_dim, act_dim = env_dims(args.env_id)
    except KeyboardInterrupt as err:
        print(f"{stopping.said(err)} before the collection started: 0 frames collected", flush=True)
        return stopping.exit_status(err)
    policy = make_policy(obs_dim, act_dim, seed=args.seed)
    env_fn = functools.partial(make_env, args.env_id, args.num_envs, args.max_episode_steps)
    if args.crash == "factory":
        env_fn = failing_env
    elif args.crash == "exit":
        env_fn = functools.partial(make_env, args.env_id, args.num_envs, args.max_episode_steps, crash_after=5)

    collector = None
    ok = True
    frames = episodes = successes = 0
    t1 = time.perf_counter()
    ours = signal.getsignal(signal.SIGTERM)
    try:
        try:
            collector = make_collector(
                policy,
                collectors=args.collectors,
                frames_per_batch=args.frames_per_batch,
                total_frames=args.frames_per_batch * args.batches,
                env_fn=env_fn,
                address=args.address,
                num_cpus=args.num_cpus,
                worker_logs=args.worker_logs,
            )
        except SystemExit as exc:  # Ray's SIGTERM handler (installed by ray.init) ran during the start-up
            if exc.code == signal.SIGTERM:
                raise stopping.Terminated() from None
            raise
        finally:
            signal.signal(signal.SIGTERM, ours)  # ray.init put sys.exit(15) there: SIGTERM stops as Ctrl-C
        collector.set_seed(args.seed)
        collector.update_policy_weights_()  # version 0 to every remote collector
        print(
            f"{args.collectors} remote collectors of {args.env_id} "
            f"({'ManiSkillEnv(batch_size=[])' if args.num_envs == 1 else f'ManiSkillEnv(num_envs={args.num_envs})'}"
            f" -> EpisodeMetrics), start-up {time.perf_counter() - t0:.1f} s"
        )
        t1 = time.perf_counter()
        for i, batch in enumerate(collector):
            s = summarize(batch)
            frames += s["frames"]
            episodes += s["episodes"]
            successes += s["successes"]
            versions = sorted(set(batch["policy_version"].flatten().tolist()))
            with torch.no_grad():
                local = policy(batch.select("observation").clone())["action"]
            same = torch.allclose(local, batch["action"], atol=1e-5)
            ok &= same and versions == [i]
            print(
                f"batch {i}: {s['frames']} frames {list(batch.shape)}, policy version {versions}, "
                f"actions = local policy's: {same}, episodes finished {s['episodes']}, "
                f"successes {s['successes']}"
            )
            new_weights(policy, version=i + 1)
            collector.update_policy_weights_()  # the next batch runs on version i + 1
        wall = time.perf_counter() - t1
        print(f"frames {frames}  ({frames / wall:.1f} frames/s over {wall:.1f} s)")
        print(f"episodes finished {episodes}")
        print(f"success {successes}/{episodes}" + (f" ({100 * successes / episodes:.1f} %)" if episodes else ""))
        print("remote collectors used the pushed weights: " + ("yes" if ok else "NO"))
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM (stopping.interruptible)
        wall = time.perf_counter() - t1
        print(
            f"{stopping.said(err)} after {frames} frames ({episodes} episodes finished, {successes} successes, "
            f"{wall:.1f} s): shutting the collector and Ray down",
            flush=True,
        )
        return stopping.exit_status(err)
    finally:
        try:
            with stopping.uninterrupted():  # a second signal waits until the actors and Ray are down
                if collector is not None:
                    collector.shutdown()
                import ray

                if ray.is_initialized():
                    ray.shutdown()
        except KeyboardInterrupt:  # that second signal, raised once everything is down: nothing more to stop
            pass
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
