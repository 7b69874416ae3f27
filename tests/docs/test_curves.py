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
