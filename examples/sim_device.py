"""``--device`` and ``--sim-backend``: where the learner runs, and which ManiSkill simulator feeds it.

Shared by ``ppo_torchrl.py``, ``sac_torchrl.py``, ``bc_torchrl.py`` and ``evaluation.make_eval_env``,
so that the choice is written once:

- ``--device``: the learner's device (policy, replay buffer, every batch). The env is made with
  ``device=<--device>``: its outputs (observations, pictures, rewards, flags, infos) arrive there and
  it takes its actions there, whichever simulator steps.
- ``--sim-backend auto`` (default): the GPU sim when ``--device`` is cuda, else the CPU sim; that is
  what ``--device`` alone meant before this flag, so existing commands keep their meaning. Under
  ``--smoke`` (a CPU configuration) ``auto`` is the CPU sim.
- ``--sim-backend cpu``: ManiSkill's CPU sim whatever the device. With ``--device cuda`` it steps on
  the CPU (one process per env) and a GPU learner reads its batches on the GPU: the set-up of a
  workstation with one NVIDIA GPU and a task that the GPU sim does not serve, or serves slowly.
- ``--sim-backend gpu``: the GPU sim; it needs ``--device cuda`` (its state lives on the GPU).

Usage in an example::

    add_arguments(parser)
    args = parser.parse_args(argv)
    check_arguments(parser, args)           # args.device: "cpu" / "cuda:0"; args.sim_backend: "cpu" / "gpu"
    make_pipeline(env_id, num_envs=n, **env_kwargs(args))
"""

from __future__ import annotations

import argparse
from typing import Any

import torch

SIM_BACKENDS = ("auto", "cpu", "gpu")


def resolve(sim_backend: str, device: str | torch.device, smoke: bool = False) -> tuple[str, torch.device]:
    """``(--sim-backend, --device)`` -> ``("cpu" | "gpu", the learner's torch.device)``.

    ``auto``: ``"gpu"`` for a cuda device (``"cpu"`` under ``smoke``), else ``"cpu"``. Raises
    ``ValueError`` for the GPU sim with a CPU learner (and for ``smoke`` with the GPU sim).
    Reads no CUDA state: ``"cuda"`` stays index-less here (:func:`check_arguments` fills the index)."""
    if sim_backend not in SIM_BACKENDS:
        raise ValueError(f"--sim-backend must be one of {', '.join(SIM_BACKENDS)}, got {sim_backend!r}")
    device = torch.device(device)
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"--device must be cpu or cuda[:index], got {str(device)!r}")
    cuda = device.type == "cuda"
    if sim_backend == "auto":
        sim_backend = "gpu" if cuda and not smoke else "cpu"
    if sim_backend == "gpu" and not cuda:
        raise ValueError(
            "--sim-backend gpu needs --device cuda: the GPU sim keeps its state and outputs on the GPU. "
            "For a CPU learner use --sim-backend cpu (or auto)."
        )
    if sim_backend == "gpu" and smoke:
        raise ValueError("--smoke is a CPU-sim configuration: drop --sim-backend gpu (--device cuda may stay)")
    return sim_backend, device


def add_arguments(p: argparse.ArgumentParser, cpu_default: bool = False) -> None:
    """Adds ``--device`` (default: cuda if available, or the CPU with ``cpu_default``) and ``--sim-backend``."""
    default_device = "cpu" if cpu_default else "cuda if available (cpu with --smoke)"
    p.add_argument(
        "--device",
        default=None,
        help=f"the learner's device (policy, replay buffer, batches; the env's outputs arrive there): cuda or cpu; "
        f"default: {default_device}",
    )
    p.add_argument(
        "--sim-backend",
        choices=SIM_BACKENDS,
        default="auto",
        help="ManiSkill's simulator. auto: the GPU sim when --device is cuda (the CPU sim under --smoke), else the "
        "CPU sim; cpu: the CPU sim whatever --device (with --device cuda: a GPU learner fed by the CPU sim); "
        "gpu: the GPU sim (needs --device cuda)",
    )


def check_arguments(
    p: argparse.ArgumentParser, args: argparse.Namespace, cpu_default: bool = False, smoke: bool = False
) -> None:
    """Fills in the default device and resolves the pair in place (``args.device``: ``"cpu"`` or
    ``"cuda:<index>"``, ``args.sim_backend``: ``"cpu"`` or ``"gpu"``); refuses, through ``p.error``
    (exit 2), a pair that cannot run. An explicit ``--sim-backend cpu`` on a machine with CUDA keeps
    the default learner on the GPU; under ``smoke`` (and with ``cpu_default``) the default device is
    the CPU."""
    # The default run is a GPU run: on a machine without CUDA it becomes a CPU-sim run, said by cpu_fallback_note.
    args.cpu_fallback = args.device is None and args.sim_backend == "auto" and not (cpu_default or smoke)
    args.cpu_fallback = args.cpu_fallback and not torch.cuda.is_available()
    if args.device is None:
        args.device = "cuda" if torch.cuda.is_available() and not (cpu_default or smoke) else "cpu"
    try:
        sim_backend, device = resolve(args.sim_backend, args.device, smoke)
    except ValueError as e:
        p.error(str(e))
    if device.type == "cuda":
        if not torch.cuda.is_available():
            p.error(f"--device {args.device} needs a CUDA GPU (torch.cuda.is_available() is False); use --device cpu")
        if device.index is None:
            # ManiSkill reports "cuda:0": an index-less "cuda" would look like another device to TorchRL.
            device = torch.device("cuda", torch.cuda.current_device())
    args.device, args.sim_backend = str(device), sim_backend


def env_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``ManiSkillEnv`` keyword arguments of the resolved pair: ``sim_backend`` and ``device``."""
    return {"sim_backend": args.sim_backend, "device": torch.device(args.device)}


def cpu_fallback_note(args: argparse.Namespace, what: str) -> None:
    """Says, once the run's sizes are known, that the default GPU run became a CPU-sim run (no CUDA here)."""
    if getattr(args, "cpu_fallback", False):
        print(
            f"No CUDA device here: the default GPU run becomes {what} on the CPU sim (long on a few cores). "
            "--smoke checks the whole loop in about a minute; --device cpu chooses this run without this note.",
            flush=True,
        )
