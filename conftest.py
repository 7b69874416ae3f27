"""Runs the Python code blocks of README.md and docs/**/*.md as tests (``make docs``), with Sybil.

Each Markdown file is one namespace: its blocks run in order, a later block seeing the names of
the earlier ones, and ``__name__`` is ``"__main__"`` so that the guarded entry points of the
examples run. A block that cannot run here (GPU sim, a Ray cluster, hours of training) is
preceded by ``<!-- skip: next "the reason" -->`` (invisible on the page). The
blocks run in a temporary folder, so files they write land there.

Only ``make docs`` collects these files (``pytest README.md docs tests/docs``); ``make test``
runs ``pytest tests`` and never loads a Markdown file.
"""

from __future__ import annotations

import os
import tempfile
import warnings

import pytest

try:
    from sybil import Sybil
    from sybil.parsers import markdown, myst
except ImportError:  # the docs extra is not installed: nothing to collect here
    Sybil = None

warnings.filterwarnings("ignore", message=".*precision lowered by casting.*")


def _setup(namespace: dict) -> None:
    namespace["__name__"] = "__main__"
    namespace["_cwd"] = os.getcwd()
    namespace["_tmp"] = tempfile.TemporaryDirectory(prefix="maniskill_torchrl_docs_")
    os.chdir(namespace["_tmp"].name)


def _teardown(namespace: dict) -> None:
    os.chdir(namespace["_cwd"])
    namespace["_tmp"].cleanup()


if Sybil is not None:
    _readme = Sybil(
        parsers=[markdown.PythonCodeBlockParser(), markdown.SkipParser()],
        patterns=["README.md"],
        setup=_setup,
        teardown=_teardown,
        name="readme",
    )
    _docs = Sybil(
        parsers=[myst.PythonCodeBlockParser(), myst.SkipParser()],
        patterns=["docs/**/*.md", "docs/*.md"],
        excludes=["docs/_build/**"],
        setup=_setup,
        teardown=_teardown,
        name="docs",
    )
    pytest_collect_file = (_readme + _docs).pytest()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A skipped doc block is reported at its line of its page (``README.md:142: <reason>``), not where pytest
    turned Sybil's ``unittest.SkipTest`` into a skip (``_pytest/unittest.py``)."""
    outcome = yield
    report = outcome.get_result()
    example = getattr(item, "example", None)
    if example is not None and report.skipped and isinstance(report.longrepr, tuple):
        reason = report.longrepr[2].removeprefix("Skipped: ")
        report.longrepr = (os.path.relpath(example.path, item.config.rootpath), example.line, reason)
