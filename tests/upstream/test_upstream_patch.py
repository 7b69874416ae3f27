"""The pull request of ``upstream/`` against TorchRL as released (``make test-upstream``; ``make test`` skips it).

The project's CI cannot reach TorchRL's repository, so the installed torchrl package (its Python files and its compiled
``_torchrl`` extension) is copied into a temporary folder, ``upstream/apply.py`` adds the module, the exports, the Hydra
config and the test file there, and TorchRL's test file ``test/libs/test_maniskill.py`` runs in a child process whose
``import torchrl`` is that copy. Beside it:

- the module imports only torch, tensordict, torchrl, numpy and the standard library at module level, ManiSkill,
  gymnasium and SAPIEN only inside functions, and nothing of this project;
- ``import torchrl.envs`` of the patched copy loads none of ManiSkill, gymnasium or SAPIEN;
- ``apply.py``: a second run changes nothing, its ``--patch`` gives the same files as applying in place, a missing
  anchor stops it before it writes anything;
- the fields of the Hydra config ``ManiSkillEnvConfig`` build an env (Hydra is not installed here: its defaults are
  read from the source and passed as Hydra's ``instantiate`` would pass them).
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
UPSTREAM = ROOT / "upstream"
APPLY = UPSTREAM / "apply.py"
MODULE = ROOT / "maniskill_torchrl" / "envs" / "maniskill.py"
TEST_FILE = UPSTREAM / "test" / "libs" / "test_maniskill.py"
TORCHRL = Path(importlib.util.find_spec("torchrl").submodule_search_locations[0])
# What the module may import at module level (besides the standard library), and inside functions.
MODULE_LEVEL = {"__future__", "torch", "tensordict", "torchrl", "numpy"}
LAZY = {"mani_skill", "gymnasium", "sapien"}
# TorchRL's own pytest.ini (markers, native tracebacks, strict xfails).
PYTEST_INI = """[pytest]
addopts =
    -ra
    --tb=native
markers =
    slow: mark test as slow to run
    gpu: mark test as requiring a GPU (CUDA device)
xfail_strict = True
"""
# The files apply.py edits in a package copy.
EDITED = [
    "torchrl/envs/__init__.py",
    "torchrl/envs/libs/__init__.py",
    "torchrl/trainers/algorithms/configs/__init__.py",
    "torchrl/trainers/algorithms/configs/envs_libs.py",
]
TIMEOUT_S = 900


def _run(cmd: list[str], cwd: Path, pythonpath: Path | None = None, check: bool = True) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    if check:
        assert proc.returncode == 0, (
            f"{' '.join(map(str, cmd))} exited with {proc.returncode}\n"
            f"--- stdout ---\n{proc.stdout[-6000:]}\n--- stderr ---\n{proc.stderr[-6000:]}"
        )
    return proc


def _copy_torchrl(target: Path, files: list[str] | None = None) -> None:
    """The installed torchrl package (or only ``files`` of it) under ``target/torchrl``."""
    if files is None:
        # With the bytecode (copytree keeps each file's time, which a .pyc is checked against): a
        # child process need not compile torchrl again; the files apply.py rewrites are newer.
        shutil.copytree(TORCHRL, target / "torchrl")
        return
    for rel in files:
        dest = target / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(TORCHRL.parent / rel, dest)


@pytest.fixture(scope="module")
def patched(tmp_path_factory) -> Path:
    """A copy of the installed torchrl with the pull request applied by ``apply.py``."""
    target = tmp_path_factory.mktemp("torchrl_patched")
    _copy_torchrl(target)
    assert list((target / "torchrl").glob("_torchrl*.so")), "the copy lacks torchrl's C extension"
    _run([sys.executable, APPLY, target], cwd=ROOT)
    (target / "pytest.ini").write_text(PYTEST_INI)
    return target


# ----------------------------------------------------------------------------- the module
def _imports(tree: ast.Module) -> tuple[list[ast.AST], list[ast.AST]]:
    """The module's import statements: those run at import time, and those inside functions and classes
    (``if TYPE_CHECKING:`` blocks are neither)."""
    top, inner = [], []

    def visit(node: ast.AST, nested: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                for sub in child.orelse:
                    visit_stmt(sub, nested)
                continue
            visit_stmt(child, nested)

    def visit_stmt(node: ast.AST, nested: bool) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            (inner if nested else top).append(node)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda)):
            visit(node, True)
        else:
            visit(node, nested)

    visit(tree, False)
    return top, inner


def _roots(node: ast.AST) -> list[str]:
    if isinstance(node, ast.ImportFrom):
        return ["." * node.level + (node.module or "")]
    return [alias.name.split(".")[0] for alias in node.names]


def test_module_imports_only_torchrl_dependencies():
    source = MODULE.read_text()
    assert "maniskill_torchrl" not in source, "the upstream module names this project"
    top, inner = _imports(ast.parse(source))
    stdlib = set(sys.stdlib_module_names)
    top_roots = {root.split(".")[0] for node in top for root in _roots(node)}
    inner_roots = {root.split(".")[0] for node in inner for root in _roots(node)}
    assert "" not in top_roots | inner_roots, "relative import"
    assert top_roots <= MODULE_LEVEL | stdlib, f"module-level imports beyond TorchRL's dependencies: {top_roots}"
    assert inner_roots <= MODULE_LEVEL | LAZY | stdlib, f"lazy imports of: {inner_roots - MODULE_LEVEL - stdlib}"
    assert {"mani_skill", "gymnasium"} <= inner_roots  # imported, lazily


def test_apply_writes_the_pull_request(patched):
    assert (patched / "torchrl/envs/libs/maniskill.py").read_text() == MODULE.read_text()
    assert (patched / "test/libs/test_maniskill.py").read_text() == TEST_FILE.read_text()
    libs = (patched / "torchrl/envs/libs/__init__.py").read_text()
    assert "from .maniskill import ManiSkillEnv, ManiSkillWrapper\n" in libs
    envs = (patched / "torchrl/envs/__init__.py").read_text()
    assert envs.count("ManiSkillEnv,") == 1 and envs.count('"ManiSkillEnv",') == 1
    configs = (patched / "torchrl/trainers/algorithms/configs/__init__.py").read_text()
    assert 'cs.store(group="env", name="maniskill", node=ManiSkillEnvConfig)' in configs
    # A package copy has no docs, CI scripts or pyproject.toml: nothing is made up for them.
    assert not (patched / ".github").exists() and not (patched / "docs").exists()


def test_patched_torchrl_envs_imports_no_simulator(patched):
    code = f"""
import json, sys
import torchrl, torchrl.envs
from torchrl import _torchrl
from torchrl.envs import ManiSkillEnv, ManiSkillWrapper
print(json.dumps({{
    "torchrl": torchrl.__file__,
    "extension": _torchrl.__file__,
    "module": sys.modules[ManiSkillEnv.__module__].__file__,
    "loaded": sorted({{m.split(".")[0] for m in sys.modules}} & {LAZY | {"maniskill_torchrl"}!r}),
}}))
"""
    out = json.loads(
        _run([sys.executable, "-c", code], cwd=patched, pythonpath=patched).stdout.strip().splitlines()[-1]
    )
    for key in ("torchrl", "extension", "module"):
        assert Path(out[key]).resolve().is_relative_to(patched.resolve()), out
    assert out["module"].endswith("torchrl/envs/libs/maniskill.py")
    assert out["loaded"] == [], f"import torchrl.envs loads {out['loaded']}"


def test_upstream_tests_pass_on_patched_torchrl(patched):
    proc = _run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-rs", "test/libs/test_maniskill.py"],
        cwd=patched,
        pythonpath=patched,
        check=False,
    )
    tail = proc.stdout[-6000:] + proc.stderr[-3000:]
    assert proc.returncode == 0, tail
    # pytest's last line, e.g. "29 passed, 5 skipped, 98 warnings in 64.20s (0:01:04)"
    summaries = re.findall(r"(?m)^=*\s*(\d+ \w+(?:, \d+ \w+)*) in [\d.]+s", proc.stdout)
    assert summaries, tail
    summary = summaries[-1]
    counts = {kind: int(n) for n, kind in re.findall(r"(\d+) (\w+)", summary)}
    assert counts.get("passed", 0) >= 25 and not counts.keys() & {"failed", "error", "errors"}, tail


def test_module_examples_run_in_patched_torchrl(patched):
    """The docstring examples of ``torchrl/envs/libs/maniskill.py`` (``from torchrl.envs import ...``) run there and
    give what they show. They carry ``# doctest: +SKIP``, as TorchRL's libs do (its doc build has no simulators):
    here they run without it, from a copy of the module beside it."""
    module = patched / "torchrl" / "envs" / "libs" / "maniskill.py"
    text = module.read_text()
    assert text.count("# doctest: +SKIP") >= 10, "the examples are not marked as TorchRL's libs mark theirs"
    unskipped = module.with_name("_maniskill_doctest.py")
    unskipped.write_text(text.replace("  # doctest: +SKIP", ""))
    try:
        proc = _run(
            [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "--doctest-modules",
             str(unskipped.relative_to(patched))],
            cwd=patched,
            pythonpath=patched,
            check=False,
        )  # fmt: skip
    finally:
        unskipped.unlink()
    tail = proc.stdout[-6000:] + proc.stderr[-3000:]
    assert proc.returncode == 0, tail
    passed = re.findall(r"(\d+) passed", proc.stdout)
    assert passed and int(passed[-1]) >= 3 and "skipped" not in proc.stdout, tail  # Wrapper, Env, get_state


# ----------------------------------------------------------------------------- the Hydra config
def _config_defaults(envs_libs: Path) -> dict:
    """``ManiSkillEnvConfig``'s fields and defaults, read from the source (MISSING: no default)."""
    tree = ast.parse(envs_libs.read_text())
    (cls,) = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "ManiSkillEnvConfig"]
    fields = {}
    for node in cls.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            value = node.value
            fields[node.target.id] = (
                "MISSING" if isinstance(value, ast.Name) and value.id == "MISSING" else ast.literal_eval(value)
            )
    return fields


def test_config_fields_build_the_env(patched):
    fields = _config_defaults(patched / "torchrl/trainers/algorithms/configs/envs_libs.py")
    assert fields.pop("_target_") == "torchrl.envs.libs.maniskill.ManiSkillEnv"
    assert fields.pop("env_name") == "MISSING"
    # Hydra's instantiate passes every field but those starting with "_" (EnvLibsConfig's _partial_).
    kwargs = {k: v for k, v in fields.items() if not k.startswith("_")}
    code = f"""
from torchrl.envs import ManiSkillEnv
kwargs = {kwargs!r}
for extra in ({{"obs_mode": "state"}}, {{"obs_mode": "state", "from_pixels": True}}):
    env = ManiSkillEnv("PickCube-v1", **{{**kwargs, **extra}})
    assert ("pixels" in env.observation_spec.keys()) == extra.get("from_pixels", False)
    env.rand_step(env.reset(seed=0))
    env.close()
print("ok")
"""
    assert _run([sys.executable, "-c", code], cwd=patched, pythonpath=patched).stdout.strip().endswith("ok")


# ----------------------------------------------------------------------------- apply.py
def test_apply_twice_and_as_a_patch(tmp_path):
    in_place, by_patch = tmp_path / "in_place", tmp_path / "by_patch"
    for target in (in_place, by_patch):
        _copy_torchrl(target, EDITED)
    _run([sys.executable, APPLY, in_place], cwd=ROOT)
    again = _run([sys.executable, APPLY, in_place], cwd=ROOT)
    assert again.stdout == "", "a second run changed files"
    assert _run([sys.executable, APPLY, in_place, "--check"], cwd=ROOT).stdout == ""

    patch = tmp_path / "maniskill.patch"
    _run([sys.executable, APPLY, by_patch, "--patch", patch], cwd=ROOT)
    assert (by_patch / EDITED[0]).read_text() == (TORCHRL.parent / EDITED[0]).read_text(), "--patch wrote files"
    if shutil.which("git") is None:
        pytest.skip("git is not installed: the patch is not applied")
    _run(["git", "apply", patch], cwd=by_patch)
    written = sorted(str(p.relative_to(in_place)) for p in in_place.rglob("*") if p.is_file())
    assert written == sorted(str(p.relative_to(by_patch)) for p in by_patch.rglob("*") if p.is_file())
    for rel in written:
        assert (in_place / rel).read_text() == (by_patch / rel).read_text(), rel


def test_apply_stops_before_writing_where_an_anchor_is_missing(tmp_path):
    _copy_torchrl(tmp_path, EDITED)
    libs = tmp_path / "torchrl/envs/libs/__init__.py"
    libs.write_text(re.sub(r"(?m)^from \.meltingpot import .*\n", "", libs.read_text()))
    proc = _run([sys.executable, APPLY, tmp_path], cwd=ROOT, check=False)
    assert proc.returncode == 1
    assert "lines start with 'from .meltingpot import '" in proc.stderr
    assert not (tmp_path / "torchrl/envs/libs/maniskill.py").exists()
    assert not (tmp_path / "test").exists()


# ----------------------------------------------------------------------------- the description
def test_description_figures_are_measured():
    """README.md's figures are what ``describe.py`` writes, from a record of this very kit."""
    proc = _run([sys.executable, UPSTREAM / "describe.py", "--check"], cwd=ROOT, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
