"""A TorchRL trainer run's CSV logs -> the learning-curve CSV committed under ``benchmarks/``.

A ``train.py`` run (``examples/trainers/train.py``, or TorchRL's sota ``train.py`` with the library's
``success_rate_evaluation`` hook and the ``csv`` logger) writes TorchRL's ``CSVLogger`` files,
``csv_logs/<exp>/scalars/<prefix>/<name>.csv``, one ``frames,value`` line per evaluation. The hook
(:class:`~maniskill_torchrl.trainer_hooks.SuccessRateEvaluation`) logs ``success_once``,
``success_at_end``, ``return`` and ``wall_s`` (seconds since the trainer was built). This script joins
them by frames into the committed format::

    eval,frames,wall_s,success_once,success_at_end,return[,seed]

one ``policy`` row per evaluation, what ``docs/_ext/curves.py`` (the curves page) draws. Several runs
(one per seed) go into one file with a ``seed`` column, read from each run's ``.hydra/config.yaml``
(``trainer.seed``) or given with ``--seeds``; the page draws their median and range.

Run::

    python scripts/trainer_csv.py outputs/sac_seed1 outputs/sac_seed2 outputs/sac_seed3 \\
        --out benchmarks/sac/pushcube_sactrainer.csv

Each argument is a Hydra run folder (holding ``csv_logs/``) or a ``csv_logs/<exp>`` folder.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

COLUMNS = ("success_once", "success_at_end", "return")


def _scalars(run: Path, prefix: str) -> Path:
    """The ``scalars/<prefix>`` folder of a run folder or of a ``csv_logs/<exp>`` folder."""
    if (run / "scalars" / prefix).is_dir():
        return run / "scalars" / prefix
    found = sorted(run.glob(f"csv_logs/*/scalars/{prefix}"))
    if len(found) != 1:
        where = [str(p) for p in found] or "none"
        raise SystemExit(f"{run}: expected one csv_logs/<exp>/scalars/{prefix} folder, found {where}")
    return found[0]


def _read(path: Path) -> dict[int, float]:
    """``{frames: value}`` of one CSVLogger scalar file (``frames,value`` lines, no header)."""
    values = {}
    for row in csv.reader(path.read_text().splitlines()):
        if row:
            values[int(float(row[0]))] = float(row[1])
    return values


def _seed(run: Path) -> int | None:
    """``trainer.seed`` of the run's Hydra config, where it has one."""
    config = run / ".hydra" / "config.yaml"
    if not config.is_file():
        return None
    from omegaconf import OmegaConf

    seed = OmegaConf.select(OmegaConf.load(config), "trainer.seed", default=None)
    return None if seed is None else int(seed)


def rows(run: Path, prefix: str = "eval") -> list[dict]:
    """One row per evaluation of ``run``, in the committed format (without the seed)."""
    folder = _scalars(run, prefix)
    series = {
        name: _read(folder / f"{name}.csv") for name in (*COLUMNS, "wall_s") if (folder / f"{name}.csv").is_file()
    }
    if "success_once" not in series:
        raise SystemExit(f"{folder}: no success_once.csv (was the success_rate_evaluation hook on?)")
    if "wall_s" not in series:
        raise SystemExit(
            f"{folder}: no wall_s.csv: the run predates the hook's wall_s (maniskill_torchrl's "
            "SuccessRateEvaluation logs it at each evaluation)"
        )
    out = []
    for frames in sorted(series["success_once"]):
        row = {"eval": "policy", "frames": frames, "wall_s": round(series["wall_s"][frames])}
        for name in COLUMNS:
            value = series.get(name, {}).get(frames)
            row[name] = "" if value is None else round(value, 4)
        out.append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="Hydra run folders (or csv_logs/<exp> folders), one per seed")
    p.add_argument("--out", type=Path, required=True, help="the CSV to write, e.g. benchmarks/sac/pushcube_x.csv")
    p.add_argument("--prefix", default="eval", help="the hook's prefix (default: %(default)s)")
    p.add_argument("--seeds", type=int, nargs="+", help="each run's seed (default: trainer.seed of its .hydra config)")
    args = p.parse_args(argv)
    if args.seeds is not None and len(args.seeds) != len(args.runs):
        p.error(f"--seeds: {len(args.seeds)} seeds for {len(args.runs)} runs")
    seeds = args.seeds or [_seed(run) for run in args.runs]
    with_seed = len(args.runs) > 1 or args.seeds is not None
    if with_seed and (None in seeds or len(set(seeds)) != len(seeds)):
        p.error(f"each run needs its own seed (found {seeds}): pass --seeds")
    header = ["eval", "frames", "wall_s", *COLUMNS] + (["seed"] if with_seed else [])
    table = []
    for run, seed in zip(args.runs, seeds):
        table += [{**row, "seed": seed} if with_seed else row for row in rows(run, args.prefix)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header, lineterminator="\n")
        writer.writeheader()
        writer.writerows(table)
    print(f"{args.out}: {len(table)} evaluations of {len(args.runs)} run(s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
