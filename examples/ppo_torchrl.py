"""PPO on a ManiSkill task with TorchRL: ``ManiSkillEnv`` + this library's transforms.

Two simulators (``--sim-backend``; the learner's device is ``--device``):

- **GPU sim** (``--sim-backend gpu``, or ``auto`` with ``--device cuda``: the
  default where ``torch.cuda.is_available()``): one ManiSkill GPU-sim env with
  ``--num-envs`` parallel envs (512) is one batched TorchRL env
  (``ManiSkillEnv(env_id, num_envs=512, sim_backend="gpu")``, batch
  ``[512]``); partial resets go through TorchRL's ``"_reset"`` mask.
- **CPU sim** (``--sim-backend cpu``, or ``auto`` with ``--device cpu``): the same call,
  ``ManiSkillEnv(env_id, num_envs=4)``, on the CPU sim: one batched TorchRL env over 4
  processes (one CPU-sim env each, the first in this one), the fastest CPU path
  (``benchmarks/RESULTS.md``). ``--vec parallel`` / ``--vec serial`` stack single unbatched
  ``ManiSkillEnv(batch_size=[])`` envs in a ``ParallelEnv`` / ``SerialEnv`` instead.
  With ``--device cuda`` the CPU sim feeds a GPU learner: the env is made with
  ``device="cuda:0"``, so batches arrive on the GPU.
  ``--smoke`` is a few hundred frames through 2 batched CPU envs that checks
  the whole loop end to end in well under a minute (``--smoke --device cuda``: the
  same on the CPU sim, the learner on the GPU).

Either way the env then gets ``ActionRepeat`` (``--repeat``, optional),
``EpisodeMetrics`` (return, length, success once / at end per episode) and,
with ``--bootstrap-at-done always`` (the default), ``IgnoreTerminations(as_truncations=True)``;
the training loop is TorchRL's: ``Collector`` -> ``GAE`` -> a replay buffer
with ``SamplerWithoutReplacement`` -> ``ClipPPOLoss``, with a
``ProbabilisticActor`` (``TanhNormal``, state-independent scale) and a
``ValueOperator``. Hyperparameters follow ManiSkill's PPO baseline
(gamma 0.8, lambda 0.9, 3x256 Tanh MLPs, normalised advantages).

Per iteration it prints frames, finished episodes, mean return, success rate
and losses; at the end it saves the policy and value state dicts to
``<out>/ppo_checkpoint.pt`` and the log to ``<out>/metrics.jsonl``. The policy of
the evaluation with the highest success_once so far is kept in
``<out>/ppo_checkpoint_best.pt`` (with that evaluation's figures).

Usage::

    python examples/ppo_torchrl.py                 # GPU: PushCube-v1, 512 envs
    python examples/ppo_torchrl.py --smoke         # CPU: end-to-end check
    python examples/ppo_torchrl.py --device cpu --num-envs 4 --total-frames 20000
    python examples/ppo_torchrl.py --sim-backend cpu --device cuda   # CPU sim, GPU learner
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs import EnvBase, ParallelEnv, SerialEnv, TransformedEnv
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

import sim_device
import stopping
from evaluation import (  # noqa: F401 (names kept here)
    episode_stats,
    evaluate_and_log,
    evaluate_policy,
    make_eval_env,
    time_limit,
)
from maniskill_torchrl.pipeline import make_env as make_pipeline
from maniskill_torchrl.transforms import IgnoreTerminations

CHECKPOINT_FORMAT = "maniskill_torchrl.ppo.v1"
BEST = "ppo_checkpoint_best.pt"  # the policy of the evaluation with the highest success_once

warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")


# ----------------------------------------------------------------------------- envs
def make_cpu_env(env_id: str, repeat: int, env_kwargs: dict[str, Any]) -> EnvBase:
    """One CPU-sim worker: ``ManiSkillEnv(batch_size=[]) -> ActionRepeat -> EpisodeMetrics`` (batch ``[]``).

    Module-level so that ``functools.partial`` of it pickles into ``ParallelEnv`` workers.
    ActionRepeat sits in the worker (no inter-process round trip per inner step);
    EpisodeMetrics after it, so episode lengths count agent steps.
    """
    return make_pipeline(env_id, repeat=repeat, sim_backend="physx_cpu", **env_kwargs)


def _env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    env_kwargs: dict[str, Any] = {"obs_mode": "state", "control_mode": args.control_mode}
    if args.obs == "rgb":
        # ManiSkill's PPO-from-rgb baseline: its cameras' rgb (no depth) beside the flattened state
        # (FlattenRGBDObservationWrapper(rgb=True, depth=False, state=...)), at --image-size pixels.
        size = {"width": args.image_size, "height": args.image_size}
        env_kwargs.update(obs_mode="rgb", sensor_configs=size)
        env_kwargs["flatten_rgbd"] = {"rgb": True, "depth": False, "state": args.include_state}
    if args.max_episode_steps is not None:
        env_kwargs["max_episode_steps"] = args.max_episode_steps
    return env_kwargs


def make_env(args: argparse.Namespace) -> EnvBase:
    """The training env: batch ``[num_envs]``, its outputs on the learner's device (``--device``).

    ``--bootstrap-at-done always`` (ManiSkill's baseline): episodes still end at success, but as
    truncations (``IgnoreTerminations(as_truncations=True)``), so GAE bootstraps from the final
    observation's value at every done: a success termination must not look like the end of all
    future reward, or the policy learns to hover short of success."""
    env_kwargs = _env_kwargs(args)
    if args.vec == "batched":
        # A batched TorchRL env on either sim (one GPU simulator, or one CPU worker per env): no CPUUnbatch.
        env = make_pipeline(
            args.env_id, num_envs=args.num_envs, repeat=args.repeat, **sim_device.env_kwargs(args), **env_kwargs
        )
    else:
        # The CPU sim's workers step on the CPU; the batched env hands their outputs over on --device.
        make = functools.partial(make_cpu_env, args.env_id, args.repeat, env_kwargs)
        if args.vec == "serial":
            env = SerialEnv(args.num_envs, make, device=args.device)
        else:
            env = ParallelEnv(args.num_envs, make, mp_start_method="spawn", device=args.device)
    if args.bootstrap_at_done == "always":
        # auto_unwrap: appended to the pipeline's TransformedEnv, as TorchRL's default does (said, so that TorchRL
        # does not warn about nested TransformedEnvs on every run)
        env = TransformedEnv(env, IgnoreTerminations(as_truncations=True), auto_unwrap=True)
    return env


def _time_limit(args: argparse.Namespace) -> int:
    return time_limit(args.env_id, args.max_episode_steps)


# --------------------------------------------------------------------------- models
class NatureCNN(nn.Module):
    """ManiSkill's PPO-from-rgb encoder (``ppo_rgb.py``'s ``NatureCNN``): three convolutions and a 256-unit
    layer over the rgb images (``[*batch, H, W, C]`` uint8, scaled to [0, 1]), a 256-unit linear layer over the
    state where there is one, the two concatenated."""

    def __init__(self, rgb_shape: torch.Size, state_dim: int | None, device: torch.device) -> None:
        super().__init__()
        channels = rgb_shape[-1]
        self.cnn = nn.Sequential(
            nn.Conv2d(channels, 32, kernel_size=8, stride=4),
            nn.ReLU(),
            nn.Conv2d(32, 64, kernel_size=4, stride=2),
            nn.ReLU(),
            nn.Conv2d(64, 64, kernel_size=3, stride=1),
            nn.ReLU(),
            nn.Flatten(),
        ).to(device)
        with torch.no_grad():
            flat = self.cnn(torch.zeros(1, channels, *rgb_shape[-3:-1], device=device)).shape[-1]
        self.fc = nn.Sequential(nn.Linear(flat, 256), nn.ReLU()).to(device)
        self.state = nn.Linear(state_dim, 256).to(device) if state_dim else None
        self.out_features = 256 + (256 if state_dim else 0)

    def forward(self, rgb: torch.Tensor, state: torch.Tensor | None = None) -> torch.Tensor:
        batch = rgb.shape[:-3]
        images = rgb.reshape(-1, *rgb.shape[-3:]).permute(0, 3, 1, 2).float() / 255.0
        features = [self.fc(self.cnn(images)).reshape(*batch, -1)]
        if self.state is not None:
            features.append(self.state(state))
        return torch.cat(features, -1)


def _head(inputs: int, out: int, device: torch.device) -> nn.Sequential:
    """ManiSkill's PPO-from-rgb heads over the encoder: 512 ReLU units, then the output."""
    return nn.Sequential(nn.Linear(inputs, 512), nn.ReLU(), nn.Linear(512, out)).to(device)


def make_models(env: EnvBase, hidden: int, device: torch.device) -> tuple[ProbabilisticActor, ValueOperator]:
    """The actor (TanhNormal over the action bounds) and the critic. From ``"observation"``: two 3-layer Tanh
    MLPs. From ``"rgb"`` (and ``"state"``, ``--obs rgb``): ManiSkill's NatureCNN encoder, shared by both, with a
    512-unit head each (``ClipPPOLoss`` sees the shared parameters once)."""
    spec = env.observation_spec
    action_spec = env.action_spec_unbatched
    act_dim = action_spec.shape[-1]
    if "rgb" in spec.keys():
        state_dim = spec["state"].shape[-1] if "state" in spec.keys() else None
        encoder = NatureCNN(spec["rgb"].shape, state_dim, device)
        keys = ["rgb", "state"] if state_dim else ["rgb"]
        common = TensorDictModule(encoder, in_keys=keys, out_keys=["features"])
        actor_net = nn.Sequential(
            _head(encoder.out_features, act_dim, device),
            AddStateIndependentNormalScale(act_dim, init_value=-0.5, device=device),
        )
        actor_module = TensorDictSequential(
            common, TensorDictModule(actor_net, in_keys=["features"], out_keys=["loc", "scale"])
        )
        value_net = _head(encoder.out_features, 1, device)
        value = TensorDictSequential(common, TensorDictModule(value_net, ["features"], ["state_value"]))
        last_layers = ((actor_net[0], 0.01), (value_net, 1.0))
    else:
        obs_dim = spec["observation"].shape[-1]

        def mlp(out: int) -> MLP:
            return MLP(
                in_features=obs_dim, out_features=out, num_cells=[hidden] * 3, activation_class=nn.Tanh, device=device
            )

        actor_net = nn.Sequential(
            mlp(act_dim),
            # ManiSkill's baseline: a learnt, state-independent log std starting at -0.5.
            AddStateIndependentNormalScale(act_dim, init_value=-0.5, device=device),
        )
        actor_module = TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"])
        value = ValueOperator(mlp(1), in_keys=["observation"])
        last_layers = ((actor_net[0], 0.01), (value.module, 1.0))
    policy = ProbabilisticActor(
        actor_module,
        spec=env.full_action_spec_unbatched.to(device),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={
            "low": action_spec.space.low.to(device),
            "high": action_spec.space.high.to(device),
        },
        return_log_prob=True,
        default_interaction_type=ExplorationType.RANDOM,
    )
    # Small last layers: near-zero initial actions and values, as in ManiSkill's baseline.
    with torch.no_grad():
        for net, std in last_layers:
            last = [m for m in net.modules() if isinstance(m, nn.Linear)][-1]
            nn.init.orthogonal_(last.weight, std)
            last.bias.zero_()
    return policy, value


def make_objective(
    args: argparse.Namespace, policy: ProbabilisticActor, value: ValueOperator
) -> tuple[GAE, ClipPPOLoss, torch.optim.Optimizer]:
    """GAE, the clipped PPO loss (normalised advantages, L2 critic) and its Adam optimiser."""
    advantage = GAE(gamma=args.gamma, lmbda=args.lmbda, value_network=value, average_gae=False)
    loss_module = ClipPPOLoss(
        policy,
        value,
        clip_epsilon=args.clip_epsilon,
        entropy_bonus=args.entropy_coeff > 0,
        entropy_coeff=args.entropy_coeff,
        critic_coeff=args.critic_coeff,
        loss_critic_type="l2",
        normalize_advantage=True,
    )
    optim = torch.optim.Adam(loss_module.parameters(), lr=args.lr, eps=1e-5)
    return advantage, loss_module, optim


def ppo_update(
    args: argparse.Namespace,
    batch: TensorDictBase,
    advantage: GAE,
    buffer: ReplayBuffer,
    loss_module: ClipPPOLoss,
    optim: torch.optim.Optimizer,
    updates_per_epoch: int,
) -> tuple[int, TensorDictBase]:
    """``--epochs`` passes of minibatch updates over ``batch``; returns the updates made and the last losses.

    Advantages come from the current critic each epoch, as in TorchRL's PPO tutorial. With
    ``--target-kl``, the updates stop once the policy has moved that far (approximate KL) from the
    one that collected ``batch``, as in ManiSkill's baseline.
    """
    updates = 0
    for _ in range(args.epochs):
        with torch.no_grad():
            advantage(batch)
        buffer.empty()
        buffer.extend(batch.reshape(-1))
        for _ in range(updates_per_epoch):
            losses = loss_module(buffer.sample())
            if args.target_kl is not None and losses["kl_approx"].item() > args.target_kl:
                return updates, losses
            loss = losses["loss_objective"] + losses["loss_critic"]
            if "loss_entropy" in losses.keys():
                loss = loss + losses["loss_entropy"]
            optim.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(loss_module.parameters(), args.max_grad_norm)
            optim.step()
            updates += 1
    return updates, losses


# ------------------------------------------------------------------------- logging
# ---------------------------------------------------------------------------- train
def train(args: argparse.Namespace) -> dict[str, Any]:
    """Runs PPO; returns the last iteration's log record."""
    start = time.perf_counter()  # wall time from here: env start-up, training and evaluation
    device = torch.device(args.device)  # cuda with its index (sim_device.check_arguments)
    torch.manual_seed(args.seed)
    if device.type == "cpu" or args.sim_backend == "cpu":
        # The CPU sim's processes need the cores: this one (sub-env 0's too) keeps to --threads.
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    env = make_env(args)
    env.set_seed(args.seed)
    policy, value = make_models(env, args.hidden, device)

    frames_per_batch = args.num_envs * args.num_steps
    total_frames = math.ceil(args.total_frames / frames_per_batch) * frames_per_batch
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        device=device,
        auto_register_policy_transforms=False,  # a feed-forward policy: no InitTracker needed
    )
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(frames_per_batch, device=device),
        sampler=SamplerWithoutReplacement(),
        batch_size=args.minibatch_size,
    )
    advantage, loss_module, optim = make_objective(args, policy, value)
    iterations = total_frames // frames_per_batch
    updates_per_epoch = max(1, frames_per_batch // args.minibatch_size)
    print(
        f"PPO on {args.env_id} ({args.sim_backend.upper()} sim, {args.num_envs} envs, "
        f"ActionRepeat({args.repeat}), learner on {args.device}): {iterations} iterations x {frames_per_batch} frames, "
        f"{args.epochs} epochs x {updates_per_epoch} minibatches of {args.minibatch_size}",
        flush=True,
    )

    log_path = out / "metrics.jsonl"
    log_path.write_text("")
    eval_env = None
    if args.eval_every > 0:
        eval_env = make_eval_env(
            args.env_id, args.eval_envs, device, args.repeat, sim_backend=args.sim_backend, **_env_kwargs(args)
        )
        eval_steps = -(-_time_limit(args) // args.repeat)  # ceil: a last partial repeat still counts

        def log_eval(frames: int, train_s: float, which: str, acting: Any) -> dict[str, float]:
            extra = {"train_s": round(train_s, 1), "env_id": args.env_id}  # the task: benchmarks.plot_ppo's title
            rec = evaluate_and_log(eval_env, acting, args, eval_steps, log_path, start, which, frames, **extra)
            return {k: rec[k] for k in ("episodes", "success_once", "success_at_end", "return") if k in rec}

        log_eval(0, 0.0, "random", None)
        log_eval(0, 0.0, "policy", policy)
    frames = 0
    record: dict[str, Any] = {}
    best: dict[str, Any] | None = None  # the best evaluation so far, saved as BEST
    t0 = time.perf_counter()
    eval_s = 0.0  # wall time spent evaluating, not counted as training time
    stopped: KeyboardInterrupt | None = None
    try:
        for it, batch in enumerate(collector, 1):
            if args.anneal_lr:  # linear decay to 0 over --total-frames, as CleanRL's / ManiSkill's anneal_lr
                for group in optim.param_groups:
                    group["lr"] = args.lr * (1.0 - frames / total_frames)
            frames += batch.numel()
            record = {"iteration": it, "frames": frames, **episode_stats(batch)}
            with stopping.uninterrupted():  # as sac_torchrl.py: a signal waits for the update's end
                updates, losses = ppo_update(args, batch, advantage, buffer, loss_module, optim, updates_per_epoch)
            collector.update_policy_weights_()
            record.update(
                loss_objective=losses["loss_objective"].item(),
                loss_critic=losses["loss_critic"].item(),
                kl_approx=losses["kl_approx"].item(),
                updates=updates,
                frames_per_s=round(frames / (time.perf_counter() - t0 - eval_s), 1),
                train_s=round(time.perf_counter() - t0 - eval_s, 1),
                wall_s=round(time.perf_counter() - start, 1),
            )
            with log_path.open("a") as f:
                f.write(json.dumps(record) + "\n")
            print(_format(record), flush=True)
            out_of_time = args.max_minutes is not None and time.perf_counter() - start >= 60 * args.max_minutes
            every = args.eval_every
            crossed = eval_env is not None and frames // every > (frames - batch.numel()) // every
            if eval_env is not None and (crossed or it == iterations or out_of_time):
                t = time.perf_counter()
                res = log_eval(frames, record["train_s"], "policy", policy)
                if "success_once" in res and (best is None or res["success_once"] > best["success_once"]):
                    best = {"frames": frames, **res}
                    with stopping.uninterrupted():
                        save_checkpoint(out / BEST, args, env, policy, value, frames, evaluation=best)
                eval_s += time.perf_counter() - t
            if out_of_time:
                print(f"--max-minutes {args.max_minutes} reached after {frames} frames: stopping", flush=True)
                break
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM (stopping.interruptible): keep the run so far
        stopped = err
        print(f"{stopping.said(err)} after {frames} frames: saving the run so far", flush=True)
    collector.shutdown()
    if not env.is_closed:
        env.close()
    if eval_env is not None:
        eval_env.close()

    ckpt = out / "ppo_checkpoint.pt"
    with stopping.uninterrupted():
        save_checkpoint(ckpt, args, env, policy, value, frames)
    print(f"saved checkpoint: {ckpt}")
    if best is not None:
        print(f"best evaluation (success_once {best['success_once']:.2f} at {best['frames']} frames): {out / BEST}")
    print(f"metrics log: {log_path}")
    if stopped is not None:
        record["stopped"] = stopping.said(stopped)
        record["exit_status"] = stopping.exit_status(stopped)
    return record


def save_checkpoint(
    path: Path,
    args: argparse.Namespace,
    env: EnvBase,
    policy: ProbabilisticActor,
    value: ValueOperator,
    frames: int,
    evaluation: dict[str, Any] | None = None,
) -> None:
    """The policy and critic with what ``examples/ppo_checkpoint.py`` checks before loading them."""
    torch.save(
        {
            "format": CHECKPOINT_FORMAT,
            "env_id": args.env_id,
            "obs_mode": "rgb" if args.obs == "rgb" else "state",
            "control_mode": args.control_mode,
            "obs_dim": env.observation_spec["observation"].shape[-1] if args.obs == "state" else None,
            "act_dim": env.action_spec_unbatched.shape[-1],
            "hidden": args.hidden,
            "repeat": args.repeat,
            "policy": policy.state_dict(),
            "value": value.state_dict(),
            "args": vars(args),
            "frames": frames,
            "evaluation": evaluation,
        },
        path,
    )


def _format(rec: dict[str, Any]) -> str:
    parts = [f"iter {rec['iteration']:3d}", f"frames {rec['frames']:8d}", f"episodes {rec['episodes']:4d}"]
    for key, name, spec in (
        ("return", "return", ".3f"),
        ("episode_len", "len", ".1f"),
        ("success_once", "success_once", ".2f"),
        ("loss_objective", "loss_pi", ".4f"),
        ("loss_critic", "loss_v", ".4f"),
        ("frames_per_s", "fps", ".0f"),
    ):
        if key in rec:
            parts.append(f"{name} {rec[key]:{spec}}")
    return " | ".join(parts)


# ----------------------------------------------------------------------------- args
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Flags; ``--smoke`` fills in a tiny CPU configuration for whatever was not given."""
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--env-id", default="PushCube-v1", help="ManiSkill task")
    p.add_argument("--smoke", action="store_true", help="tiny CPU-sim run: 2 batched CPU envs, a few hundred frames")
    sim_device.add_arguments(p)
    p.add_argument("--num-envs", type=int, default=None, help="default: 512 on the GPU sim, 2 on the CPU sim")
    p.add_argument(
        "--vec",
        choices=("batched", "parallel", "serial"),
        default="batched",
        help="batched: ManiSkillEnv(num_envs=--num-envs) (one GPU simulator, or one CPU worker "
        "process per env); parallel / serial: a ParallelEnv / SerialEnv of unbatched "
        "CPU envs",
    )
    p.add_argument("--num-steps", type=int, default=None, help="rollout steps per env per iteration")
    p.add_argument(
        "--total-frames",
        type=int,
        default=None,
        help="frames to collect; default 300 with --smoke, 2,000,000 on the GPU sim, 300,000 on the CPU sim",
    )
    p.add_argument("--repeat", type=int, default=1, help="ActionRepeat")
    p.add_argument("--control-mode", default="pd_joint_delta_pos", help="ManiSkill's controller of the agent")
    p.add_argument(
        "--max-episode-steps", type=int, default=None, help="episode length (default: the task's time limit)"
    )
    p.add_argument(
        "--epochs",
        type=int,
        default=None,
        help="PPO epochs per batch; default 2 with --smoke, 4 on the GPU sim, 8 on the CPU sim",
    )
    p.add_argument(
        "--minibatch-size",
        type=int,
        default=None,
        help="frames per minibatch; default 50 with --smoke, 800 on the GPU sim, 50 on the CPU sim",
    )
    p.add_argument(
        "--obs",
        choices=("state", "rgb"),
        default="state",
        help="state: the task's state vector; rgb: its cameras' rgb (and the state, see --no-state) through "
        "FlattenRGBD and ManiSkill's NatureCNN, as ManiSkill's PPO-from-rgb baseline",
    )
    p.add_argument("--image-size", type=int, default=64, help="camera width and height in pixels with --obs rgb")
    p.add_argument(
        "--no-state",
        dest="include_state",
        action="store_false",
        help="--obs rgb without the state beside the images (ManiSkill's --no-include-state)",
    )
    p.add_argument("--hidden", type=int, default=256, help="width of the 3-layer Tanh MLPs of actor and critic")
    p.add_argument("--lr", type=float, default=3e-4, help="Adam's learning rate")
    p.add_argument("--anneal-lr", action="store_true", help="decay the learning rate linearly to 0 over --total-frames")
    p.add_argument("--gamma", type=float, default=0.8, help="discount")
    p.add_argument("--lmbda", type=float, default=0.9, help="GAE's lambda")
    p.add_argument(
        "--bootstrap-at-done",
        choices=("always", "never"),
        default="always",
        help="always: bootstrap from the final observation's value at every done, success terminations "
        "included (ManiSkill's PPO baseline); never: a termination ends the return (TorchRL's GAE default)",
    )
    p.add_argument("--clip-epsilon", type=float, default=0.2, help="ClipPPOLoss's clip range")
    p.add_argument("--entropy-coeff", type=float, default=0.0, help="entropy bonus weight (0: none)")
    p.add_argument(
        "--target-kl",
        type=float,
        default=None,
        help="stop an iteration's updates once the approximate KL to the collecting policy exceeds this "
        "(ManiSkill's baseline: 0.1); default: no stop",
    )
    p.add_argument("--critic-coeff", type=float, default=0.5, help="value loss weight")
    p.add_argument("--max-grad-norm", type=float, default=0.5, help="gradient clipping norm")
    p.add_argument("--threads", type=int, default=1, help="torch threads of this process on the CPU sim or learner")
    p.add_argument(
        "--eval-every",
        type=int,
        default=None,
        help="evaluate every this many frames (0: never); default 0 with --smoke, 20000 on the CPU, 200000 on the GPU",
    )
    p.add_argument("--eval-episodes", type=int, default=50, help="seeded episodes per evaluation")
    p.add_argument(
        "--eval-envs",
        type=int,
        default=None,
        help="parallel evaluation envs; default: --eval-episodes on the GPU, 2 on the CPU",
    )
    p.add_argument("--eval-seed", type=int, default=10_000, help="evaluation episodes use seeds from here")
    p.add_argument(
        "--max-minutes",
        type=float,
        default=None,
        help="stop after this much wall time (training and evaluation), with a last evaluation",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of envs, policy and sampling")
    p.add_argument(
        "--out", default="outputs/ppo", help="output folder: ppo_checkpoint.pt, ppo_checkpoint_best.pt, metrics.jsonl"
    )
    args = p.parse_args(argv)

    sim_device.check_arguments(p, args, smoke=args.smoke)
    gpu = args.sim_backend == "gpu"  # the GPU sim's defaults; a GPU learner on the CPU sim takes the CPU sim's
    if gpu and args.vec != "batched":
        p.error(f"--vec {args.vec} is for the CPU sim: the GPU sim is one batched env (--vec batched)")
    # Defaults per configuration: (num_envs, num_steps, total_frames, epochs, minibatch).
    if args.smoke:
        defaults = (2, 50, 300, 2, 50)
    elif gpu:
        defaults = (512, 50, 2_000_000, 4, 800)
    else:
        defaults = (2, 100, 300_000, 8, 50)  # chosen on the CPU sim: benchmarks/RESULTS.md, "PPO"
    for name, value in zip(("num_envs", "num_steps", "total_frames", "epochs", "minibatch_size"), defaults):
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.eval_every is None:
        args.eval_every = 0 if args.smoke else (200_000 if gpu else 20_000)
    if args.eval_envs is None:
        args.eval_envs = args.eval_episodes if gpu else min(2, args.eval_episodes)
    for name in (
        "num_envs",
        "num_steps",
        "total_frames",
        "epochs",
        "minibatch_size",
        "repeat",
        "hidden",
        "threads",
        "eval_episodes",
        "eval_envs",
    ):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.obs == "rgb" and args.image_size < 36:
        p.error(f"--image-size must be >= 36 with --obs rgb (NatureCNN's convolutions), got {args.image_size}")
    if args.minibatch_size > args.num_envs * args.num_steps:
        p.error(
            f"--minibatch-size ({args.minibatch_size}) exceeds the frames per iteration "
            f"(--num-envs x --num-steps = {args.num_envs * args.num_steps})"
        )
    sim_device.cpu_fallback_note(args, f"{args.num_envs} envs, {args.total_frames:,} frames")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from maniskill_torchrl._internal.rendering import quiet_maniskill

    quiet_maniskill()  # ManiSkill's notes that say nothing actionable here (no CUDA to render with, task builders')
    with stopping.interruptible():  # SIGTERM as Ctrl-C: the run so far is saved, then exit 143 (130)
        record = train(args)
    return record.get("exit_status", 0)


if __name__ == "__main__":  # ParallelEnv spawns workers: keep the entry point guarded
    sys.exit(main())
