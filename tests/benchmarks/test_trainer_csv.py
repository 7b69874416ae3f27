"""``scripts/trainer_csv.py``: a trainer run's CSV logs (TorchRL's ``CSVLogger``, ``csv_logs/<exp>/scalars/eval/``)
into the committed learning-curve CSV, several seeds in one file; ``benchmarks/plot_runs.py`` draws them as median
and range (issue 62)."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import pytest

from benchmarks import plot_runs

ROOT = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("trainer_csv", ROOT / "scripts" / "trainer_csv.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(folder: Path, seed: int, success: list[float], wall: list[float]) -> Path:
    """A Hydra run folder as train.py leaves it: its config and the hook's scalars."""
    scalars = folder / "csv_logs" / "sac_x" / "scalars" / "eval"
    scalars.mkdir(parents=True)
    (folder / ".hydra").mkdir()
    (folder / ".hydra" / "config.yaml").write_text(f"trainer:\n  seed: {seed}\n")
    frames = [20000, 40000]
    series = {"success_once": success, "success_at_end": success, "return": [1.5, 2.5], "wall_s": wall}
    for name, values in series.items():
        (scalars / f"{name}.csv").write_text("".join(f"{f},{v}\n" for f, v in zip(frames, values)))
    return folder


def test_runs_become_the_committed_format_with_seeds(tmp_path):
    runs = [
        _run(tmp_path / "a", 1, [0.2, 0.8], [100.4, 200.6]),
        _run(tmp_path / "b", 2, [0.4, 0.9], [110, 230]),
        _run(tmp_path / "c", 3, [0.0, 0.6], [90, 190]),
    ]
    out = tmp_path / "curve.csv"
    assert _script().main([*map(str, runs), "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.read_text().splitlines()))
    assert list(rows[0]) == ["eval", "frames", "wall_s", "success_once", "success_at_end", "return", "seed"]
    assert [(r["seed"], r["frames"], r["wall_s"], r["success_once"]) for r in rows[:2]] == [
        ("1", "20000", "100", "0.2"),
        ("1", "40000", "201", "0.8"),
    ]
    records = [{k: float(v) if k != "eval" else v for k, v in r.items()} for r in rows]
    med, lo, hi, n = plot_runs.seeds_median(records)
    assert n == 3 and [m["success_once"] for m in med] == [0.2, 0.8]
    assert [(a["success_once"], b["success_once"]) for a, b in zip(lo, hi)] == [(0.0, 0.4), (0.6, 0.9)]
    log = tmp_path / "curve.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    assert plot_runs.main([f"sac={log}", "--out", str(tmp_path / "curve.png")]) == 0


def test_one_run_without_seed_keeps_the_old_columns(tmp_path):
    run = _run(tmp_path / "a", 1, [0.2, 0.8], [100, 200])
    out = tmp_path / "one.csv"
    _script().main([str(run / "csv_logs" / "sac_x"), "--out", str(out)])
    assert out.read_text().splitlines()[0] == "eval,frames,wall_s,success_once,success_at_end,return"


def test_a_run_without_wall_time_names_the_hook(tmp_path):
    run = _run(tmp_path / "a", 1, [0.2, 0.8], [100, 200])
    (run / "csv_logs" / "sac_x" / "scalars" / "eval" / "wall_s.csv").unlink()
    with pytest.raises(SystemExit, match="no wall_s.csv"):
        _script().main([str(run), "--out", str(tmp_path / "x.csv")])
