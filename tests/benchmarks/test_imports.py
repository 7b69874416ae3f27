"""Every name the benchmarks import from the library exists (a benchmark imports inside ``main`` to start fast, so
a renamed private, e.g. the adapter's ``_leaf``, breaks it only when someone runs it)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def _library_imports() -> list[tuple[str, str, str]]:
    found = []
    for path in sorted(BENCHMARKS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "maniskill_torchrl":
                found += [(path.name, node.module, alias.name) for alias in node.names]
    return found


IMPORTS = _library_imports()


def test_the_scan_finds_the_benchmarks_imports():
    assert ("bench_obs_copy.py", "maniskill_torchrl.envs.maniskill", "_mapped") in IMPORTS


@pytest.mark.parametrize(
    ("module", "names"), sorted({(m, tuple(n for _, mm, n in IMPORTS if mm == m)) for _, m, _ in IMPORTS})
)
def test_each_name_a_benchmark_imports_from_the_library_exists(module, names):
    mod = importlib.import_module(module)
    missing = [
        n for n in names if n != "*" and not hasattr(mod, n) and importlib.util.find_spec(f"{module}.{n}") is None
    ]
    assert not missing, f"benchmarks import {missing} from {module}, which has no such name"
