"""SAC on a ManiSkill task with TorchRL: ``ManiSkillEnv`` + this library's transforms + TorchRL's ``SACLoss``.

The env is ``ManiSkillEnv(env_id, num_envs=N)`` through the library's pipeline, with
``IgnoreTerminations``: episodes run to the time limit and no done cuts the bootstrap, which is
ManiSkill's SAC baseline (``partial_reset=False``, ``bootstrap_at_done="always"``). TorchRL's
``SACLoss`` bootstraps from ``("next", "observation")`` unless ``("next", "terminated")``, so the
final observation of each episode (kept by the env at every done) is where the target reads.

Configurations, as ``ppo_torchrl.py``'s (``--sim-backend``, ``--device``: ``sim_device.py``):

- **CPU sim** (default without CUDA): ``ManiSkillEnv(env_id, num_envs=4)``, 4 CPU-sim processes;
  with ``--sim-backend cpu --device cuda`` they feed a learner on the GPU (the env is made with
  ``device="cuda:0"``: batches arrive there).
- **GPU sim** (``--device cuda``, ``--sim-backend auto`` or ``gpu``): one GPU-sim env with
  ``--num-envs`` (default 32) parallel envs.

The loop is TorchRL's: a ``Collector`` (random actions for the first ``--learning-starts`` frames),
a ``ReplayBuffer`` over ``LazyTensorStorage``, ``SACLoss`` with two Q-nets (layer norm) and an
autotuned entropy coefficient, ``SoftUpdate`` target nets. Per collected batch it makes
``--utd`` gradient steps per frame. Hyperparameters are ManiSkill's SAC baseline's (gamma 0.8,
tau 0.005, lr 3e-4, 3x256 MLPs, log-std in [-5, 2], control mode ``pd_joint_delta_pos``) except
where this 2-core CPU needs otherwise: ``--batch-size`` 512 (ManiSkill: 4096 on a GPU) and 4 envs.

Evaluation (``--eval-every`` frames, and at the end) is the PPO example's: ``--eval-episodes``
seeded episodes through ``EpisodeMetrics``, deterministic actions (``tanh(loc)``). The checkpoint
(``<out>/sac_checkpoint.pt``, and ``sac_checkpoint_best.pt`` for the best evaluation) is read by
``examples/evaluate_gym.py --checkpoint``.

Usage::

    python examples/sac_torchrl.py --env-id PushCube-v1 --total-frames 100000
    python examples/sac_torchrl.py --smoke        # a few hundred frames end to end
    python examples/sac_torchrl.py --sim-backend cpu --device cuda   # CPU sim, GPU learner
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate, ValueEstimators

import sim_device
import stopping
from evaluation import episode_stats, evaluate_and_log, make_eval_env, time_limit
from maniskill_torchrl.pipeline import make_env as make_pipeline

CHECKPOINT_FORMAT = "maniskill_torchrl.sac.v1"
BEST = "sac_checkpoint_best.pt"


class BoundedLogStd(nn.Module):
    """``(loc, raw) -> (loc, scale)`` with ``log scale`` in ``[low, high]`` through a tanh, as
    ManiSkill's SAC actor (after SpinUp / Yarats)."""

    def __init__(self, low: float = -5.0, high: float = 2.0) -> None:
        super().__init__()
        self.low, self.high = low, high

    def forward(self, out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, raw = out.chunk(2, -1)
        log_std = self.low + 0.5 * (self.high - self.low) * (torch.tanh(raw) + 1)
        return loc, log_std.exp()


def mlp(sizes: list[int], layer_norm: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-2], sizes[1:-1]):
        layers += [nn.Linear(a, b), *([nn.LayerNorm(b)] if layer_norm else []), nn.ReLU()]
    layers.append(nn.Linear(sizes[-2], sizes[-1]))
    for m in layers:
        if isinstance(m, nn.Linear):  # ManiSkill's weight_init
            nn.init.orthogonal_(m.weight)
            nn.init.zeros_(m.bias)
    return nn.Sequential(*layers)


class QNet(nn.Module):
    """``(observation, action) -> Q``: ManiSkill's SAC critic (layer norm after each hidden layer)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: int) -> None:
        super().__init__()
        self.net = mlp([obs_dim + act_dim, hidden, hidden, hidden, 1], layer_norm=True)

    def forward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([observation, action], -1))


def make_models(
    obs_dim: int, action_spec: Any, hidden: int, device: torch.device
) -> tuple[ProbabilisticActor, ValueOperator]:
    """The actor (TanhNormal over the action bounds) and one Q-net (``SACLoss`` copies it per Q)."""
    act_dim = action_spec.shape[-1]
    actor_net = nn.Sequential(mlp([obs_dim, hidden, hidden, hidden, 2 * act_dim], layer_norm=False), BoundedLogStd())
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
        spec=action_spec,
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high},
        return_log_prob=False,
    ).to(device)
    qnet = ValueOperator(QNet(obs_dim, act_dim, hidden), in_keys=["observation", "action"]).to(device)
    return actor, qnet


def make_objective(args: argparse.Namespace, actor: ProbabilisticActor, qnet: ValueOperator) -> tuple[Any, ...]:
    loss = SACLoss(actor, qnet, num_qvalue_nets=2, loss_function="l2", alpha_init=1.0, target_entropy="auto")
    loss.make_value_estimator(ValueEstimators.TD0, gamma=args.gamma)
    target = SoftUpdate(loss, tau=args.tau)
    optim = {
        "actor": torch.optim.Adam(loss.actor_network_params.values(True, True), lr=args.lr),
        "qvalue": torch.optim.Adam(loss.qvalue_network_params.values(True, True), lr=args.lr),
        "alpha": torch.optim.Adam([loss.log_alpha], lr=args.lr),
    }
    return loss, target, optim


def sac_update(loss: SACLoss, optim: dict[str, torch.optim.Optimizer], batch: Any) -> dict[str, float]:
    """One gradient step of the critics, the actor and the entropy coefficient."""
    out = loss(batch)
    total = out["loss_qvalue"] + out["loss_actor"] + out["loss_alpha"]
    for o in optim.values():
        o.zero_grad(set_to_none=True)
    total.backward()
    for o in optim.values():
        o.step()
    return out


def make_env(args: argparse.Namespace) -> EnvBase:
    """The training env: batch ``[num_envs]``, its outputs on the learner's device (``--device``)."""
    return make_pipeline(
        args.env_id,
        num_envs=args.num_envs,
        ignore_terminations=True,
        **sim_device.env_kwargs(args),
        obs_mode="state",
        control_mode=args.control_mode,
        **({"max_episode_steps": args.max_episode_steps} if args.max_episode_steps else {}),
    )


def save_checkpoint(
    path: Path,
    args: argparse.Namespace,
    env: EnvBase,
    actor: Any,
    loss: SACLoss,
    frames: int,
    evaluation: dict[str, Any] | None = None,
) -> None:
    """What ``examples/ppo_checkpoint.py`` checks and loads (``algorithm`` says which actor to build)."""
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "algorithm": "sac",
            "env_id": args.env_id,
            "obs_mode": "state",
            "control_mode": args.control_mode,
            "obs_dim": env.observation_spec["observation"].shape[-1],
            "act_dim": env.action_spec_unbatched.shape[-1],
            "hidden": args.hidden,
            "repeat": 1,
            "policy": actor.state_dict(),
            "loss": loss.state_dict(),  # the Q-nets, their targets and the entropy coefficient
            "args": vars(args),
            "frames": frames,
            "evaluation": evaluation,
        },
        path,
    )


def train(args: argparse.Namespace) -> dict[str, Any]:
    start = time.perf_counter()
    device = torch.device(args.device)
    torch.manual_seed(args.seed)
    if device.type == "cpu" or args.sim_backend == "cpu":
        # The CPU sim's processes need the cores: this one (sub-env 0's too) keeps to --threads.
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    env = make_env(args)
    env.set_seed(args.seed)
    obs_dim = env.observation_spec["observation"].shape[-1]
    actor, qnet = make_models(obs_dim, env.action_spec_unbatched.to(device), args.hidden, device)
    loss, target, optim = make_objective(args, actor, qnet)
    frames_per_batch = args.num_envs * args.steps_per_batch
    collector = Collector(
        env,
        actor,
        frames_per_batch=frames_per_batch,
        total_frames=math.ceil(args.total_frames / frames_per_batch) * frames_per_batch,
        # whole batches of random actions (TorchRL rounds up, with a warning, otherwise)
        init_random_frames=math.ceil(args.learning_starts / frames_per_batch) * frames_per_batch,
        device=device,
        auto_register_policy_transforms=False,  # a feed-forward policy: no InitTracker needed
    )
    buffer = ReplayBuffer(storage=LazyTensorStorage(args.buffer_size, device=device), batch_size=args.batch_size)
    eval_env = make_eval_env(
        args.env_id,
        args.eval_envs,
        device,
        1,
        sim_backend=args.sim_backend,
        control_mode=args.control_mode,
        **({"max_episode_steps": args.max_episode_steps} if args.max_episode_steps else {}),
    )
    eval_steps = args.max_episode_steps or time_limit(args.env_id)
    log_path = out / "metrics.jsonl"
    log_path.write_text("")

    def log_eval(frames: int, which: str, acting: Any, timing: dict[str, float]) -> dict[str, Any]:
        return evaluate_and_log(eval_env, acting, args, eval_steps, log_path, start, which, frames, **timing)

    timing = {"sim_s": 0.0, "update_s": 0.0}
    log_eval(0, "random", None, timing)
    print(
        f"SAC on {args.env_id} ({args.sim_backend.upper()} sim, {args.num_envs} envs, learner on {args.device}): "
        f"{frames_per_batch} frames per batch, {args.utd} updates per frame, batch {args.batch_size}",
        flush=True,
    )
    frames, updates, best = 0, 0, None
    next_eval = args.eval_every
    t_batch = time.perf_counter()
    record: dict[str, Any] = {}
    progress = stopping.Progress(args.progress_every, total=args.total_frames)
    last_return = None
    stopped: KeyboardInterrupt | None = None
    try:
        for batch in collector:
            timing["sim_s"] += time.perf_counter() - t_batch
            frames += batch.numel()
            buffer.extend(batch.reshape(-1))
            t = time.perf_counter()
            losses = None
            if frames >= args.learning_starts:
                # a signal waits for the updates' end: raised inside TorchRL's functional calls, a
                # KeyboardInterrupt comes out as another error (tensordict's to_module exit)
                with stopping.uninterrupted():
                    for _ in range(max(1, round(args.utd * batch.numel()))):
                        losses = sac_update(loss, optim, buffer.sample().to(device))
                        target.step()
                        updates += 1
                collector.update_policy_weights_()
            timing["update_s"] += time.perf_counter() - t
            ended = batch["next", "done"].squeeze(-1)
            if ended.any():
                last_return = batch["next", "episode", "return"][ended].float().mean().item()
            progress.update(frames, last_return, updates=updates)
            out_of_time = args.max_minutes is not None and time.perf_counter() - start >= 60 * args.max_minutes
            last = frames >= args.total_frames or out_of_time
            if frames >= next_eval or last:
                next_eval += args.eval_every
                stats = episode_stats(batch)
                record = {"frames": frames, "updates": updates, **{f"train_{k}": v for k, v in stats.items()}}
                if losses is not None:
                    record.update({k: losses[k].item() for k in ("loss_qvalue", "loss_actor", "alpha")})
                record.update(log_eval(frames, "policy", actor, {k: round(v, 1) for k, v in timing.items()}))
                if best is None or record.get("success_once", 0) > best.get("success_once", 0):
                    best = record
                    with stopping.uninterrupted():
                        save_checkpoint(out / BEST, args, env, actor, loss, frames, evaluation=best)
            if last:
                break
            t_batch = time.perf_counter()
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM (stopping.interruptible): keep the run so far
        stopped = err
        print(f"{stopping.said(err)} after {frames} frames: saving the run so far", flush=True)
    collector.shutdown()
    if not env.is_closed:
        env.close()
    eval_env.close()
    with stopping.uninterrupted():
        save_checkpoint(out / "sac_checkpoint.pt", args, env, actor, loss, frames, evaluation=record)
    best_line = ""
    if best is not None:
        best_line = f"; best success_once {best.get('success_once', 0):.2f} at {best['frames']} frames: {out / BEST}"
    print(f"saved {out / 'sac_checkpoint.pt'}{best_line}; metrics log: {log_path}", flush=True)
    if stopped is not None:
        record["stopped"] = stopping.said(stopped)
        record["exit_status"] = stopping.exit_status(stopped)
    return record


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--env-id", default="PushCube-v1", help="ManiSkill task")
    p.add_argument("--smoke", action="store_true", help="a few hundred frames on 2 CPU-sim envs, end to end")
    sim_device.add_arguments(p)
    p.add_argument("--num-envs", type=int, default=None, help="default: 32 on the GPU sim, 4 on the CPU sim")
    p.add_argument("--steps-per-batch", type=int, default=8, help="steps per env per collected batch")
    p.add_argument("--total-frames", type=int, default=200_000, help="frames to collect")
    p.add_argument("--learning-starts", type=int, default=4_000, help="random-action frames before the updates")
    p.add_argument("--buffer-size", type=int, default=1_000_000, help="replay buffer capacity in frames")
    p.add_argument("--batch-size", type=int, default=512, help="samples per gradient step")
    p.add_argument("--utd", type=float, default=0.5, help="gradient steps per collected frame")
    p.add_argument("--control-mode", default="pd_joint_delta_pos", help="ManiSkill's controller of the agent")
    p.add_argument(
        "--max-episode-steps", type=int, default=None, help="episode length (default: the task's time limit)"
    )
    p.add_argument("--hidden", type=int, default=256, help="width of the MLPs of actor and Q-nets")
    p.add_argument("--lr", type=float, default=3e-4, help="Adam's learning rate")
    p.add_argument("--gamma", type=float, default=0.8, help="discount")
    p.add_argument("--tau", type=float, default=0.005, help="the target Q-nets' soft-update rate")
    p.add_argument("--threads", type=int, default=1, help="torch threads of this process on the CPU sim or learner")
    p.add_argument("--eval-every", type=int, default=20_000, help="frames between evaluations")
    p.add_argument("--eval-episodes", type=int, default=50, help="seeded episodes per evaluation")
    p.add_argument(
        "--eval-envs", type=int, default=None, help="default: --eval-episodes on the GPU sim, 2 on the CPU sim"
    )
    p.add_argument("--eval-seed", type=int, default=10_000, help="evaluation episodes use seeds from here")
    p.add_argument("--max-minutes", type=float, default=None, help="stop after this much wall time, then evaluate")
    p.add_argument(
        "--progress-every",
        type=float,
        default=15.0,
        help="seconds between progress lines (frames, frames/s, last return) between evaluations; -1: none",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of envs, policy and sampling")
    p.add_argument(
        "--out", default="outputs/sac", help="output folder: sac_checkpoint.pt, sac_checkpoint_best.pt, metrics.jsonl"
    )
    args = p.parse_args(argv)
    sim_device.check_arguments(p, args, smoke=args.smoke)
    gpu = args.sim_backend == "gpu"  # the GPU sim's defaults; a GPU learner on the CPU sim takes the CPU sim's
    if args.num_envs is None:
        args.num_envs = 2 if args.smoke else (32 if gpu else 4)
    if args.eval_envs is None:
        args.eval_envs = args.eval_episodes if gpu else 2
    if args.smoke:
        args.total_frames, args.learning_starts, args.eval_every, args.eval_episodes = 400, 100, 400, 2
        args.batch_size, args.hidden = 64, 32
    for name in ("num_envs", "steps_per_batch", "total_frames", "batch_size", "hidden", "eval_episodes", "eval_envs"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.utd <= 0:
        p.error(f"--utd must be > 0, got {args.utd}")
    sim_device.cpu_fallback_note(args, f"{args.num_envs} envs, {args.total_frames:,} frames")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from maniskill_torchrl._internal.rendering import quiet_maniskill

    quiet_maniskill()  # ManiSkill's notes that say nothing actionable here (no CUDA to render with, task builders')
    with stopping.interruptible():  # SIGTERM as Ctrl-C: the run so far is saved, then exit 143 (130)
        record = train(args)
    return record.get("exit_status", 0)


if __name__ == "__main__":  # the CPU env's workers start with spawn/forkserver: keep the entry point guarded
    sys.exit(main())
