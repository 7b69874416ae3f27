"""The ``maniskill-torchrl`` command line: parsing and dispatch.

``maniskill-torchrl demo`` shows the library end to end on the CPU (about a
minute on 2 idle cores): ``ManiSkillEnv(env_id, num_envs=N)`` on the CPU sim under
``ActionRepeat -> EpisodeMetrics``, fed to a :class:`torchrl.collectors.Collector`;
it prints a summary table and writes a per-episode return plot, a short rollout
video and a JSON summary.

- :mod:`~maniskill_torchrl.cli.parser`: the flags and their checks;
- :mod:`~maniskill_torchrl.cli.demo`: the collection;
- :mod:`~maniskill_torchrl.cli.report`: the summary, the plot and the video;
- :mod:`~maniskill_torchrl.cli.scripted_policy`: the demo's policies.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from maniskill_torchrl.cli.demo import run_demo
from maniskill_torchrl.cli.parser import UsageError, build_parser, validate_demo_args
from maniskill_torchrl.cli.scripted_policy import PickCubeScriptedPolicy

__all__ = ["main", "build_parser", "PickCubeScriptedPolicy"]

# subcommand -> (flag checks, runner)
_COMMANDS = {"demo": (validate_demo_args, run_demo)}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``maniskill-torchrl`` (and ``python -m maniskill_torchrl``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    validate, run = _COMMANDS[args.command]
    try:
        validate(args)
    except UsageError as err:
        args.subparser.error(str(err))  # exits with code 2
    os.environ.setdefault("PYTHONWARNINGS", "ignore::DeprecationWarning")  # reaches spawned workers
    return run(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
