"""The accelerator-machine check and kit (scripts/gpu_check.py, scripts/gpu_kit.py): the summary's
parsing of the stages' JUnit and sweep files, and the kit's split into carries. The machine itself is checked by
running them there (benchmarks/README.md, "GPU kit"); `make gpu-check` is their dry run here."""

from __future__ import annotations

import importlib.util
import json
import platform
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_junit_counts_failures_skip_reasons_and_slowest(tmp_path):
    (tmp_path / "suite.xml").write_text(
        '<testsuites><testsuite><testcase classname="a" name="ok" time="2.5"/>'
        '<testcase classname="a" name="bad" time="1"><failure message="boom"/></testcase>'
        '<testcase classname="b" name="err" time="0.5"><error message="setup"/></testcase>'
        '<testcase classname="b" name="s1" time="0"><skipped message="no CUDA"/></testcase>'
        '<testcase classname="b" name="s2" time="0"><skipped message="no CUDA"/></testcase></testsuite></testsuites>'
    )
    res = load("gpu_check").junit(tmp_path / "suite.xml")
    assert [res[k] for k in ("passed", "failed", "errors", "skipped")] == [1, 1, 1, 2]
    assert res["failed_tests"] == {"a::bad": "failure: boom", "b::err": "error: setup"}
    assert res["skip_reasons"] == {"no CUDA": 2}
    assert list(res["slowest_s"])[:2] == ["a::ok", "a::bad"]
    assert "unreadable" in load("gpu_check").junit(tmp_path / "missing.xml")["junit"]


def test_sweep_summary_ratios_scaling_and_runs_without_result(tmp_path):
    runs = [("gym N=1 r=2", 100, 1.0), ("gym N=8 r=2", 600, 1.0), ("batched:t1 N=1 r=2", 110, 1.0)]
    data = [{"name": n, "result": {"units": u, "wall_s": w, "startup_s": 9.0}} for n, u, w in runs]
    data.append({"name": "batched:t1 N=8 r=2", "result": {"skipped": "start-up past 40 s"}})
    (tmp_path / "sweep.json").write_text(json.dumps({"complete": True, "runs": data}))
    res = load("gpu_check").sweep_summary(tmp_path / "sweep.json")
    assert res["frames_per_s"] == {"gym": {1: 100.0, 8: 600.0}, "batched:t1": {1: 110.0}}
    assert res["ratio_to_gym"] == {"batched:t1": {1: 1.1}}
    assert res["scaling_vs_n_times_n1"] == {"gym": {8: 0.75}, "batched:t1": {}}
    assert res["not_measured"] == {"batched:t1": {8: "start-up past 40 s"}}


def test_kit_splits_wheels_into_the_fewest_parts_under_the_limit(tmp_path):
    wheels = []
    for name, size in (("a", 40), ("b", 30), ("c", 20), ("d", 5)):
        (path := tmp_path / f"{name}.whl").write_bytes(b"x" * size)
        wheels.append(path)
    parts = load("gpu_kit").assemble(wheels, deb_bytes=10, limit=60)
    assert len(parts) == 2 and sorted(p.name for part in parts for p in part) == ["a.whl", "b.whl", "c.whl", "d.whl"]
    assert all(sum(p.stat().st_size for p in part) + (10 if i == 0 else 0) <= 60 for i, part in enumerate(parts))


@pytest.mark.skipif(
    not (sys.platform == "linux" and platform.machine() == "x86_64"), reason="the kit's platforms are x86_64 Linux's"
)
def test_kit_download_asks_pip_for_real_platform_tags(tmp_path):
    """Every --platform of the kit's download is a platform tag that ``packaging.tags`` gives this
    x86_64 Linux machine (glibc >= 2.28; PEP 600 names and the legacy aliases): a misspelt one
    (``manylinux2_28_x86_64``, issue 44) is an unknown platform that no wheel has."""
    from packaging.tags import sys_tags

    known = {tag.platform for tag in sys_tags()}
    assert "manylinux2_28_x86_64" not in known  # the check can tell a misspelt tag
    command = load("gpu_kit").download_command(tmp_path, ["torchrl==0.14.1"])
    platforms = [command[i + 1] for i, arg in enumerate(command) if arg == "--platform"]
    assert platforms and set(platforms) <= known, set(platforms) - known
    assert "manylinux_2_28_x86_64" in platforms  # torchrl 0.14.1's cp312 wheels are 2_28
