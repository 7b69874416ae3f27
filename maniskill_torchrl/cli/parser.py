"""The ``maniskill-torchrl`` flags: the argument parser and the checks argparse cannot make flag by flag."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

__all__ = ["DEFAULT_ENV", "UsageError", "build_parser", "validate_demo_args"]

DEFAULT_ENV = "PickCube-v1"
# CPU rendering costs grow with the frame size (docs/guides/cpu_and_gpu.md):
# ManiSkill's 512 px default is much slower than this.
DEFAULT_VIDEO_SIZE = 256


def _positive_int(text: str) -> int:
    """argparse type: an int >= 1 (argparse prefixes the flag's name to the message)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def _seed(text: str) -> int:
    """argparse type: a seed in [0, 2**31)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 0 <= value < 2**31:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**31), got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``maniskill-torchrl`` argument parser (subcommand ``demo``)."""
    from maniskill_torchrl import __version__

    parser = argparse.ArgumentParser(
        prog="maniskill-torchrl",
        description="ManiSkill 3 as a TorchRL citizen. Run `maniskill-torchrl demo` for a tour.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    demo = sub.add_parser(
        "demo",
        help="collect frames from a batched CPU ManiSkill env; write a plot and a video",
        description=(
            "Collects frames with a TorchRL Collector from ManiSkillEnv(env_id, num_envs=--workers) "
            "on the CPU sim (one process per env) under ActionRepeat -> EpisodeMetrics, prints a "
            "summary and writes returns.png, rollout.mp4 and summary.json to --out."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    demo.add_argument("--env-id", default=DEFAULT_ENV, help="ManiSkill task id")
    demo.add_argument("--repeat", type=_positive_int, default=2, help="ActionRepeat: sim steps per agent step")
    demo.add_argument(
        "--frames",
        type=_positive_int,
        default=3000,
        help="agent steps to collect over all workers (rounded up to whole batches)",
    )
    demo.add_argument("--workers", type=_positive_int, default=2, help="CPU envs (num_envs), one process each")
    demo.add_argument("--out", type=Path, default=Path("outputs/demo"), help="output folder")
    demo.add_argument("--seed", type=_seed, default=0, help="seed of envs and policy")
    demo.add_argument(
        "--policy",
        choices=("auto", "scripted", "random"),
        default="auto",
        help="'scripted' is a pick-and-place controller for PickCube-v1; "
        "'auto' uses it there and random actions elsewhere",
    )
    demo.add_argument("--no-video", action="store_true", help="skip the rollout video")
    demo.add_argument("--video-steps", type=_positive_int, default=48, help="agent steps in the rollout video")
    demo.add_argument(
        "--video-size", type=_positive_int, default=DEFAULT_VIDEO_SIZE, help="video width and height in pixels"
    )
    demo.add_argument("--no-progress", action="store_true", help="no progress bar")
    demo.set_defaults(subparser=demo)

    demos = sub.add_parser(
        "make-demos",
        help="plan motion-planning demonstrations with ManiSkill's planner and convert them",
        description=(
            "Plans NUM_DEMOS successful ENV_ID demonstrations with ManiSkill's motion planner (CPU sim), "
            "converts them to --control-mode with state observations, and prints the converted .h5 "
            "(maniskill_torchrl.data.motion_planning). Kept when made already."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    demos.add_argument("env_id", help="ManiSkill task id with a motion-planning solution (e.g. PickCube-v1)")
    demos.add_argument("num_demos", type=_positive_int, help="successful demonstrations to plan")
    demos.add_argument("--control-mode", default="pd_ee_delta_pos", help="control mode of the converted file")
    demos.add_argument("--out", type=Path, default=Path("demos"), help="output folder (<out>/<env_id>/motionplanning)")
    demos.add_argument(
        "--processes", type=_positive_int, default=None, help="planner processes (default: the usable CPUs)"
    )
    demos.set_defaults(subparser=demos)
    return parser


class UsageError(ValueError):
    """A bad combination of flags: reported by argparse (usage line, exit code 2)."""


def validate_demo_args(args: argparse.Namespace) -> None:
    """Checks what argparse cannot check flag by flag; resolves ``--policy auto``.

    Raises:
        UsageError: with a message naming the flags involved.
    """
    if args.frames < args.workers:
        raise UsageError(f"--frames ({args.frames}) must be at least --workers ({args.workers})")
    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} exists and is not a folder")
    if args.policy == "auto":
        args.policy = "scripted" if args.env_id == DEFAULT_ENV else "random"
    if args.policy == "scripted" and args.env_id != DEFAULT_ENV:
        raise UsageError(
            f"--policy scripted is a controller for {DEFAULT_ENV} only (got --env-id {args.env_id}); "
            "use --policy random"
        )
    from maniskill_torchrl._internal.assets import registered_env_ids, similar_env_ids

    registered = registered_env_ids()
    if args.env_id not in registered:
        close = similar_env_ids(args.env_id)
        hint = f"; did you mean one of {close}?" if close else ""
        raise UsageError(
            f"unknown --env-id {args.env_id!r}{hint} (tasks that work offline include "
            "PickCube-v1, PushCube-v1, StackCube-v1, PullCube-v1)"
        )
    missing = _missing_assets(registered[args.env_id])
    if missing:
        # Checked here: in a worker ManiSkill would prompt on stdin for the download, then exit.
        raise UsageError(
            f"--env-id {args.env_id} needs assets that are not downloaded ({', '.join(missing[:5])}); "
            f"fetch them with `python -m mani_skill.utils.download_asset {args.env_id}` or pick another task"
        )


def _missing_assets(spec: Any) -> list[str]:
    """The asset ids a ManiSkill task needs and does not find on disk (as ``EnvSpec.make`` checks)."""
    from mani_skill.utils import assets

    missing = []
    for asset_id in getattr(spec, "asset_download_ids", None) or []:
        ids = (
            assets.expand_data_group_into_individual_data_source_ids(asset_id)
            if asset_id in assets.DATA_GROUPS
            else [asset_id]
        )
        missing += [i for i in ids if not assets.is_data_source_downloaded(i)]
    return missing
