"""Writes the figures of the pull request's description (``upstream/README.md``) from
what the kit measures, so that they cannot go stale.

``README.md`` holds each figure between two HTML comments, ``<!-- kit:NAME -->`` and
``<!-- /kit -->`` (GitHub does not show them). This script fills them in:

- from the kit's files, at every run: the module's and the test file's lines, the test
  functions, the files the pull request adds or edits;
- from ``upstream/measured.json``, the record of the last measured runs: the lines the
  patch adds, each run's pytest summary and time, the lint tools and what they said.
  A record names the SHA-256 of the kit it measured: ``--check`` fails once the kit has
  changed since, until the runs are measured again.

Usage::

    python upstream/describe.py              # rewrite the figures of README.md
    python upstream/describe.py --check      # exit 1: README.md or the record stale
    # Measure: apply the kit to a TorchRL checkout (its git dir and a revision) or to a
    # copy of the installed torchrl package, run its test file there, lint it:
    python upstream/describe.py --measure-git ~/src/rl/.git --rev main --lint /tmp/lint
    python upstream/describe.py --measure-installed

``--lint DIR``: a folder made by ``pip install --target DIR`` with the tools of
TorchRL's pre-commit (usort, black, flake8, pydocstyle, codespell, pyupgrade,
autoflake); they run on the two Python files of the pull request, in the checkout,
with its ``setup.cfg``.
"""

from __future__ import annotations

import argparse
import ast
import datetime
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import apply  # noqa: E402

README = HERE / "README.md"
RECORD = HERE / "measured.json"
TEST_FILE = HERE / "test" / "libs" / "test_maniskill.py"
MARK = re.compile(r"<!-- kit:(\w+) -->(.*?)<!-- /kit -->", re.S)
# TorchRL's own pytest.ini (markers, native tracebacks, strict xfails): a package copy
# has none.
PYTEST_INI = """[pytest]
addopts =
    -ra
    --tb=native
markers =
    slow: mark test as slow to run
    gpu: mark test as requiring a GPU (CUDA device)
xfail_strict = True
"""
MODULE, TESTS = apply.MODULE_TARGET, "test/libs/test_maniskill.py"
# TorchRL's pre-commit hooks (.pre-commit-config.yaml): the command of each, the
# distribution that gives its version, the files it takes (pydocstyle: torchrl/ only).
LINTERS = {
    "usort": (["-m", "usort", "check"], "usort", [MODULE, TESTS]),
    "black": (["-m", "black", "--check", "--quiet"], "black", [MODULE, TESTS]),
    "flake8": (["-m", "flake8", "--config=setup.cfg"], "flake8", [MODULE, TESTS]),
    "pydocstyle": (["-m", "pydocstyle"], "pydocstyle", [MODULE]),
    "pyupgrade": (["-m", "pyupgrade", "--py311-plus"], "pyupgrade", [MODULE, TESTS]),
    "codespell": (["-m", "codespell_lib"], "codespell", [MODULE, TESTS]),
    "autoflake": (
        [
            "-m",
            "autoflake",
            "--check",
            "--remove-unused-variables",
            "--remove-all-unused-imports",
        ],
        "autoflake",
        [MODULE, TESTS],
    ),
}


# --------------------------------------------------------------------------- the kit
def kit_files() -> list[str]:
    """The paths, in TorchRL's tree, that the pull request adds or edits."""
    return sorted(set(apply.NEW_FILES) | {edit.path for edit in apply.EDITS})


def kit_hash() -> str:
    """SHA-256 of what the pull request is made of: its new files and its edits."""
    digest = hashlib.sha256()
    for rel, source in sorted(apply.NEW_FILES.items()):
        digest.update(rel.encode() + b"\0" + source.read_bytes() + b"\0")
    for edit in apply.EDITS:
        digest.update(
            f"{edit.path}\0{edit.anchor}\0{edit.text}\0{edit.before}".encode()
        )
    return digest.hexdigest()


def _lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def _test_functions(path: Path) -> int:
    tree = ast.parse(path.read_text())
    return sum(
        isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and node.name.startswith("test_")
        for node in ast.walk(tree)
    )


def _number(n: int) -> str:
    return f"{n:,}"


def _count(summary: str, kind: str) -> int:
    found = re.search(rf"(\d+) {kind}", summary)
    return int(found.group(1)) if found else 0


def figures(record: dict) -> dict[str, str]:
    """The text of every ``kit:`` mark of README.md."""
    runs = record.get("runs", [])
    main = next((r for r in runs if r.get("git")), None)
    files = kit_files()
    out = {
        "files": str(len(files)),
        "module_lines": _number(_lines(apply.MODULE_SOURCE)),
        "test_lines": _number(_lines(TEST_FILE)),
        "tests": str(_test_functions(TEST_FILE)),
        "record": f"`upstream/measured.json` (kit `{record.get('kit', '?')[:12]}`)",
    }
    rows = ["| where | result |", "|---|---|"]
    for run in runs:
        rows.append(f"| {run['where']} | {run['summary']} in {run['seconds']:.0f} s |")
    out["runs"] = "\n" + "\n".join(rows) + "\n"
    if main is not None:
        out["added"] = "+" + _number(main["added"])
        out["patched_files"] = str(main["files"])
        cases = _count(main["summary"], "passed") + _count(main["summary"], "skipped")
        out["cases"] = str(cases)
        out["main_commit"] = f"`{main['commit'][:9]}`"
        out["main_seconds"] = f"{main['seconds']:.0f} s"
        out["machine"] = main["machine"]
        versions = dict(main["versions"])
        wheel = versions.pop(
            "torchrl", "?"
        )  # the checkout's torchrl ran, not the wheel's
        out["versions"] = ", ".join(f"{k} {v}" for k, v in versions.items())
        out["wheel"] = wheel
        lint = main.get("lint") or {}
        out["lint"] = (
            ", ".join(
                f"{name} {v['version']}" + ("" if v["clean"] else " (NOT clean)")
                for name, v in lint.items()
            )
            or "no lint tool run"
        )
    return out


def render(text: str, values: dict[str, str]) -> str:
    def fill(match: re.Match) -> str:
        name = match.group(1)
        if name not in values:
            raise SystemExit(
                f"describe.py: README.md marks {name!r}, which nothing measures"
            )
        return f"<!-- kit:{name} -->{values[name]}<!-- /kit -->"

    return MARK.sub(fill, text)


def load_record() -> dict:
    return json.loads(RECORD.read_text()) if RECORD.exists() else {"runs": []}


# --------------------------------------------------------------------------- measuring
def _torchrl_package() -> Path:
    return Path(importlib.util.find_spec("torchrl").submodule_search_locations[0])


def _versions() -> dict[str, str]:
    names = ["torch", "tensordict", "torchrl", "mani_skill", "sapien", "hydra-core"]
    out = {"Python": ".".join(map(str, sys.version_info[:3]))}
    for name in names:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            pass
    return out


def _machine() -> str:
    cores = os.cpu_count()
    try:
        import torch

        gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    except Exception:  # a broken CUDA driver is no GPU
        gpu = "no GPU"
    return f"{cores} cores, {gpu}"


def _pytest(target: Path) -> tuple[str, float, str]:
    """Runs the test file in ``target``: pytest's summary, the seconds, the output."""
    cmd = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-rs"]
    env = dict(os.environ, PYTHONPATH=str(target), PYTHONUNBUFFERED="1")
    start = time.perf_counter()
    proc = subprocess.run(
        cmd + ["test/libs/test_maniskill.py"],
        cwd=target,
        env=env,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    seconds = time.perf_counter() - start
    found = re.findall(r"(?m)^=*\s*(\d+ \w+(?:, \d+ \w+)*) in [\d.]+s", proc.stdout)
    summary = found[-1] if found else f"no summary (exit {proc.returncode})"
    summary = ", ".join(p for p in summary.split(", ") if "warning" not in p)
    return summary, seconds, proc.stdout[-4000:] + proc.stderr[-2000:]


def _lint(target: Path, tools: Path) -> dict[str, dict]:
    out = {}
    env = dict(os.environ, PYTHONPATH=str(tools))
    for name, (args, package, files) in LINTERS.items():
        # The tools folder's version first: the one that runs.
        dist = next(tools.glob(f"{package}-*.dist-info"), None)
        if dist is not None:
            version = dist.name[len(package) + 1 : -len(".dist-info")]
        else:
            try:
                version = importlib.metadata.version(package)
            except importlib.metadata.PackageNotFoundError:
                continue
        proc = subprocess.run(
            [sys.executable, *args, *files],
            cwd=target,
            env=env,
            capture_output=True,
            text=True,
        )
        said = (proc.stdout + proc.stderr).strip()
        out[name] = {
            "version": version,
            "clean": proc.returncode == 0,
            "said": said[-800:],
        }
    checker = target / "scripts" / "check-docstring-args"
    if checker.exists():
        proc = subprocess.run(
            [sys.executable, str(checker), MODULE],
            cwd=target,
            capture_output=True,
            text=True,
        )
        said = (proc.stdout + proc.stderr).strip()
        out["check-docstring-args"] = {
            "version": "checkout",
            "clean": proc.returncode == 0,
            "said": said[-800:],
        }
    return out


def _added(diff: str) -> int:
    return sum(
        line.startswith("+") and not line.startswith("+++")
        for line in diff.splitlines()
    )


def measure_git(git_dir: Path, rev: str, lint: Path | None) -> dict:
    """The kit applied to ``rev`` of a TorchRL repository, its test file run there with
    the installed torchrl's compiled extension."""

    def git(*args: str, **kwargs) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["git", "--git-dir", str(git_dir), *args], check=True, **kwargs
        )

    commit = git("rev-parse", rev, capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="torchrl-") as tmp:
        target = Path(tmp)
        archive = git("archive", commit, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
        diff = apply.patch(target)
        apply.apply(target)
        for ext in _torchrl_package().glob("_torchrl*.so"):
            shutil.copy2(ext, target / "torchrl" / ext.name)
        summary, seconds, output = _pytest(target)
        print(output)
        run = {
            "where": f"pytorch/rl {rev} (`{commit[:9]}`), its pytest.ini, conftest",
            "git": True,
            "commit": commit,
            "files": diff.count("diff --git"),
            "added": _added(diff),
            "summary": summary,
            "seconds": round(seconds, 1),
            "date": datetime.date.today().isoformat(),
            "machine": _machine(),
            "versions": _versions(),
        }
        if lint is not None:
            run["lint"] = _lint(target, lint)
    return run


def measure_installed() -> dict:
    """The kit applied to a copy of the installed torchrl package, its test file run."""
    version = importlib.metadata.version("torchrl")
    with tempfile.TemporaryDirectory(prefix="torchrl-") as tmp:
        target = Path(tmp)
        shutil.copytree(_torchrl_package(), target / "torchrl")
        apply.apply(target)
        (target / "pytest.ini").write_text(PYTEST_INI)
        summary, seconds, output = _pytest(target)
        print(output)
    hydra = importlib.util.find_spec("hydra") is not None
    return {
        "where": f"torchrl {version} as installed, a patched copy"
        + (", Hydra installed" if hydra else ", no Hydra"),
        "git": False,
        "summary": summary,
        "seconds": round(seconds, 1),
        "date": datetime.date.today().isoformat(),
        "machine": _machine(),
        "versions": _versions(),
    }


def record_run(run: dict) -> None:
    """Keeps ``run`` in the record, in place of an older run of the same kind."""
    record = load_record()
    kit = kit_hash()
    runs = [r for r in record.get("runs", []) if r["git"] != run["git"]]
    if record.get("kit") != kit:
        runs = []  # runs of another kit say nothing of this one
    record = {"kit": kit, "runs": sorted(runs + [run], key=lambda r: not r["git"])}
    RECORD.write_text(json.dumps(record, indent=2) + "\n")


# --------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--check", action="store_true", help="change nothing")
    group.add_argument("--measure-git", type=Path, help="a TorchRL git dir")
    group.add_argument("--measure-installed", action="store_true")
    parser.add_argument("--rev", default="main", help="with --measure-git")
    parser.add_argument("--lint", type=Path, help="a folder of lint tools")
    args = parser.parse_args(argv)
    if args.measure_git is not None:
        record_run(measure_git(args.measure_git, args.rev, args.lint))
    elif args.measure_installed:
        record_run(measure_installed())
    record = load_record()
    text = README.read_text()
    new = render(text, figures(record))
    if args.check:
        problems = []
        if record.get("kit") != kit_hash():
            problems.append(
                "the kit changed since upstream/measured.json was measured: run "
                "--measure-git and --measure-installed again"
            )
        if new != text:
            problems.append("README.md's figures are stale: run upstream/describe.py")
        for problem in problems:
            print(f"describe.py: {problem}", file=sys.stderr)
        return 1 if problems else 0
    if new != text:
        README.write_text(new)
        print(f"wrote {README}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
