"""The pictures of ``docs/curves.md`` (``docs/_ext/curves.py``): drawn from the CSVs in git into a
temporary folder, each a real PNG of some size, each shown on the page. Runs under ``make docs``."""

from __future__ import annotations

import importlib.util
import struct
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def curves():
    pytest.importorskip("matplotlib")
    spec = importlib.util.spec_from_file_location("curves", ROOT / "docs" / "_ext" / "curves.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def pngs(curves, tmp_path_factory) -> list[Path]:
    return curves.draw_all(tmp_path_factory.mktemp("curves"))


def test_every_picture_drawn(pngs):
    names = {p.name for p in pngs}
    assert names == {
        "ppo_pullcube.png",
        "ppo_pullcube_trainer.png",
        "ppo_pushcube_rgb.png",
        "sac_pushcube.png",
        "rlpd_pickcube.png",
        "bc.png",
        "collection_2cores.png",
        "collection_16cores.png",
        "collection_many_cores_emulated.png",
    }
    for png in pngs:
        data = png.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{png.name} is not a PNG"
        width, height = struct.unpack(">II", data[16:24])
        assert width >= 600 and height >= 400, f"{png.name} is {width}x{height}"
        assert len(data) > 20_000, f"{png.name} is {len(data)} bytes: an empty figure?"


def test_page_shows_every_picture(curves, pngs):
    page = (ROOT / "docs" / "curves.md").read_text()
    for png in pngs:
        assert f"{curves.OUT}/{png.name}" in page, f"docs/curves.md does not show {png.name}"


def test_collection_csvs_read(curves):
    # the copied tables: gym and the README pipeline at every N, frames/s a number
    for name, ns in (("sweep_2cores.csv", {1, 2}), ("sweep_16cores_h200.csv", {1, 8, 15})):
        rows = curves.read_csv(ROOT / "benchmarks" / "collection" / name)
        for pipeline in ("gym", "batched:t1,rp,dev,em"):
            assert {r["n"] for r in rows if r["pipeline"] == pipeline} == ns, (name, pipeline)
        assert all(isinstance(r["frames_per_s"], int) for r in rows)


def test_many_cores_csv_reads(curves):
    # the emulator's sweep: gym, the README pipeline and the asynchronous path at every N, with the ideal
    rows = curves.read_csv(ROOT / "benchmarks" / "collection" / "many_cores_emulated.csv")
    ns = {r["n"] for r in rows}
    assert {1, 15, 64} <= ns
    for pipeline in ("gym", "readme", "async"):
        assert {r["n"] for r in rows if r["pipeline"] == pipeline} == ns, pipeline
    for r in rows:
        assert isinstance(r["frames_per_s"], int) and r["ideal_frames_per_s"] > r["frames_per_s"] > 0
        assert abs(r["share"] - r["frames_per_s"] / r["ideal_frames_per_s"]) < 0.01 * r["share"] + 0.001


def test_collection_legends_in_words_explained_by_the_captions(curves):
    """Every pipeline of the collection figures has a legend name in words (not its benchmark id), and the
    page's captions give both the name and the id."""
    page = (ROOT / "docs" / "curves.md").read_text()
    captions = " ".join(page.split())
    for name in ("sweep_2cores.csv", "sweep_16cores_h200.csv", "many_cores_emulated.csv"):
        for pipeline in {r["pipeline"] for r in curves.read_csv(ROOT / "benchmarks" / "collection" / name)}:
            label = curves.LABELS[pipeline]
            assert ":" not in label.split("(")[0], label
            assert f"`{pipeline}`" in captions or f"`{pipeline}:" in captions, f"no caption gives {pipeline}"
            words = label.split(" (")[0].split(",")[0]
            assert words in captions, f"no caption explains {label!r}"


def _log(tmp_path, records) -> Path:
    import json

    path = tmp_path / "metrics.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    return path


_KEYS = ("eval", "frames", "wall_s", "episodes", "success_once", "success_at_end", "return")
RUN = [
    dict(zip(_KEYS, values))
    for values in (
        ("random", 0, 5.0, 4, 0.0, 0.0, 1.0),
        ("policy", 100, 60.0, 4, 0.5, 0.25, 3.0),
        ("policy", 200, 120.0, 4, 1.0, 0.75, 5.0),
    )
]


def test_plot_ppo_target_only_when_given_and_titled_with_the_task(tmp_path):
    """``benchmarks.plot_ppo``: a target line only with ``--target``, the title "PPO on <task>", one legend
    below the axes (none on them), the random policy dashed, success from 0."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from benchmarks import plot_ppo

    log = _log(tmp_path, RUN)
    for argv, target, title in (
        ([], None, f"PPO ({log})"),
        (["--task", "PullCube-v1", "--target", "0.7"], 0.7, "PPO on PullCube-v1"),
    ):
        plot_ppo.main([str(log), "--out", str(tmp_path / "ppo.png"), *argv])
        fig = plt.gcf()
        ax = fig.axes[0]
        levels = {line.get_ydata()[0]: line.get_linestyle() for line in ax.lines if len(set(line.get_ydata())) == 1}
        assert levels.get(0.0) == "--"  # the random policy, dashed
        assert (target in levels) is (target is not None) and levels.get(target, ":") == ":"
        assert 0.8 not in levels
        assert fig._suptitle.get_text() == title
        assert len(fig.legends) == 1 and all(a.get_legend() is None for a in fig.axes)
        assert ax.get_ylim()[0] == 0
        plt.close("all")
    with_task = _log(tmp_path, [{**r, "env_id": "PushCube-v1"} for r in RUN])
    plot_ppo.main([str(with_task), "--out", str(tmp_path / "ppo.png")])
    assert plt.gcf()._suptitle.get_text() == "PPO on PushCube-v1"
    plt.close("all")


def test_plot_runs_markers_only_from_zero(tmp_path):
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from benchmarks import plot_runs

    log = _log(tmp_path, RUN)
    plot_runs.main([f"a={log}", "--out", str(tmp_path / "runs.png"), "--markers-only"])
    fig = plt.gcf()
    measured = [line for ax in fig.axes for line in ax.lines if len(set(line.get_ydata())) > 1]
    assert measured and all(line.get_linestyle() == "None" and line.get_marker() for line in measured)
    assert all(ax.get_ylim()[0] == 0 for ax in fig.axes)
    assert len(fig.legends) == 1 and all(a.get_legend() is None for a in fig.axes)
    plt.close("all")
