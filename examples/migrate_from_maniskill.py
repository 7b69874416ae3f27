"""Migrating gym code to maniskill_torchrl is a one-line import change.

Before::

    from mani_skill.utils.wrappers.action_repeat import ActionRepeatWrapper
    from mani_skill.utils.wrappers.gymnasium import CPUGymWrapper

After::

    from maniskill_torchrl.wrappers.action_repeat import ActionRepeatWrapper
    from maniskill_torchrl.wrappers.gymnasium import CPUGymWrapper

This script runs the same seeded loop (``gym.make`` -> ``ActionRepeatWrapper``
-> ``CPUGymWrapper(record_metrics=True)``, seeded resets, seeded random
actions) once with ManiSkill's wrappers and once with this library's, prints
the two traces side by side and says whether they are identical: every
observation, reward, flag and info entry (``info["episode"]`` metrics
included), value for value and type for type. Exit code 0 if identical, 1 if not.

Ctrl-C and SIGTERM stop it: it says how far it got (which run, at which step), compares the records
both runs have so far, closes the env and exits 130 (SIGINT) or 143 (SIGTERM), without a traceback.

Usage::

    python examples/migrate_from_maniskill.py --env-id PickCube-v1 --steps 30 --repeat 2
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from types import ModuleType
from typing import Any

import gymnasium as gym
import mani_skill.envs  # noqa: F401  (registers the tasks)
import numpy as np

import stopping

# The two modules compared. (`import mani_skill.utils.wrappers as m` would resolve the
# attribute chain, and `mani_skill.utils` is shadowed there by `mani_skill.envs.utils`.)
maniskill_wrappers = importlib.import_module("mani_skill.utils.wrappers")
torchrl_wrappers = importlib.import_module("maniskill_torchrl.wrappers")
LEFT, RIGHT = "mani_skill.utils.wrappers", "maniskill_torchrl.wrappers"

warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")


def run(
    wrappers: ModuleType, args: argparse.Namespace, trace: list[dict[str, Any]] | None = None
) -> list[dict[str, Any]]:
    """The seeded loop, with ``ActionRepeatWrapper`` / ``CPUGymWrapper`` taken from ``wrappers``.

    Every reset is seeded (``seed + episode``): an unseeded reset of a second env
    in the same process would not reproduce the first one's. The records are appended to
    ``trace`` (a new list by default) as they come: after a ``KeyboardInterrupt`` it holds those so far.
    """
    trace = [] if trace is None else trace
    env = gym.make(
        args.env_id,
        num_envs=1,
        obs_mode=args.obs_mode,
        max_episode_steps=args.max_episode_steps,
        sim_backend="physx_cpu",
    )
    if args.repeat > 1:
        env = wrappers.ActionRepeatWrapper(env, repeat=args.repeat)
    try:
        _loop(
            wrappers.CPUGymWrapper(env, ignore_terminations=args.ignore_terminations, record_metrics=True), args, trace
        )
    finally:
        env.close()
    return trace


def _loop(env: gym.Env, args: argparse.Namespace, trace: list[dict[str, Any]]) -> None:
    rng = np.random.default_rng(args.seed)
    space = env.action_space
    episode = 0
    obs, info = env.reset(seed=args.seed)
    trace.append({"step": 0, "kind": "reset", "obs": obs, "info": info})
    for t in range(1, args.steps + 1):
        action = rng.uniform(space.low, space.high).astype(space.dtype)
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append(
            {
                "step": t,
                "kind": "step",
                "obs": obs,
                "reward": reward,
                "terminated": terminated,
                "truncated": truncated,
                "info": info,
            }
        )
        if terminated or truncated:
            episode += 1
            obs, info = env.reset(seed=args.seed + episode)
            trace.append({"step": t, "kind": "reset", "obs": obs, "info": info})


def _typename(x: Any) -> str:
    t = type(x)
    return f"{t.__module__}.{t.__qualname__}"  # python bool vs numpy.bool: both are named "bool"


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    """Where ``a`` and ``b`` differ in value, dtype, shape or python type (empty if identical)."""
    if type(a) is not type(b):
        return [f"{path}: type {_typename(a)} vs {_typename(b)}"]
    if isinstance(a, dict):
        out = [f"{path}/{k}: missing on one side" for k in sorted(set(a) ^ set(b), key=str)]
        for k in a.keys() & b.keys():
            out += differences(a[k], b[k], f"{path}/{k}")
        return out
    if isinstance(a, np.ndarray):
        if a.dtype != b.dtype or a.shape != b.shape:
            return [f"{path}: {a.dtype}{a.shape} vs {b.dtype}{b.shape}"]
        # Bit equality (NaNs in the same places count as equal).
        same = np.array_equal(a.view(np.uint8), b.view(np.uint8)) if a.dtype.kind in "fc" else np.array_equal(a, b)
        return [] if same else [f"{path}: values differ (max abs diff {np.max(np.abs(a - b))})"]
    if isinstance(a, (float, np.floating)):
        return [] if np.asarray(a).tobytes() == np.asarray(b).tobytes() else [f"{path}: {a!r} vs {b!r}"]
    return [] if a == b else [f"{path}: {a!r} vs {b!r}"]


def _fmt(rec: dict[str, Any]) -> str:
    if rec["kind"] == "reset":
        return "reset"
    ep = rec["info"].get("episode", {})
    flags = ("T" if rec["terminated"] else "-") + ("t" if rec["truncated"] else "-")
    succ = rec["info"].get("success")
    return (
        f"r={rec['reward']:+.5f} {flags} succ={'?' if succ is None else int(succ)} "
        f"ret={ep.get('return', float('nan')):.5f} len={ep.get('episode_len', '?')}"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env-id", default="PickCube-v1")
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--repeat", type=int, default=2, help="ActionRepeatWrapper repeat (1: no ActionRepeatWrapper)")
    p.add_argument("--max-episode-steps", type=int, default=20, help="short, so that episodes end and reset")
    p.add_argument("--ignore-terminations", action="store_true")
    p.add_argument("--obs-mode", default="state")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.steps < 1 or args.repeat < 1 or args.max_episode_steps < 1:
        p.error("--steps, --repeat and --max-episode-steps must be >= 1")

    theirs: list[dict[str, Any]] = []
    ours: list[dict[str, Any]] = []
    runs = ((LEFT, maniskill_wrappers, theirs), (RIGHT, torchrl_wrappers, ours))
    where = "before run 1/2"
    with stopping.interruptible():  # SIGTERM as Ctrl-C: say how far it got, then exit 143 (130)
        try:
            for n, (name, wrappers, trace) in enumerate(runs):
                where = f"in run {n + 1}/2 ({name})"
                print(f"run {n + 1}/2: {name}, {args.steps} steps", flush=True)
                run(wrappers, args, trace)
            where = "while comparing"
            return 0 if compare(args, theirs, ours) else 1
        except KeyboardInterrupt as err:
            stopped = err
    last = {"theirs": theirs[-1]["step"] if theirs else 0, "ours": ours[-1]["step"] if ours else 0}
    print(
        f"{stopping.said(stopped)} {where}: {LEFT} reached step {last['theirs']} of {args.steps}, "
        f"{RIGHT} step {last['ours']}"
    )
    if ours:
        same = compare(args, theirs, ours, partial=True)
        print(f"identical so far: {same} ({min(len(theirs), len(ours))} records compared)")
    else:
        print("identical so far: not compared (the second run had not started)")
    return stopping.exit_status(stopped)


def compare(
    args: argparse.Namespace, theirs: list[dict[str, Any]], ours: list[dict[str, Any]], partial: bool = False
) -> bool:
    """Prints the two traces side by side (``partial``: only their differences, over the records both
    have) and says whether they are identical."""
    diffs: list[str] = []
    rows: list[str] = []
    width = max(len(_fmt(r)) for r in theirs + ours) + 2
    for a, b in zip(theirs, ours):
        d = differences(a, b, f"step {a['step']} {a['kind']}")
        diffs += d
        rows.append(f"{a['step']:>4}  {_fmt(a):<{width}}{_fmt(b):<{width}}{'yes' if not d else 'NO'}")
    if not partial:
        print(
            f"{args.env_id}: ActionRepeatWrapper(repeat={args.repeat}) -> CPUGymWrapper(record_metrics=True, "
            f"ignore_terminations={args.ignore_terminations}), {args.steps} seeded random steps"
        )
        print(f"{'step':>4}  {LEFT:<{width}}{RIGHT:<{width}}same")
        print("\n".join(rows))
        if len(theirs) != len(ours):
            diffs.append(f"trace lengths differ: {len(theirs)} vs {len(ours)}")
        print(
            f"identical: {not diffs} ({len(theirs)} records compared: observations, rewards, flags, infos, "
            "info['episode'])"
        )
    for d in diffs[:20]:
        print(f"  {d}")
    return not diffs


if __name__ == "__main__":
    sys.exit(main())
