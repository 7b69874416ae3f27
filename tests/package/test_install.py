"""Installation: ManiSkill is the user's choice (release extra or nightly), and without any the
library says how to install it; the package ships its ``py.typed`` marker."""

from __future__ import annotations

import subprocess
import sys
from importlib import resources
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# Runs first in the child: a meta path finder that hides ManiSkill (and SAPIEN) as if not installed.
HIDE_MANISKILL = """
import sys

class _HideManiSkill:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("mani_skill", "sapien"):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, _HideManiSkill())
"""


@pytest.mark.parametrize(
    "statement",
    [
        "import maniskill_torchrl",
        "from maniskill_torchrl import ManiSkillEnv",
        "from maniskill_torchrl.transforms import ActionRepeat",
        "from maniskill_torchrl.wrappers import CPUGymWrapper",
    ],
)
def test_import_without_maniskill_says_how_to_install(statement):
    child = subprocess.run(
        [sys.executable, "-c", HIDE_MANISKILL + statement],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert child.returncode == 1, child.stderr
    last = child.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: maniskill_torchrl needs ManiSkill 3"), child.stderr
    assert 'pip install "maniskill-torchrl[maniskill]"' in last
    assert "pip install mani-skill-nightly" in last
    assert "During handling of the above exception" not in child.stderr  # one error, not a chain


@pytest.mark.slow
def test_import_with_maniskill_succeeds():
    child = subprocess.run(
        [sys.executable, "-c", "import maniskill_torchrl.wrappers, maniskill_torchrl as m; print(m.__version__)"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert child.returncode == 0, child.stderr


def test_py_typed_marker():
    assert resources.files("maniskill_torchrl").joinpath("py.typed").is_file()
