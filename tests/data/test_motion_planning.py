"""maniskill_torchrl.data.motion_planning: paths from the caller and the interpreter, never the working
directory or a repository; nothing installed at run time (the planner's numpy 1 named when missing).
The planner itself runs in tests/examples (make test-examples) and in the README walk (make test-readme)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from maniskill_torchrl.cli import main
from maniskill_torchrl.data import motion_planning
from maniskill_torchrl.data.motion_planning import Numpy1Missing, demo_path, make_demos, numpy1_folder


def test_missing_numpy1_says_how_to_make_it(tmp_path, monkeypatch):
    empty = tmp_path / "numpy1"
    monkeypatch.setenv("MANISKILL_TORCHRL_NUMPY1", str(empty))
    with pytest.raises(Numpy1Missing) as error:
        numpy1_folder()
    message = str(error.value)
    assert f'-m pip install --target "{empty}" "numpy<2"' in message and "make setup" in message
    # before anything runs or is written
    with pytest.raises(Numpy1Missing):
        make_demos("PickCube-v1", 2, out_dir=tmp_path / "demos")
    assert not (tmp_path / "demos" / "PickCube-v1" / "motionplanning" / "planning.log").exists()


def test_the_default_numpy1_is_the_environments(monkeypatch):
    monkeypatch.delenv("MANISKILL_TORCHRL_NUMPY1", raising=False)
    try:
        folder = numpy1_folder()
    except Numpy1Missing as error:
        assert str(Path(sys.prefix) / "numpy1") in str(error)
    else:
        assert folder is None or folder == Path(sys.prefix) / "numpy1"


def test_made_demos_are_found_from_any_folder(tmp_path, monkeypatch):
    out = tmp_path / "demos"
    path = demo_path(out, "PickCube-v1")
    path.parent.mkdir(parents=True)
    path.touch()
    (path.parent / ".made-20").touch()
    monkeypatch.setattr(motion_planning, "_run", lambda *a, **k: pytest.fail("ran the planner"))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    lines: list[str] = []
    assert make_demos("PickCube-v1", 20, out_dir=out, log=lines.append) == path
    assert "made already" in lines[0]
    # a relative --out is the caller's folder, resolved once
    assert demo_path("demos", "PickCube-v1") == elsewhere / "demos" / path.relative_to(out)
    # more demos than were made: planned again (here: the missing numpy 1 stops it first)
    monkeypatch.setenv("MANISKILL_TORCHRL_NUMPY1", str(tmp_path / "none"))
    if int(__import__("numpy").__version__.split(".")[0]) >= 2:
        with pytest.raises(Numpy1Missing):
            make_demos("PickCube-v1", 21, out_dir=out)


def test_cli_make_demos_reports_the_missing_numpy1(tmp_path, monkeypatch, capsys):
    if int(__import__("numpy").__version__.split(".")[0]) < 2:
        pytest.skip("numpy 1 here: nothing is missing")
    monkeypatch.setenv("MANISKILL_TORCHRL_NUMPY1", str(tmp_path / "none"))
    assert main(["make-demos", "PickCube-v1", "2", "--out", str(tmp_path / "demos")]) == 1
    assert "pip install --target" in capsys.readouterr().err
