"""Records the real task that ``benchmarks/replay_task.py`` replays: PickCube-v1, ``obs_mode="state"``,
CPU sim, ``max_episode_steps=50``, episodes reset with seeds 0..``--episodes``-1 and stepped 50 times
with seeded uniform random actions (``torch.Generator().manual_seed(seed)``, float32 in the action
space's bounds), each held for 2 steps as an agent at action repeat 2 holds it (so the replay is
the real episode at repeat 1 and at repeat 2 alike), every call under :func:`torch.inference_mode`
(as the library's workers step).

It saves each step's outputs (observation, reward, the task's infos) once, and the wall time of
each ``BaseEnv.step`` and ``BaseEnv.reset`` (the task itself, without gym's wrappers) over
``--passes`` passes over all the episodes (the outputs of every pass must be equal, bit for bit), to
``benchmarks/replay/pickcube_state.npz`` with the machine, date and command in its ``meta``.
The replay scales the times to a target machine's mean, so this machine's speed does not matter;
its noise does: run it on a quiet machine (it waits for one, ``--max-busy``).

    python -m benchmarks.record_replay [--episodes 20] [--passes 3] [--out benchmarks/replay/pickcube_state.npz]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.machine import machine_line, wait_for_quiet

ENV_ID = "PickCube-v1"
OUT = Path(__file__).resolve().parent / "replay" / "pickcube_state.npz"
EPISODE = 50
HOLD = 2  # the action repeat benchmarked: each drawn action is held for 2 sim steps
MAKE_KWARGS = {"obs_mode": "state", "max_episode_steps": EPISODE, "sim_backend": "physx_cpu", "render_backend": "none"}


def episode_actions(space, seed: int, steps: int = EPISODE, hold: int = HOLD) -> np.ndarray:
    """The ``[steps, *action]`` float32 actions of the episode seeded ``seed``, each held for ``hold``
    steps (an agent at action repeat ``hold``)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    low = torch.as_tensor(space.low, dtype=torch.float32)
    high = torch.as_tensor(space.high, dtype=torch.float32)
    drawn = low + (high - low) * torch.rand((-(-steps // hold), *space.shape), generator=g)
    return drawn.repeat_interleave(hold, dim=0)[:steps].numpy()


class _Timed:
    """Wall time of each call of ``base.<name>`` (an instance attribute over the method: gym's
    wrappers call it through ``self.env.<name>``)."""

    def __init__(self, base, name: str) -> None:
        self.times: list[float] = []
        self._call = getattr(base, name)
        setattr(base, name, self)

    def __call__(self, *args, **kwargs):
        t0 = time.perf_counter()
        out = self._call(*args, **kwargs)
        self.times.append(time.perf_counter() - t0)
        return out


def _np(x):
    return x.detach().cpu().numpy().copy()


def record(episodes: int, passes: int) -> dict:
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401
    import torch

    torch.set_num_threads(1)
    with torch.inference_mode():
        env = gym.make(ENV_ID, num_envs=1, **MAKE_KWARGS)
        base = env.unwrapped
        step_t, reset_t = _Timed(base, "step"), _Timed(base, "reset")
        # untimed warm-up: one episode (a seeded episode does not depend on what ran before it)
        env.reset(seed=10_000)
        for a in episode_actions(base.single_action_space, 10_000):
            env.step(torch.from_numpy(a)[None])
        step_t.times.clear()
        reset_t.times.clear()
        runs = []
        for _ in range(passes):
            run = {"reset_obs": [], "reset_info": [], "obs": [], "reward": [], "info": [], "terminated": []}
            run["truncated"] = []
            for seed in range(episodes):
                obs, info = env.reset(seed=seed)
                run["reset_obs"].append(_np(obs[0]))
                run["reset_info"].append({k: _np(v[0]) for k, v in info.items() if isinstance(v, torch.Tensor)})
                ep = {k: [] for k in ("obs", "reward", "info", "terminated", "truncated")}
                for a in episode_actions(base.single_action_space, seed):
                    obs, reward, terminated, truncated, info = env.step(torch.from_numpy(a)[None])
                    ep["obs"].append(_np(obs[0]))
                    ep["reward"].append(_np(reward[0]))
                    ep["terminated"].append(_np(terminated[0]))
                    ep["truncated"].append(_np(truncated[0]))
                    ep["info"].append({k: _np(v[0]) for k, v in info.items()})
                for k, v in ep.items():
                    run[k].append(v)
            runs.append(run)
    step_s = np.asarray(step_t.times).reshape(passes, episodes, EPISODE)
    reset_s = np.asarray(reset_t.times).reshape(passes, episodes)
    first = runs[0]
    for other in runs[1:]:  # every pass the same, bit for bit
        for key in ("reset_obs", "obs", "reward", "terminated", "truncated"):
            if not np.array_equal(np.asarray(first[key]), np.asarray(other[key])):
                raise RuntimeError(f"{ENV_ID}: two passes over the same seeded episodes differ in {key!r}")
    info_keys = [k for k in first["info"][0][0] if k != "elapsed_steps"]
    out = {
        "seeds": np.arange(episodes, dtype=np.int64),
        "actions": np.stack([episode_actions(base.single_action_space, s) for s in range(episodes)]),
        "reset_obs": np.stack(first["reset_obs"]),
        "obs": np.asarray(first["obs"]),
        "reward": np.asarray(first["reward"]),
        "terminated": np.asarray(first["terminated"]),
        "truncated": np.asarray(first["truncated"]),
        "step_s": step_s,
        "reset_s": reset_s,
        "action_low": base.single_action_space.low,
        "action_high": base.single_action_space.high,
    }
    for key in info_keys:
        out["info_" + key] = np.asarray([[i[key] for i in ep] for ep in first["info"]])
        out["reset_info_" + key] = np.asarray([i[key] for i in first["reset_info"]])
    space = base.single_observation_space
    meta = {
        "env_id": ENV_ID,
        "make_kwargs": MAKE_KWARGS,
        "obs_mode": base.obs_mode,
        "reward_mode": base.reward_mode,
        "control_mode": base.control_mode,
        "sim_freq": base.sim_freq,
        "control_freq": base.control_freq,
        "single_observation_space": {"shape": list(space.shape), "dtype": str(space.dtype)},
        "info_keys": info_keys,
        "episodes": episodes,
        "passes": passes,
        "actions": "torch.Generator().manual_seed(seed): low + (high - low) * torch.rand((25, *shape)), float32, "
        "each held for 2 steps",
        "hold": HOLD,
        "timing": "wall time of each BaseEnv.step / BaseEnv.reset under torch.inference_mode, one torch thread",
    }
    env.close()
    return out, meta


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=20, help="seeded episodes, seeds 0..N-1 (default 20)")
    p.add_argument("--passes", type=int, default=3, help="timed passes over them (default 3)")
    p.add_argument("--out", default=str(OUT))
    p.add_argument("--max-busy", type=float, default=0.3, help="wait until other processes use fewer cores")
    p.add_argument("--max-wait", type=float, default=120.0, help="seconds, at most, to wait for that")
    args = p.parse_args(argv)
    busy = wait_for_quiet(args.max_busy, args.max_wait, verbose=True)
    t0 = time.perf_counter()
    arrays, meta = record(args.episodes, args.passes)
    meta.update(
        machine=machine_line(),
        date=dt.date.today().isoformat(),
        command="python -m benchmarks.record_replay " + shlex.join(argv if argv is not None else sys.argv[1:]),
        busy_cores_before=None if busy is None else round(busy, 2),
        recorded_s=round(time.perf_counter() - t0, 1),
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, meta=np.asarray(json.dumps(meta)), **arrays)
    steps = arrays["step_s"]
    print(
        f"wrote {out} ({out.stat().st_size / 1024:.0f} KB): {args.episodes} episodes x {EPISODE} steps, "
        f"{args.passes} passes; step {1e3 * steps.mean():.3f} ms mean, {1e3 * np.median(steps):.3f} median, "
        f"cv {steps.std() / steps.mean():.2f}; reset {1e3 * arrays['reset_s'].mean():.3f} ms mean "
        f"(busy before: {meta['busy_cores_before']})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
