"""Every optional dependency, missing, raises an ImportError that names the extra installing it
(`pip install "maniskill-torchrl[<extra>]"`), from the library and from the examples that need it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from maniskill_torchrl._internal.extras import EXTRAS, require

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.mark.parametrize("module", sorted(EXTRAS))
def test_require_names_the_extra(module, monkeypatch):
    monkeypatch.setitem(sys.modules, module, None)  # as if not installed
    with pytest.raises(ImportError) as error:
        require(module, "this feature")
    dist, extra = EXTRAS[module]
    assert f'pip install "maniskill-torchrl[{extra}]"' in str(error.value) and dist in str(error.value)
    assert error.value.name == module


def _blocked(module: str, code: str) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter where ``module`` cannot be imported."""
    prelude = f"import sys; sys.modules[{module!r}] = None\n"
    return subprocess.run(
        [sys.executable, "-c", prelude + code], capture_output=True, text=True, timeout=120, cwd=EXAMPLES
    )


@pytest.mark.parametrize(
    "module, code",
    [
        ("hydra", "import maniskill_torchrl.configs"),
        (
            "hydra",
            "import runpy; sys.argv = ['train.py']; runpy.run_path('trainers/train.py', run_name='__main__')",
        ),
    ],
    ids=["configs", "train.py"],
)
def test_missing_hydra_names_the_extra(module, code):
    proc = _blocked(module, code)
    assert proc.returncode != 0
    assert 'pip install "maniskill-torchrl[hydra]"' in proc.stderr, proc.stderr[-2000:]
    assert "ModuleNotFoundError" not in proc.stderr, proc.stderr[-2000:]
