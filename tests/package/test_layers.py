"""The package's layers, read statically from its imports (``ast``, nothing imported).

Each module sits in one layer of :data:`LAYERS` (bottom first, as in ``docs/contributing.md``,
"Module layout"), and imports only from its own layer or those below: the helpers at the bottom,
the CPU engine beside the envs (only the factory, ``ManiSkillEnv``, names it), the transforms
and the gym shim above the envs and below data, testing, the recipe and the CLI. No import
chain inside the package is longer than :data:`MAX_CHAIN` modules.

Every import counts, at any depth: module level, inside functions (lazy imports) and
``importlib.import_module("...")`` calls; imports under ``if TYPE_CHECKING:`` never run and
are left out of the chains. ``from pkg import name`` is an import of ``pkg.name`` when that is a
module, else of ``pkg``. The root package (``maniskill_torchrl/__init__.py``, whose public
names load on first use) is the facade above everything, and no layer.
"""

from __future__ import annotations

import ast
import importlib
import sys
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PKG = "maniskill_torchrl"
PKG_DIR = ROOT / PKG
MAX_CHAIN = 7

# Bottom first. A module's layer is the first entry whose name is the module or a package above it.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    (
        "helpers",
        ("errors", "_internal", "_private"),
    ),
    ("engines", ("engines",)),
    ("envs", ("envs", "parallel", "async_collector")),
    ("transforms and the gym shim", ("transforms", "wrappers")),
    ("data and testing", ("data", "testing")),
    ("recipe", ("pipeline", "configs", "evaluation", "trainer_hooks", "objectives")),
    ("CLI", ("cli", "__main__")),
]
ADAPTER = PKG_DIR / "envs" / "maniskill.py"


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module(p): p for p in sorted(PKG_DIR.rglob("*.py"))}


def layer(module: str) -> int:
    """The rank of ``module``'s layer in :data:`LAYERS`."""
    rel = module.removeprefix(PKG + ".")
    for rank, (_, names) in enumerate(LAYERS):
        if any(rel == n or rel.startswith(n + ".") for n in names):
            return rank
    raise AssertionError(f"{module} is in no layer of tests/test_layers.py's LAYERS: add it to one")


def _type_checking(node: ast.AST) -> bool:
    test = getattr(node, "test", None)
    return isinstance(node, ast.If) and getattr(test, "id", getattr(test, "attr", None)) == "TYPE_CHECKING"


def _nodes(tree: ast.AST):
    """Every node of ``tree`` but those under ``if TYPE_CHECKING:``."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        if _type_checking(node):
            todo.extend(node.orelse)
        else:
            todo.extend(ast.iter_child_nodes(node))


@cache
def imports(module: str) -> frozenset[str]:
    """The package modules ``module`` imports (its own file only), resolved to module names."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names: set[str] = set()
    for node in _nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            subs = {f"{base}.{a.name}" for a in node.names} & MODULES.keys()
            names.update(subs or {base})
        elif isinstance(node, ast.Call):  # importlib.import_module("...") / __import__("...")
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if called in ("import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant):
                names.add(str(node.args[0].value))
    return frozenset(n for n in names if n in MODULES and n not in (PKG, module))


def longest_chain(module: str, seen: tuple[str, ...] = ()) -> list[str]:
    """The longest chain of imports from ``module`` that visits no module twice."""
    best = [module]
    for name in sorted(imports(module)):
        if name not in seen:
            chain = [module, *longest_chain(name, (*seen, module))]
            best = chain if len(chain) > len(best) else best
    return best


def upward(module: str) -> list[str]:
    """The modules ``module`` imports from a layer above its own."""
    return sorted(n for n in imports(module) if layer(n) > layer(module))


def long_chains(modules) -> dict[str, str]:
    """The import chains of more than :data:`MAX_CHAIN` modules, from each of ``modules``."""
    chains = {m: longest_chain(m) for m in modules}
    return {m: " -> ".join(c) for m, c in chains.items() if len(c) > MAX_CHAIN}


@pytest.mark.parametrize("module", [m for m in MODULES if m != PKG])
def test_no_import_runs_upward(module: str) -> None:
    up = upward(module)
    assert not up, f"{module} ({LAYERS[layer(module)][0]}) imports from a layer above it: {up}"


def test_import_chains_are_short() -> None:
    long = long_chains(MODULES)
    assert not long, f"import chains longer than {MAX_CHAIN} modules: {long}"
    assert max(len(longest_chain(m)) for m in MODULES) >= 5  # the parser sees chains at all


def test_the_checks_fail_on_a_bad_graph(monkeypatch: pytest.MonkeyPatch) -> None:
    """The same two checks, on a made-up graph: a helper importing the envs is upward, and a
    chain of eight modules is too long."""
    chain = [f"{PKG}.cli", f"{PKG}.pipeline", f"{PKG}.transforms.action_repeat", f"{PKG}.envs.maniskill"]
    chain += [f"{PKG}.engines.cpu_vector", f"{PKG}.engines._worker", f"{PKG}._internal.repeat", f"{PKG}._private"]
    graph = dict(zip(chain, ({n} for n in chain[1:]))) | {f"{PKG}._private": {f"{PKG}.envs.maniskill"}}
    monkeypatch.setattr(sys.modules[__name__], "imports", lambda m: frozenset(graph.get(m, ())))
    assert upward(f"{PKG}._private") == [f"{PKG}.envs.maniskill"]
    assert upward(f"{PKG}.envs.maniskill") == []
    assert list(long_chains([f"{PKG}.cli"])) == [f"{PKG}.cli"]
    assert not long_chains([f"{PKG}.pipeline"])  # seven modules: within the limit


def _gymnasium_vector(module: str) -> list[str]:
    path = MODULES[module]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            found += [n for n in names if n == "gymnasium.vector" or n.startswith("gymnasium.vector.")]
    return found


@pytest.mark.parametrize("module", [m for m in MODULES if m != PKG and layer(m) in (0, 2)])
def test_the_helpers_and_envs_import_no_gymnasium_vector(module: str) -> None:
    assert not _gymnasium_vector(module), f"{module} imports gymnasium's vector module"


def _names_used(node: ast.AST) -> set[str]:
    return {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}


def test_the_adapter_is_self_contained() -> None:
    """``envs/maniskill.py`` is the file bound for TorchRL's tree: at module level it imports
    torch, tensordict, torchrl, numpy and the standard library only; it names no module of this
    project anywhere, nor the CPU engine (``engine_env.py`` adds that on top)."""
    import sys

    tree = ast.parse(ADAPTER.read_text())
    top = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            top |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            top.add(node.module.split(".")[0])
    allowed = {"torch", "tensordict", "torchrl", "numpy", "__future__"} | set(sys.stdlib_module_names)
    assert top <= allowed, f"module-level imports beyond torch/tensordict/torchrl/numpy: {top - allowed}"
    every = {
        (a.name if isinstance(n, ast.Import) else n.module or "")
        for n in ast.walk(tree)
        if isinstance(n, (ast.Import, ast.ImportFrom))
        for a in n.names
    }
    assert not [m for m in every if m.startswith(PKG)], every
    assert "CPUVectorEnv" not in _names_used(tree)


def test_nothing_shadows_a_torchrl_name() -> None:
    """No public name of the package or its public modules is also a public name of
    ``torchrl.envs`` (``ParallelEnv`` was, until it became ``ManiSkillParallelEnv``)."""
    import torchrl.envs

    import maniskill_torchrl

    theirs = set(torchrl.envs.__all__) if hasattr(torchrl.envs, "__all__") else set(dir(torchrl.envs))
    ours = set(maniskill_torchrl.__all__)
    for public in ("transforms", "wrappers", "data", "testing", "pipeline", "parallel", "envs", "engines"):
        ours |= set(importlib.import_module(f"{PKG}.{public}").__all__)
    assert "ParallelEnv" in theirs
    assert not ours & theirs, sorted(ours & theirs)


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
