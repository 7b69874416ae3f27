"""Behaviour cloning from ManiSkill motion-planning demonstrations, with TorchRL.

The data path is the library's: ManiSkill's own motion planner writes the demonstrations
(:func:`maniskill_torchrl.data.motion_planning.make_demos`, run on demand; it needs a numpy 1 for ManiSkill's
planner, which ``make setup`` makes and whose absence it names), ManiSkill's ``replay_trajectory`` converts them to
``--control-mode`` with state observations, and :class:`~maniskill_torchrl.data.ManiSkillExperienceReplay`
reads the file as a TorchRL replay buffer laid out as the env's steps. The policy then runs, unchanged,
on ``ManiSkillEnv`` with TorchRL's ``InitTracker`` + ``CatFrames`` (observation history) and
``MultiStepActorWrapper`` (action chunks), and ``EpisodeMetrics`` scores it on seeded episodes.

Two policies, both reading the last ``--obs-horizon`` observations and predicting the next
``--pred-horizon`` actions, of which ``--act-horizon`` are executed before re-planning (the settings of
ManiSkill's Diffusion Policy baseline: 2, 16, 8):

- ``--policy mlp`` (default): an MLP regressing the chunk with a mean-squared error;
- ``--policy diffusion``: a small diffusion policy, DDPM with an MLP noise predictor (ManiSkill's
  baseline uses a 1-D conv U-Net) and an exponential moving average of its weights; it needs many
  more iterations than the MLP (benchmarks/RESULTS.md, "Behaviour cloning").

Observations are standardised and actions scaled to [-1, 1] per dimension with the demonstrations'
statistics (kept in the checkpoint): in ``pd_ee_delta_pos`` the arm's deltas span a few hundredths
and the gripper's command is +-1, and without the scaling the loss hardly sees the arm.

Evaluation follows ManiSkill's BC / Diffusion Policy baselines: episodes run to the time limit
(``IgnoreTerminations``), success_once over ``--eval-episodes`` seeded episodes, and
``--max-episode-steps 100`` (the demonstrations take 70-100 steps; the registered limit of
PickCube-v1 and PushCube-v1 is 50). Evaluation seeds start at ``--eval-seed`` (10000), far from the
demonstrations' seeds (0 to ``--num-demos``).

Usage::

    python examples/bc_torchrl.py --env-id PickCube-v1            # makes the demos if missing
    python examples/bc_torchrl.py --env-id PushCube-v1 --num-demos 500
    python examples/bc_torchrl.py --smoke                         # end-to-end in about a minute
    python examples/bc_torchrl.py --device cuda --sim-backend cpu # GPU learner, CPU-sim evaluation

The learner runs on ``--device`` (default: the CPU; the policies are small) and the evaluation env is
made with ``--sim-backend`` (``sim_device.py``: ``auto`` is the GPU sim with ``--device cuda``, else
the CPU sim) and ``device=<--device>``, so that its observations arrive on the learner's device.

Writes ``<out>/metrics.jsonl`` (one line per evaluation), ``<out>/bc_checkpoint.pt`` (the policy
with its normalisation, settings and last evaluation) and prints one line per evaluation.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from torchrl.envs import CatFrames, EnvBase, InitTracker, TransformedEnv
from torchrl.modules import MultiStepActorWrapper

import sim_device
import stopping
from maniskill_torchrl.data import ManiSkillExperienceReplay

CHECKPOINT_FORMAT = "maniskill_torchrl.bc/1"


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The description as written, every option's default shown."""


# --------------------------------------------------------------------------- data
def demo_file(args: argparse.Namespace) -> Path:
    """The converted demonstration file; made with :func:`~maniskill_torchrl.data.motion_planning.make_demos`
    under ``--demo-dir`` (as given, resolved once: the same folder whatever the script's location) when missing."""
    from maniskill_torchrl.data.motion_planning import Numpy1Missing, make_demos

    if args.demos is not None:
        path = Path(args.demos)
        if not path.exists():
            raise SystemExit(f"--demos {path}: no such file")
        return path
    try:
        return make_demos(args.env_id, args.num_demos, args.control_mode, args.demo_dir)
    except (Numpy1Missing, RuntimeError) as err:
        raise SystemExit(f"making the demonstrations failed: {err}") from None


class ChunkDataset:
    """Every step of every demonstration as (observation history, action chunk) pairs.

    As ManiSkill's Diffusion Policy baseline pads them: the history repeats an episode's first
    observation before its start, the chunk repeats its last action after its end. Built once from
    the replay buffer's storage as index tables, so that a batch is two gathers."""

    def __init__(self, demos: ManiSkillExperienceReplay, obs_horizon: int, pred_horizon: int) -> None:
        steps = demos[:]  # the whole (memory-mapped) storage, laid out as the env's steps
        self.observation = steps["observation"].float()
        self.action = steps["action"].float()
        traj = steps["collector", "traj_ids"]
        n = traj.shape[0]
        idx = torch.arange(n)
        new = torch.ones(n, dtype=torch.bool)
        new[1:] = traj[1:] != traj[:-1]
        start = torch.cummax(torch.where(new, idx, 0), 0).values  # each step's episode start
        last = torch.ones(n, dtype=torch.bool)
        last[:-1] = traj[1:] != traj[:-1]
        end = torch.flip(torch.cummin(torch.flip(torch.where(last, idx, n), [0]), 0).values, [0])  # episode's last step
        back = torch.arange(-(obs_horizon - 1), 1)
        ahead = torch.arange(pred_horizon)
        self.obs_index = torch.maximum(idx[:, None] + back, start[:, None])
        self.act_index = torch.minimum(idx[:, None] + ahead, end[:, None])
        self.episodes = int(new.sum())
        self.obs_mean = self.observation.mean(0)
        self.obs_std = self.observation.std(0).clamp_min(1e-2)

    def __len__(self) -> int:
        return self.obs_index.shape[0]

    def sample(self, batch: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        i = torch.randint(len(self), (batch,), generator=generator)
        obs = self.observation[self.obs_index[i]].flatten(1)  # (batch, obs_horizon * obs_dim), oldest first
        return obs, self.action[self.act_index[i]]  # (batch, pred_horizon, act_dim)


# --------------------------------------------------------------------------- models
def mlp(dims: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-2], dims[1:-1]):
        layers += [nn.Linear(a, b), nn.Mish()]
    return nn.Sequential(*layers, nn.Linear(dims[-2], dims[-1]))


class Normalise(nn.Module):
    """The observation history to zero mean and unit scale, and actions to [-1, 1] per dimension
    (their range in the demonstrations: the arm's deltas span a few hundredths, the gripper's
    command is +-1, so that a plain loss would hardly see the arm). Buffers: the checkpoint carries them."""

    def __init__(
        self, obs_mean: torch.Tensor, obs_std: torch.Tensor, horizon: int, act_low: torch.Tensor, act_high: torch.Tensor
    ) -> None:
        super().__init__()
        self.register_buffer("mean", obs_mean.repeat(horizon))
        self.register_buffer("std", obs_std.repeat(horizon))
        self.register_buffer("act_center", (act_high + act_low) / 2)
        self.register_buffer("act_scale", ((act_high - act_low) / 2).clamp_min(1e-4))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return (obs - self.mean) / self.std

    def action(self, chunk: torch.Tensor) -> torch.Tensor:
        return (chunk - self.act_center) / self.act_scale

    def unaction(self, chunk: torch.Tensor) -> torch.Tensor:
        return chunk * self.act_scale + self.act_center


class ChunkMLP(nn.Module):
    """Regresses the action chunk: observation history -> (pred_horizon, act_dim)."""

    def __init__(self, obs_dim: int, act_dim: int, pred_horizon: int, hidden: int, depth: int) -> None:
        super().__init__()
        self.shape = (pred_horizon, act_dim)
        self.net = mlp([obs_dim, *[hidden] * depth, pred_horizon * act_dim])

    def loss(self, obs: torch.Tensor, chunk: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return (self(obs) - chunk).pow(2).mean()

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs).unflatten(-1, self.shape).clamp(-1, 1)


class DiffusionMLP(nn.Module):
    """DDPM over the action chunk (epsilon prediction, squared-cosine schedule, as ManiSkill's
    Diffusion Policy baseline), with an MLP noise predictor conditioned on the observation history
    and a sinusoidal embedding of the diffusion step. Actions arrive normalised to [-1, 1]
    (:class:`Normalise`), so samples are clipped there."""

    def __init__(
        self, obs_dim: int, act_dim: int, pred_horizon: int, hidden: int, depth: int, steps: int = 100
    ) -> None:
        super().__init__()
        self.shape = (pred_horizon, act_dim)
        self.steps = steps
        self.embed_dim = 64
        self.net = mlp([pred_horizon * act_dim + obs_dim + self.embed_dim, *[hidden] * depth, pred_horizon * act_dim])
        s = 0.008  # the squared-cosine schedule of Nichol & Dhariwal, as diffusers' "squaredcos_cap_v2"
        t = torch.arange(steps + 1, dtype=torch.float64) / steps
        alpha_bar = torch.cos((t + s) / (1 + s) * math.pi / 2) ** 2
        betas = (1 - alpha_bar[1:] / alpha_bar[:-1]).clamp(max=0.999)
        alphas = 1 - betas
        self.register_buffer("betas", betas.float())
        self.register_buffer("alphas", alphas.float())
        self.register_buffer("alpha_bar", torch.cumprod(alphas, 0).float())

    def _embed(self, t: torch.Tensor) -> torch.Tensor:
        half = self.embed_dim // 2
        freq = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device) / half)
        angle = t.float()[:, None] * freq[None]
        return torch.cat([angle.sin(), angle.cos()], -1)

    def _eps(self, noisy: torch.Tensor, obs: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([noisy.flatten(1), obs, self._embed(t)], -1))

    def loss(self, obs: torch.Tensor, chunk: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        b = chunk.shape[0]
        # drawn on the CPU generator (the same numbers whatever the device), then moved to the data
        t = torch.randint(self.steps, (b,), generator=generator).to(chunk.device)
        noise = torch.randn(chunk.shape, generator=generator).to(chunk.device)
        ab = self.alpha_bar[t].view(b, 1, 1)
        noisy = ab.sqrt() * chunk + (1 - ab).sqrt() * noise
        return (self._eps(noisy, obs, t) - noise.flatten(1)).pow(2).mean()

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        b = obs.shape[0]
        x = torch.randn(b, *self.shape, device=obs.device)
        for t in range(self.steps - 1, -1, -1):
            tt = torch.full((b,), t, device=obs.device)
            eps = self._eps(x, obs, tt).view_as(x)
            ab, a, beta = self.alpha_bar[t], self.alphas[t], self.betas[t]
            x0 = ((x - (1 - ab).sqrt() * eps) / ab.sqrt()).clamp(-1, 1)
            if t == 0:
                x = x0
                break
            ab_prev = self.alpha_bar[t - 1]
            # the DDPM posterior mean from the clipped x0, and its variance
            mean = (ab_prev.sqrt() * beta / (1 - ab)) * x0 + (a.sqrt() * (1 - ab_prev) / (1 - ab)) * x
            var = beta * (1 - ab_prev) / (1 - ab)
            x = mean + var.clamp_min(1e-20).sqrt() * torch.randn_like(x)
        return x


class ChunkPolicy(nn.Module):
    """Normalisation + the model; the module the TorchRL actor wraps and the checkpoint holds."""

    def __init__(self, normalise: Normalise, model: nn.Module) -> None:
        super().__init__()
        self.normalise = normalise
        self.model = model

    def loss(self, obs: torch.Tensor, chunk: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return self.model.loss(self.normalise(obs), self.normalise.action(chunk), generator)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.normalise.unaction(self.model(self.normalise(obs)))


def make_policy(settings: dict[str, Any], data: ChunkDataset | None = None) -> ChunkPolicy:
    """The policy ``settings`` describe, normalised by ``data``'s statistics; without ``data`` the
    normalisation is the identity until a checkpoint's state dict is loaded."""
    obs_dim, act_dim = settings["obs_dim"], settings["act_dim"]
    if data is not None:
        stats = (data.obs_mean, data.obs_std, data.action.amin(0), data.action.amax(0))
    else:
        stats = (torch.zeros(obs_dim), torch.ones(obs_dim), -torch.ones(act_dim), torch.ones(act_dim))
    cls = DiffusionMLP if settings["policy"] == "diffusion" else ChunkMLP
    model = cls(
        obs_dim * settings["obs_horizon"],
        settings["act_dim"],
        settings["pred_horizon"],
        settings["hidden"],
        settings["depth"],
    )
    mean, std, low, high = stats
    return ChunkPolicy(Normalise(mean, std, settings["obs_horizon"], low, high), model)


def make_actor(policy: ChunkPolicy, settings: dict[str, Any]) -> MultiStepActorWrapper:
    """The TorchRL actor: predicts a chunk from ``"observation_history"`` every ``act_horizon`` steps
    (and at every reset, from ``"is_init"``), and hands out one action per step in between."""
    chunk = TensorDictModule(policy, in_keys=["observation_history"], out_keys=["action_chunk"])
    return MultiStepActorWrapper(chunk, n_steps=settings["pred_horizon"], replan_interval=settings["act_horizon"])


def with_history(env: EnvBase, obs_horizon: int) -> TransformedEnv:
    """``InitTracker`` (for the chunk wrapper) and the last ``obs_horizon`` observations, oldest first,
    as ``"observation_history"``; after a reset the history repeats the first observation, as the
    training data's padding does. Appended to ``env``'s transforms where it has some."""
    env = env if isinstance(env, TransformedEnv) else TransformedEnv(env)
    env.append_transform(InitTracker())
    env.append_transform(CatFrames(N=obs_horizon, dim=-1, in_keys=["observation"], out_keys=["observation_history"]))
    return env


# --------------------------------------------------------------------------- training
def evaluate(args: argparse.Namespace, policy: nn.Module, settings: dict[str, Any]) -> dict[str, float]:
    from evaluation import evaluate_policy, make_eval_env  # shared with the PPO and SAC examples

    env = with_history(
        make_eval_env(
            args.env_id,
            args.eval_envs,
            torch.device(args.device),
            sim_backend=args.sim_backend,
            obs_mode="state",
            control_mode=args.control_mode,
            max_episode_steps=args.max_episode_steps,
        ),
        settings["obs_horizon"],
    )
    try:
        torch.manual_seed(args.eval_seed)  # the diffusion policy's sampling noise
        return evaluate_policy(
            env, make_actor(policy, settings), args.eval_episodes, args.eval_seed, args.max_episode_steps
        )
    finally:
        env.close()


def train(args: argparse.Namespace) -> dict[str, Any]:
    t0 = time.perf_counter()
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    path = demo_file(args)
    t_demos = time.perf_counter() - t0
    demos = ManiSkillExperienceReplay(
        path, args.batch_size, env_id=args.env_id, success_only=True, num_episodes=args.num_demos
    )
    data = ChunkDataset(demos, args.obs_horizon, args.pred_horizon)
    settings = {
        "policy": args.policy,
        "env_id": args.env_id,
        "control_mode": args.control_mode,
        "obs_horizon": args.obs_horizon,
        "pred_horizon": args.pred_horizon,
        "act_horizon": args.act_horizon,
        "obs_dim": data.observation.shape[-1],
        "act_dim": data.action.shape[-1],
        "hidden": args.hidden,
        "depth": args.depth,
    }
    device = torch.device(args.device)
    policy = make_policy(settings, data).to(device)
    ema = AveragedModel(policy, multi_avg_fn=get_ema_multi_avg_fn(args.ema))
    optim = torch.optim.AdamW(policy.parameters(), lr=args.lr, weight_decay=1e-6)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(optim, args.iterations)
    gen = torch.Generator().manual_seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = (out / "metrics.jsonl").open("w")
    print(
        f"{args.env_id}: {data.episodes} demos, {len(data)} steps ({path}, {t_demos:.0f} s); "
        f"{args.policy} policy, {sum(p.numel() for p in policy.parameters())} parameters, "
        f"learner on {args.device}, {args.sim_backend.upper()}-sim evaluation",
        flush=True,
    )
    losses: list[float] = []
    record: dict[str, Any] = {}
    t_train = time.perf_counter()
    stopped: KeyboardInterrupt | None = None
    t_line = time.perf_counter()
    it = 0
    try:
        for it in range(1, args.iterations + 1):
            obs, chunk = (x.to(device) for x in data.sample(args.batch_size, gen))
            loss = policy.loss(obs, chunk, gen)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            sched.step()
            ema.update_parameters(policy)
            losses.append(loss.item())
            if it % 100 == 0 and time.perf_counter() - t_line >= args.progress_every >= 0:
                t_line = time.perf_counter()
                print(f"it {it:6d}/{args.iterations}  loss {sum(losses) / len(losses):.4f}", flush=True)
            if it % args.eval_every == 0 or it == args.iterations:
                t_eval = time.perf_counter()
                result = evaluate(args, ema.module.eval(), settings)
                record = {
                    "iteration": it,
                    "loss": sum(losses) / len(losses),
                    "wall_s": time.perf_counter() - t0,
                    "train_s": t_eval - t_train,
                    "eval_s": time.perf_counter() - t_eval,
                    **result,
                }
                losses.clear()
                print(
                    f"it {it:6d}  loss {record['loss']:.4f}  success_once {result['success_once']:.2f}  "
                    f"at_end {result['success_at_end']:.2f}  wall {record['wall_s']:.0f} s  "
                    f"(eval {record['eval_s']:.0f} s)",
                    flush=True,
                )
                log.write(json.dumps(record) + "\n")
                log.flush()
                t_train += time.perf_counter() - t_eval  # train_s counts gradient steps only
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM (stopping.interruptible): keep the run so far
        stopped = err
        print(f"{stopping.said(err)} at iteration {it}: saving the policy so far", flush=True)
    log.close()
    with stopping.uninterrupted():
        state = {"format": CHECKPOINT_FORMAT, "settings": settings, "policy": ema.module.state_dict()}
        torch.save({**state, "evaluation": record}, out / "bc_checkpoint.pt")
    print(f"saved {out / 'bc_checkpoint.pt'}; metrics log: {out / 'metrics.jsonl'}", flush=True)
    if stopped is not None:
        record = {**record, "stopped": stopping.said(stopped), "exit_status": stopping.exit_status(stopped)}
    return record


def load_policy(path: str | Path) -> tuple[MultiStepActorWrapper, dict[str, Any]]:
    """The actor saved by :func:`train`, and its settings (env_id, control_mode, horizons)."""
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a bc_torchrl.py checkpoint (format {ckpt.get('format')!r})")
    settings = ckpt["settings"]
    policy = make_policy(settings)
    policy.load_state_dict(ckpt["policy"])
    return make_actor(policy.eval(), settings), settings


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("--env-id", default="PickCube-v1", help="ManiSkill task (one with a motion-planning solution)")
    p.add_argument("--demos", default=None, help="a converted ManiSkill .h5 (default: made under --demo-dir)")
    p.add_argument("--demo-dir", default="demos", help="folder of the made demos: <demo-dir>/<env-id>/motionplanning")
    p.add_argument("--num-demos", type=int, default=1000, help="successful demonstrations to plan and train on")
    p.add_argument("--control-mode", default="pd_ee_delta_pos", help="control mode of the demos and the policy")
    p.add_argument("--policy", choices=["mlp", "diffusion"], default="mlp", help="chunk regression or DDPM")
    p.add_argument("--obs-horizon", type=int, default=2, help="observations the policy reads (history)")
    p.add_argument("--pred-horizon", type=int, default=16, help="actions predicted per chunk")
    p.add_argument("--act-horizon", type=int, default=8, help="actions of a chunk executed before re-planning")
    p.add_argument("--hidden", type=int, default=512, help="MLP width")
    p.add_argument("--depth", type=int, default=3, help="MLP hidden layers")
    p.add_argument("--iterations", type=int, default=5000, help="gradient steps")
    p.add_argument("--batch-size", type=int, default=256, help="samples per gradient step")
    p.add_argument("--lr", type=float, default=1e-3, help="AdamW learning rate (cosine-annealed)")
    p.add_argument("--ema", type=float, default=0.999, help="decay of the weights' moving average (evaluated)")
    p.add_argument("--eval-every", type=int, default=2500, help="iterations between evaluations")
    p.add_argument("--eval-episodes", type=int, default=100, help="seeded episodes per evaluation")
    p.add_argument("--eval-envs", type=int, default=2, help="batched envs for evaluation")
    p.add_argument("--eval-seed", type=int, default=10_000, help="evaluation episodes use seeds from here")
    p.add_argument("--max-episode-steps", type=int, default=100, help="evaluation episode length")
    p.add_argument("--seed", type=int, default=0, help="seed of the model, the sampling and the demos' order")
    p.add_argument("--threads", type=int, default=2, help="torch threads of this process")
    p.add_argument("--out", default="outputs/bc", help="output folder: metrics.jsonl, bc_checkpoint.pt")
    p.add_argument("--progress-every", type=float, default=15.0, help="seconds between loss lines; -1: none")
    p.add_argument("--smoke", action="store_true", help="20 demos, 300 iterations, 4 evaluation episodes")
    sim_device.add_arguments(p, cpu_default=True)
    args = p.parse_args(argv)
    sim_device.check_arguments(p, args, cpu_default=True, smoke=args.smoke)
    if args.smoke:
        args.num_demos, args.iterations, args.eval_every, args.eval_episodes = 20, 300, 300, 4
    if not 1 <= args.act_horizon <= args.pred_horizon:
        p.error("--act-horizon must be in [1, --pred-horizon]")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from maniskill_torchrl._internal.rendering import quiet_maniskill

    quiet_maniskill()  # ManiSkill's notes that say nothing actionable here (no CUDA to render with, task builders')
    with stopping.interruptible():  # SIGTERM as Ctrl-C: the policy so far is saved, then exit 143 (130)
        record = train(args)
    print(json.dumps(record))
    return record.get("exit_status", 0)


if __name__ == "__main__":  # the evaluation env's workers re-import this file
    sys.exit(main())
