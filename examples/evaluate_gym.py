"""Evaluate a policy as ManiSkill's baselines do: gymnasium's ``AsyncVectorEnv`` of ``CPUGymWrapper`` envs.

Each sub-env is ``CPUGymWrapper(gym.make(env_id, num_envs=1, ...),
ignore_terminations=True, record_metrics=True)``, imported from
``maniskill_torchrl.wrappers`` instead of ``mani_skill.utils.wrappers`` (the
one line that changes): episodes run to the time limit and every step's info
carries ``info["episode"]`` (``success_once``, ``success_at_end``, ``return``,
``episode_len``...). The script prints those for each finished episode and
their averages.

``--checkpoint PATH`` evaluates what ``examples/ppo_torchrl.py``, ``examples/sac_torchrl.py`` or
``examples/trainers/train.py`` saved (``ppo_checkpoint.pt`` / ``sac_checkpoint.pt`` / the run folder's
``policy.pt``, whose actor is rebuilt from the config saved with it; loaded and checked by
``ppo_checkpoint.load_checkpoint``):
its task and control mode by default, its actor acting deterministically (the
TanhNormal's ``tanh(loc)`` scaled to the action bounds), episode ``k`` seeded
``--seed + k``. ``--video PATH`` writes the first ``--video-episodes`` episodes
to an mp4 (sub-envs made with ``render_mode="rgb_array"``, the task's default
render camera). ``--backend torchrl`` runs the same evaluation on the TorchRL
side instead: ``evaluation.make_eval_env`` (``ManiSkillEnv(num_envs=N) ->
IgnoreTerminations -> EpisodeMetrics``) and ``evaluation.evaluate_policy``,
which print the averages; on the same seeds both backends give the same numbers.

The vector env uses ``context="forkserver"``: gymnasium's default ``fork``
hangs once SAPIEN is loaded in the parent. forkserver (like spawn) re-imports
this file in the workers, hence the ``if __name__ == "__main__"`` guard and
the module-level env factory.

Ctrl-C and SIGTERM stop the evaluation: the script prints the averages of the episodes finished so far
and how many they are, closes its vector env (the workers ignore SIGINT and finish their step; a worker
that a signal killed is terminated) and exits 130 (SIGINT) or 143 (SIGTERM), without a traceback.

Usage::

    python examples/evaluate_gym.py --env-id PickCube-v1 --num-envs 4 --episodes 8
    python examples/evaluate_gym.py --policy zero --max-episode-steps 20
    python examples/evaluate_gym.py --checkpoint outputs/ppo/ppo_checkpoint.pt --episodes 10 --video eval.mp4
    python examples/evaluate_gym.py --checkpoint outputs/ppo/ppo_checkpoint.pt --backend torchrl
    python examples/evaluate_gym.py --checkpoint outputs/<date>/<time>/policy.pt   # a train.py run
"""

from __future__ import annotations

import argparse
import functools
import multiprocessing
import signal
import sys
import time
import warnings
from typing import Any

import gymnasium as gym
import numpy as np

import stopping

CLOSE_TIMEOUT_S = 30.0  # a pending step of the workers may finish before they close; then they are terminated


def make_env(
    env_id: str,
    max_episode_steps: int | None,
    obs_mode: str,
    control_mode: str | None = None,
    repeat: int = 1,
    render: bool = False,
) -> gym.Env:
    """One evaluation env, built inside a vector-env worker (hence module-level and picklable)."""
    if multiprocessing.parent_process() is not None:
        # A worker: Ctrl-C reaches the whole process group, and the main process stops the evaluation and
        # closes the workers (gymnasium's worker would report a KeyboardInterrupt as its error).
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    import mani_skill.envs  # noqa: F401  (registers the tasks in the worker)

    from maniskill_torchrl._internal.rendering import quiet_maniskill

    # was: from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper
    #      from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper
    from maniskill_torchrl.wrappers.action_repeat import ActionRepeatWrapper
    from maniskill_torchrl.wrappers.gymnasium import CPUGymWrapper

    warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")
    # In every worker process (and gymnasium's dummy env in this one): ManiSkill's notes that say nothing
    # actionable here (no CUDA to render with: it renders on the CPU; its task builders' "no initial pose").
    quiet_maniskill()
    kwargs: dict[str, Any] = {"num_envs": 1, "obs_mode": obs_mode, "sim_backend": "physx_cpu"}
    if max_episode_steps is not None:
        kwargs["max_episode_steps"] = max_episode_steps
    if control_mode is not None:
        kwargs["control_mode"] = control_mode
    if render:
        kwargs["render_mode"] = "rgb_array"
    env = gym.make(env_id, **kwargs)
    if repeat > 1:
        # Note: ActionRepeatWrapper sits inside CPUGymWrapper (its required place), so it stops
        # repeating at a termination (a success); the TorchRL backend's IgnoreTerminations sits
        # before ActionRepeat and keeps repeating. With repeat > 1 the two backends can
        # therefore differ on episodes that succeed mid-repeat; with repeat 1 they agree.
        env = ActionRepeatWrapper(env, repeat)
    return CPUGymWrapper(env, ignore_terminations=True, record_metrics=True)


def close_envs(envs: gym.vector.VectorEnv) -> None:
    """Closes ``envs``, also in the middle of a step (after Ctrl-C or SIGTERM): the pending step is waited
    for (``CLOSE_TIMEOUT_S`` at most), then the workers close; workers that a signal killed, or that do
    not answer, are terminated. Either way no process or pipe is left."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Calling `close` while waiting for a pending call.*")
        try:
            envs.close(timeout=CLOSE_TIMEOUT_S)
        except (Exception, KeyboardInterrupt):  # a dead worker's pipe (EOFError), a timeout, a second signal
            # What close(terminate=True) does, without first waiting again for the step that failed.
            for process in envs.processes:
                if process.is_alive():
                    process.terminate()
            for pipe in envs.parent_pipes:
                if pipe is not None:
                    pipe.close()
            for process in envs.processes:
                process.join()
            envs.closed = True


def evaluate(args: argparse.Namespace, episodes: list[dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    """Runs ``args.episodes`` episodes over ``args.num_envs`` envs; returns one record per episode.

    The records are appended to ``episodes`` (a new list by default) as the episodes finish: after a
    ``KeyboardInterrupt`` (Ctrl-C, SIGTERM) it holds the finished ones."""
    episodes = [] if episodes is None else episodes
    thunk = functools.partial(make_env, args.env_id, args.max_episode_steps, args.obs_mode)
    envs = gym.vector.AsyncVectorEnv([thunk] * args.num_envs, context="forkserver")
    try:
        envs.action_space.seed(args.seed)
        obs, _ = envs.reset(seed=args.seed)  # sub-env i is seeded with seed + i
        zero = np.zeros(envs.action_space.shape, dtype=envs.action_space.dtype)
        while len(episodes) < args.episodes:
            action = zero if args.policy == "zero" else envs.action_space.sample()
            obs, reward, terminated, truncated, infos = envs.step(action)
            done = np.logical_or(terminated, truncated)
            if not done.any():
                continue
            # gymnasium >= 1.0 (next-step autoreset): the done step's info is the episode's last;
            # the next step() resets those envs and ignores their action.
            ep = infos["episode"]
            for i in np.flatnonzero(done):
                if len(episodes) == args.episodes:
                    break
                rec = {"env": int(i)}
                for key in ("success_once", "success_at_end", "fail_once", "fail_at_end", "return", "episode_len"):
                    if key in ep:
                        rec[key] = ep[key][i].item()
                episodes.append(rec)
                print(_format(len(episodes), rec), flush=True)
    finally:
        close_envs(envs)
    return episodes


METRICS = ("success_once", "success_at_end", "fail_once", "fail_at_end", "return", "episode_len")


def evaluate_checkpoint(
    args: argparse.Namespace, ckpt: dict[str, Any], episodes: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """The checkpoint's policy over ``args.episodes`` episodes, ``args.num_envs`` at a time (appended to
    ``episodes`` as each round finishes, as in :func:`evaluate`).

    Episodes run in rounds of ``num_envs``: each round starts with
    ``envs.reset(seed=args.seed + first)`` (sub-env ``i`` gets ``seed + first + i``), so
    episode ``k`` is seeded ``seed + k``, as in ``evaluation.evaluate_policy``. With
    ``ignore_terminations=True`` all sub-envs of a round end together, at the time limit.
    """
    from ppo_checkpoint import numpy_policy, policy_from_checkpoint, specs_from_spaces

    render = args.video is not None
    thunk = functools.partial(
        make_env, args.env_id, args.max_episode_steps, args.obs_mode, args.control_mode, ckpt["repeat"], render
    )
    envs = gym.vector.AsyncVectorEnv([thunk] * args.num_envs, context="forkserver")
    try:
        specs = specs_from_spaces(envs.single_observation_space, envs.single_action_space)
        act = numpy_policy(policy_from_checkpoint(ckpt, specs, args.control_mode))
        episodes = [] if episodes is None else episodes
        videos: dict[int, list[np.ndarray]] = {}  # episode index -> frames
        for first in range(0, args.episodes, args.num_envs):
            recording = [i for i in range(args.num_envs) if first + i < min(args.video_episodes, args.episodes)]
            obs, _ = envs.reset(seed=args.seed + first)
            if render and recording:
                _add_frames(videos, envs, first, recording)
            while True:
                obs, reward, terminated, truncated, infos = envs.step(act(obs))
                if render and recording:
                    _add_frames(videos, envs, first, recording)  # before any reset: the last frame is kept
                done = np.logical_or(terminated, truncated)
                if done.all():
                    break
                if done.any():
                    raise RuntimeError(
                        f"sub-envs {np.flatnonzero(done).tolist()} ended before the others "
                        "although terminations are ignored"
                    )
            ep = infos["episode"]
            for i in range(min(args.num_envs, args.episodes - first)):
                rec: dict[str, Any] = {"env": i, "seed": args.seed + first + i}
                for key in METRICS:
                    if key in ep:
                        rec[key] = ep[key][i].item()
                episodes.append(rec)
                print(_format(len(episodes), rec), flush=True)
        if render:
            fps = max(1, round(envs.call("get_wrapper_attr", "control_freq")[0] / ckpt["repeat"]))
            frames = [f for k in sorted(videos) for f in videos[k]]
            _write_video(args.video, frames, fps)
            print(f"video: {args.video} ({len(videos)} episodes, {len(frames)} frames, {fps} fps)")
    finally:
        close_envs(envs)
    return episodes


def _add_frames(
    videos: dict[int, list[np.ndarray]], envs: gym.vector.VectorEnv, first: int, recording: list[int]
) -> None:
    images = envs.call("render")  # one frame per sub-env (all render; only the recorded ones are kept)
    for i in recording:
        videos.setdefault(first + i, []).append(np.asarray(images[i]))


def _write_video(path: str, frames: list[np.ndarray], fps: int) -> None:
    from maniskill_torchrl._internal.extras import require

    imageio = require("imageio.v2", "--video")  # the demo extra

    imageio.mimsave(path, frames, fps=fps, macro_block_size=16)


def evaluate_torchrl(args: argparse.Namespace, ckpt: dict[str, Any]) -> dict[str, float]:
    """The same evaluation on the TorchRL side: ``evaluation.make_eval_env`` + ``evaluate_policy``.

    Same sub-env seeds (episode ``k``: ``seed + k``), same observations, same deterministic
    actions from the same network at the same batch size: the averages equal the gym backend's.
    """
    import math

    import torch

    from evaluation import evaluate_policy, make_eval_env
    from ppo_checkpoint import policy_from_checkpoint

    env_kwargs: dict[str, Any] = {"obs_mode": args.obs_mode, "control_mode": args.control_mode}
    if args.max_episode_steps is not None:
        env_kwargs["max_episode_steps"] = args.max_episode_steps
        limit = args.max_episode_steps
    else:
        import mani_skill.envs  # noqa: F401  (registers the tasks)

        limit = gym.spec(args.env_id).max_episode_steps
        if limit is None:
            raise SystemExit(f"{args.env_id} has no registered time limit: pass --max-episode-steps")
    # ActionRepeat(r) ends an episode of `limit` sim steps after ceil(limit / r) agent steps.
    max_steps = math.ceil(limit / ckpt["repeat"])
    env = make_eval_env(args.env_id, args.num_envs, torch.device("cpu"), ckpt["repeat"], **env_kwargs)
    try:
        policy = policy_from_checkpoint(ckpt, env, args.control_mode)
        return evaluate_policy(env, policy, args.episodes, args.seed, max_steps)
    finally:
        env.close()


def _format(n: int, rec: dict[str, Any]) -> str:
    where = f"env {rec['env']}" + (f", seed {rec['seed']}" if "seed" in rec else "")
    parts = [f"episode {n:3d} ({where})"]
    for key in ("success_once", "success_at_end", "fail_once", "fail_at_end"):
        if key in rec:
            parts.append(f"{key}={rec[key]}")
    parts.append(f"return={rec['return']:.4f}")
    parts.append(f"episode_len={rec['episode_len']}")
    return "  ".join(parts)


def print_averages(episodes: list[dict[str, Any]]) -> None:
    """Averages over all episodes, one ``avg <metric>`` line each."""
    print(f"episodes: {len(episodes)}")
    for key in METRICS:
        vals = [float(e[key]) for e in episodes if key in e]
        if vals:
            print(f"avg {key}: {np.mean(vals):.4f}")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument(
        "--env-id",
        default=None,
        help="default: the checkpoint's task, else PickCube-v1; with --checkpoint, must be its task",
    )
    p.add_argument("--num-envs", type=int, default=2, help="AsyncVectorEnv sub-envs (processes)")
    p.add_argument("--episodes", type=int, default=4, help="episodes to evaluate in all")
    p.add_argument("--seed", type=int, default=0, help="episode k is seeded --seed + k")
    p.add_argument("--policy", choices=("random", "zero"), default="random", help="without --checkpoint")
    p.add_argument(
        "--checkpoint",
        default=None,
        metavar="PATH",
        help="evaluate the ppo_checkpoint.pt of examples/ppo_torchrl.py, the sac_checkpoint.pt of "
        "examples/sac_torchrl.py or the policy.pt of examples/trainers/train.py (the file, or its folder)",
    )
    p.add_argument("--control-mode", default=None, help="default: the checkpoint's, else the task's")
    p.add_argument(
        "--backend",
        choices=("gym", "torchrl"),
        default="gym",
        help="gym: AsyncVectorEnv of CPUGymWrapper; torchrl: ppo_torchrl's make_eval_env + "
        "evaluate_policy (averages only; needs --checkpoint)",
    )
    p.add_argument("--video", default=None, metavar="PATH", help="write an mp4 of the first episodes (gym backend)")
    p.add_argument("--video-episodes", type=int, default=2, help="episodes in the --video")
    p.add_argument("--max-episode-steps", type=int, default=None, help="default: the task's time limit")
    p.add_argument("--obs-mode", default="state", help="ManiSkill observation mode (checkpoints: state)")
    args = p.parse_args(argv)
    for name in ("num_envs", "episodes"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.max_episode_steps is not None and args.max_episode_steps < 1:
        p.error(f"--max-episode-steps must be >= 1, got {args.max_episode_steps}")
    if args.video_episodes < 1:
        p.error(f"--video-episodes must be >= 1, got {args.video_episodes}")
    if args.checkpoint is None:
        if args.backend == "torchrl":
            p.error("--backend torchrl evaluates a checkpoint: pass --checkpoint PATH")
        if args.video is not None:
            p.error("--video records a checkpoint's policy: pass --checkpoint PATH")
        if args.env_id is None:
            args.env_id = "PickCube-v1"
    elif args.backend == "torchrl" and args.video is not None:
        p.error("--video is recorded by the gym backend: drop --backend torchrl")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    episodes: list[dict[str, Any]] = []  # the finished episodes, also after Ctrl-C / SIGTERM
    with stopping.interruptible():  # SIGTERM as Ctrl-C: the averages so far are printed, then exit 143 (130)
        try:
            return _main(args, episodes)
        except KeyboardInterrupt as err:
            stopped = err
    if args.backend == "torchrl":  # evaluate_policy gives its averages at the end only
        print(f"{stopping.said(stopped)}: evaluation stopped before its averages (--backend torchrl)")
        return stopping.exit_status(stopped)
    print(f"{stopping.said(stopped)} after {len(episodes)} of {args.episodes} episodes: the averages so far")
    print_averages(episodes)
    return stopping.exit_status(stopped)


def _main(args: argparse.Namespace, episodes: list[dict[str, Any]]) -> int:
    t0 = time.perf_counter()
    if args.checkpoint is None:
        evaluate(args, episodes)
    else:
        import torch

        from ppo_checkpoint import CheckpointError, load_checkpoint

        torch.set_num_threads(1)  # a small MLP: more threads only compete with the sim workers
        try:
            ckpt = load_checkpoint(args.checkpoint, args.env_id)
            args.env_id = ckpt["env_id"]
            if args.control_mode is None:
                args.control_mode = ckpt["control_mode"]
            print(
                f"checkpoint {ckpt['path']}: {ckpt['env_id']}, control mode {args.control_mode}, "
                f"repeat {ckpt['repeat']}, {ckpt.get('frames', '?')} frames; backend {args.backend}",
                flush=True,
            )
            if args.backend == "torchrl":
                res = evaluate_torchrl(args, ckpt)
                print(f"episodes: {int(res['episodes'])}")
                for key in METRICS:
                    if key in res:
                        print(f"avg {key}: {res[key]:.4f}")
                print(f"wall time: {time.perf_counter() - t0:.1f} s")
                return 0
            evaluate_checkpoint(args, ckpt, episodes)
        except CheckpointError as exc:
            print(f"evaluate_gym.py: error: {exc}", file=sys.stderr)
            return 2
    print_averages(episodes)
    print(f"wall time: {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":  # forkserver workers re-import this file
    # The forkserver imports ManiSkill once: each worker it forks starts without importing it again.
    multiprocessing.set_forkserver_preload(["__main__", "mani_skill.envs", "maniskill_torchrl.wrappers"])
    sys.exit(main())
