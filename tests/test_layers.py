"""The package's layers, read statically from its imports (``ast``, nothing imported).

- The env core's helpers import neither the CPU engine (``maniskill_torchrl.engines``, or its
  deprecated aliases ``cpu_vector`` / ``cpu_worker`` / ``cpu_failures``, or the root package's
  ``CPUVectorEnv``) nor gymnasium's vector module. In the adapter's one file
  (``envs/maniskill.py``) only the factory, ``ManiSkillEnv``, names the engine: the wrapper reads
  the engine's declared capabilities instead.
- The transforms and the gym shim import no engine.
- The engine imports neither the gym shim, the transforms, nor the env core.

Every import counts, at any depth: module level, inside functions (lazy imports) and under
``TYPE_CHECKING``; so do the package modules they import in turn (the root package's own
``__init__``, whose public names load on first use, is not followed).
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = "maniskill_torchrl"
PKG_DIR = ROOT / PKG

# The helpers below the env core (DESIGN.md, "Layers"): none reaches the engine.
CORE_HELPERS = [
    "errors",
    "specs",
    "host_gather",
    "masked_merge",
    "episode_stats",
    "numpy_sum",
    "envs/_seeding",
]
HELPERS = sorted(p.stem for p in PKG_DIR.glob("_*.py") if not p.name.startswith("__"))
ENGINE = ("engines", "cpu_vector", "cpu_worker", "cpu_failures", "CPUVectorEnv")
# The adapter (envs/), its deprecated paths, and the checks below it.
ENV_CORE = ("envs", "errors", "maniskill_wrapper", "maniskill_env", "env")
ADAPTER = PKG_DIR / "envs" / "maniskill.py"


def _is_engine(name: str) -> bool:
    return any(name == f"{PKG}.{e}" or name.startswith(f"{PKG}.{e}.") for e in ENGINE)


def _file(module: str) -> Path | None:
    """The source file of a package module, or None (outside the package, or not a module)."""
    if module != PKG and not module.startswith(PKG + "."):
        return None
    path = ROOT.joinpath(*module.split("."))
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def imports(path: Path) -> frozenset[str]:
    """Every module name ``path`` imports, anywhere in it. ``from a import b`` gives ``a`` and ``a.b``
    (``b`` may be a submodule); relative imports are resolved."""
    module = _module(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Call):  # importlib.import_module("...") / __import__("...")
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if called in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant):
                names.add(str(node.args[0].value))
    return frozenset(names)


def closure(path: Path) -> dict[str, str]:
    """Every module ``path`` imports, directly or through the package's modules: name -> the
    package module that imports it."""
    seen: dict[str, str] = {}
    todo = [path]
    visited: set[Path] = set()
    while todo:
        current = todo.pop()
        if current in visited:
            continue
        visited.add(current)
        for name in imports(current):
            seen.setdefault(name, _module(current))
            target = _file(name)
            if target is not None and name != PKG:  # the root package's names load lazily
                todo.append(target)
    return seen


def _offences(path: Path, bad) -> list[str]:
    return sorted(f"{by} imports {name}" for name, by in closure(path).items() if bad(name))


def _files(*names: str) -> list[Path]:
    return [PKG_DIR / f"{n}.py" for n in names]


def _reaches_engine_or_vector(name: str) -> bool:
    return _is_engine(name) or name == "gymnasium.vector" or name.startswith("gymnasium.vector.")


@pytest.mark.parametrize("path", _files(*CORE_HELPERS, *HELPERS), ids=lambda p: p.name)
def test_the_helpers_import_no_engine_and_no_gymnasium_vector(path: Path) -> None:
    assert path.is_file(), path
    bad = _offences(path, _reaches_engine_or_vector)
    assert not bad, f"{path.name} reaches the CPU engine or gymnasium.vector: {bad}"


def _names_used(node: ast.AST) -> set[str]:
    return {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}


def test_only_the_factory_picks_the_engine() -> None:
    """The adapter's one file holds both classes, as TorchRL's do: ``ManiSkillEnv`` (the factory)
    picks the CPU engine; ``ManiSkillWrapper`` never names it (it reads the capabilities an
    engine declares), and nothing else of the file does. Besides the engine, the adapter reaches
    neither the engine's modules through its other imports nor gymnasium's vector module."""
    tree = ast.parse(ADAPTER.read_text())
    classes = {n.name: n for n in tree.body if isinstance(n, ast.ClassDef)}
    assert {"ManiSkillWrapper", "ManiSkillEnv"} <= set(classes)
    assert "CPUVectorEnv" in _names_used(classes["ManiSkillEnv"])
    elsewhere = [n for n in tree.body if not isinstance(n, (ast.ClassDef, ast.ImportFrom, ast.Import))]
    assert "CPUVectorEnv" not in _names_used(classes["ManiSkillWrapper"])
    assert all("CPUVectorEnv" not in _names_used(n) for n in elsewhere)
    others = {n for n in imports(ADAPTER) if not _is_engine(n)}
    reached = set()
    for name in others:
        target = _file(name)
        if target is not None and name != PKG:
            reached |= {f"{by} imports {n}" for n, by in closure(target).items() if _reaches_engine_or_vector(n)}
    assert not {n for n in others if n.startswith("gymnasium.vector")}
    assert not reached, reached


@pytest.mark.parametrize(
    "path",
    sorted((PKG_DIR / "transforms").glob("*.py")) + sorted((PKG_DIR / "wrappers").glob("*.py")),
    ids=lambda p: f"{p.parent.name}/{p.name}",
)
def test_transforms_and_the_gym_shim_import_no_engine(path: Path) -> None:
    bad = _offences(path, _is_engine)
    assert not bad, f"{path.parent.name}/{path.name} reaches the CPU engine: {bad}"


def _engine_files() -> list[Path]:
    files = sorted((PKG_DIR / "engines").glob("*.py"))
    # Before the engine had its subpackage it lived in these root modules.
    return files + [p for p in _files("cpu_vector", "cpu_worker", "cpu_failures") if p.is_file()]


@pytest.mark.parametrize("path", _engine_files(), ids=lambda p: p.name)
def test_the_engine_imports_no_gym_shim_transform_or_env_core(path: Path) -> None:
    above = [f"{PKG}.{m}" for m in ("wrappers", "transforms", *ENV_CORE)]

    def bad(name: str) -> bool:
        return any(name == a or name.startswith(a + ".") for a in above)

    offences = _offences(path, bad)
    assert not offences, f"{path.name} reaches a layer above it: {offences}"


def test_the_parser_sees_what_it_checks() -> None:
    """The factory picks the engine (so an engine import is seen when there is one); the engine
    exists where the layers say; the core list names real modules."""
    assert any(_is_engine(n) for n in imports(ADAPTER))
    assert (PKG_DIR / "engines" / "cpu_vector.py").is_file()
    assert all(p.is_file() for p in _files(*CORE_HELPERS)), CORE_HELPERS
    assert "_action_repeat" in HELPERS


CAPABILITIES = (
    "returns_copies",
    "runs_inference_mode",
    "seeds_partial_resets",
    "reconfigures_partially",
    "repeats_actions",
)


def test_the_engine_declares_what_the_core_reads() -> None:
    """The capabilities the core reads with ``getattr(base, name, False)``: True on the CPU engine,
    absent from ManiSkill's ``BaseEnv`` (so a plain ManiSkill env reads False)."""
    from mani_skill.envs.sapien_env import BaseEnv

    from maniskill_torchrl.engines import CPUVectorEnv

    for name in CAPABILITIES:
        assert getattr(CPUVectorEnv, name) is True, name
        assert not hasattr(BaseEnv, name), name
    for name in ("render_frame_shape", "set_repeat", "repeat"):
        assert hasattr(CPUVectorEnv, name) and not hasattr(BaseEnv, name), name


def test_the_old_engine_path_is_a_deprecated_alias() -> None:
    import importlib
    import sys

    import maniskill_torchrl
    from maniskill_torchrl.engines.cpu_vector import CPUVectorEnv

    sys.modules.pop("maniskill_torchrl.cpu_vector", None)
    with pytest.warns(DeprecationWarning, match="maniskill_torchrl.engines"):
        old = importlib.import_module("maniskill_torchrl.cpu_vector")
    assert old.CPUVectorEnv is CPUVectorEnv is maniskill_torchrl.CPUVectorEnv


@pytest.mark.parametrize("old", ["env", "maniskill_wrapper", "maniskill_env"])
def test_the_old_adapter_paths_are_deprecated_aliases(old: str) -> None:
    import importlib
    import sys

    import maniskill_torchrl

    sys.modules.pop(f"{PKG}.{old}", None)
    with pytest.warns(DeprecationWarning, match="maniskill_torchrl.envs.maniskill"):
        module = importlib.import_module(f"{PKG}.{old}")
    for name in module.__all__:
        assert getattr(module, name) is getattr(maniskill_torchrl, name)
