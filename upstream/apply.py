"""Turns a TorchRL tree into TorchRL with ManiSkill: the pull request of ``upstream/``.

``TARGET`` is a TorchRL checkout (a folder with ``torchrl/``, ``test/``, ``docs/`` and
``pyproject.toml``) or a folder holding a copy of an installed ``torchrl`` package
(``TARGET/torchrl``, e.g. copied from site-packages). This script

- copies ``maniskill_torchrl/envs/maniskill.py`` (the module's one source) to
  ``torchrl/envs/libs/maniskill.py``;
- copies the new files kept under ``upstream/`` in TorchRL's layout: the test file
  ``test/libs/test_maniskill.py`` and the CI scripts
  ``.github/unittest/linux_libs/scripts_maniskill/*`` (those in a checkout only);
- makes the edits of :data:`EDITS` to TorchRL's own files: the exports, the Hydra
  config, the docs, the extra, the CI job and labels. A package copy has only the
  files under ``torchrl/``; the others are skipped there.

Each edit inserts lines before or after the one line of a file that starts with its
anchor (an mjlab line: mjlab's pull request, pytorch/rl#3910, touched the same
places). Anchors rather than a diff: the same edits apply to torchrl 0.14.1's
package files and to checkouts of other commits, whose neighbouring lines differ. An
anchor found zero or several times stops the script before any file is written. A
second run changes nothing.

Usage::

    python upstream/apply.py TARGET             # apply in place
    python upstream/apply.py TARGET --check     # say what would change, change nothing
    python upstream/apply.py TARGET --patch maniskill.patch
        # leave TARGET as it is and write the pull request as a patch against it
        # (`git apply maniskill.patch` in the checkout)
"""

from __future__ import annotations

import argparse
import ast
import difflib
import sys
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
MODULE_SOURCE = ROOT / "maniskill_torchrl" / "envs" / "maniskill.py"
MODULE_TARGET = "torchrl/envs/libs/maniskill.py"
CI_DIR = ".github/unittest/linux_libs/scripts_maniskill"
# New files: path in TorchRL's tree -> where its text comes from.
NEW_FILES = {
    MODULE_TARGET: MODULE_SOURCE,
    "test/libs/test_maniskill.py": HERE / "test" / "libs" / "test_maniskill.py",
    **{
        f"{CI_DIR}/{p.name}": p
        for p in sorted((HERE / CI_DIR).iterdir())
        if p.is_file()
    },
}


@dataclass(frozen=True)
class Edit:
    """Insert ``text`` before or after the one line of ``path`` starting with
    ``anchor``."""

    path: str
    anchor: str
    text: str
    before: bool = True


CONFIG_SOURCE = ROOT / "maniskill_torchrl" / "configs.py"
CONFIG_TARGET = "torchrl.envs.libs.maniskill.ManiSkillEnv"


def _config_class() -> str:
    """``ManiSkillEnvConfig``'s source in ``maniskill_torchrl/configs.py``, the one
    class of both trees, with TorchRL's ``ManiSkillEnv`` as its ``_target_``."""
    source = CONFIG_SOURCE.read_text()
    tree = ast.parse(source)
    (node,) = [
        n
        for n in tree.body
        if isinstance(n, ast.ClassDef) and n.name == "ManiSkillEnvConfig"
    ]
    lines = source.splitlines(keepends=True)
    text = "".join(lines[node.decorator_list[0].lineno - 1 : node.end_lineno])
    target = '    _target_: str = "maniskill_torchrl.ManiSkillEnv"\n'
    if text.count(target) != 1:
        raise ApplyError(
            f"{CONFIG_SOURCE}: ManiSkillEnvConfig has no line {target.strip()!r}"
        )
    return text.replace(target, f'    _target_: str = "{CONFIG_TARGET}"\n') + "\n\n"


# The CI job, after mjlab's (a YAML block whose `if:` line is longer than 88 columns).
_JOB = (HERE / "edits" / "unittests-maniskill.yml").read_text()

EDITS = [
    # The two exports.
    Edit(
        "torchrl/envs/libs/__init__.py",
        "from .meltingpot import ",
        "from .maniskill import ManiSkillEnv, ManiSkillWrapper\n",
    ),
    Edit(
        "torchrl/envs/libs/__init__.py",
        '    "MeltingpotEnv",',
        '    "ManiSkillEnv",\n    "ManiSkillWrapper",\n',
    ),
    Edit(
        "torchrl/envs/__init__.py",
        "    MeltingpotEnv,",
        "    ManiSkillEnv,\n    ManiSkillWrapper,\n",
    ),
    Edit(
        "torchrl/envs/__init__.py",
        '    "MeltingpotEnv",',
        '    "ManiSkillEnv",\n    "ManiSkillWrapper",\n',
    ),
    # The Hydra config, beside MJLabEnvConfig.
    Edit(
        "torchrl/trainers/algorithms/configs/envs_libs.py",
        "class DMControlEnvConfig(",
        _config_class(),
        # before the "@dataclass" line above the anchor: see _insert
    ),
    Edit(
        "torchrl/trainers/algorithms/configs/__init__.py",
        "    MeltingpotEnvConfig,",
        "    ManiSkillEnvConfig,\n",
    ),
    Edit(
        "torchrl/trainers/algorithms/configs/__init__.py",
        '    "MeltingpotEnvConfig",',
        '    "ManiSkillEnvConfig",\n',
    ),
    Edit(
        "torchrl/trainers/algorithms/configs/__init__.py",
        '    cs.store(group="env", name="meltingpot",',
        '    cs.store(group="env", name="maniskill", node=ManiSkillEnvConfig)\n',
    ),
    # Docs.
    Edit(
        "docs/source/reference/envs_libraries.rst",
        "    MeltingpotEnv",
        "    ManiSkillEnv\n    ManiSkillWrapper\n",
    ),
    Edit(
        "docs/source/reference/config.rst",
        "    MeltingpotEnvConfig",
        "    ManiSkillEnvConfig\n",
    ),
    # The install extra, after mjlab's.
    Edit(
        "pyproject.toml",
        "mjlab = [",
        'maniskill = ["mani_skill>=3.0.0"]\n',
        before=False,
    ),
    # CI: the job and the labels that trigger it.
    Edit(
        ".github/workflows/test-linux-libs.yml",
        "  unittests-botorch:",
        _JOB,
    ),
    Edit(
        ".github/labeler.yml",
        '"Environments/dm_control":',
        '"Environments/maniskill":\n'
        "  - changed-files:\n"
        "    - any-glob-to-any-file:\n"
        "      - 'torchrl/envs/libs/maniskill.py'\n"
        "      - 'test/libs/test_maniskill.py'\n"
        "      - '.github/unittest/linux_libs/scripts_maniskill/**'\n"
        "\n",
    ),
    Edit(
        ".github/labels.yml",
        "- name: Environments/chess",
        "- name: Environments/maniskill\n"
        '  description: "Triggers maniskill environment tests only"\n'
        '  color: "0E8A16"\n'
        "\n",
    ),
]


class ApplyError(RuntimeError):
    """The target is not a TorchRL tree these edits fit."""


def _insert(text: str, edit: Edit) -> str:
    """``text`` with ``edit`` made (unchanged where it already is)."""
    lines = text.splitlines(keepends=True)
    hits = [i for i, line in enumerate(lines) if line.startswith(edit.anchor)]
    if len(hits) != 1:
        raise ApplyError(
            f"{edit.path}: {len(hits)} lines start with {edit.anchor!r}, expected one."
        )
    (i,) = hits
    if not edit.before:
        i += 1
    elif edit.text.startswith("@dataclass") and lines[i - 1].startswith("@dataclass"):
        i -= 1  # a class goes before the decorator of the anchor's class
    new = edit.text.splitlines(keepends=True)
    start = i - len(new) if edit.before else i
    if lines[max(start, 0) : start + len(new)] == new:
        return text  # applied already
    if edit.text in text:
        raise ApplyError(f"{edit.path}: the ManiSkill lines are there, elsewhere.")
    return "".join(lines[:i] + new + lines[i:])


def is_checkout(target: Path) -> bool:
    return (target / "pyproject.toml").is_file() and (target / "test").is_dir()


def changes(target: Path) -> dict[str, tuple[str | None, str, bool]]:
    """``{path: (old text or None, new text, executable)}`` of what applying the
    pull request to ``target`` changes, or ApplyError."""
    target = Path(target)
    if not (target / "torchrl" / "envs" / "libs" / "__init__.py").is_file():
        raise ApplyError(f"{target} holds no torchrl package (torchrl/envs/libs).")
    checkout = is_checkout(target)
    out: dict[str, tuple[str | None, str, bool]] = {}
    for rel, source in NEW_FILES.items():
        if not checkout and not rel.startswith(("torchrl/", "test/")):
            continue
        path = target / rel
        old = path.read_text() if path.exists() else None
        new = source.read_text()
        if old != new:
            out[rel] = (old, new, source.suffix == ".sh")
    edited: dict[str, str] = {}
    for edit in EDITS:
        path = target / edit.path
        if not path.exists():
            if checkout:
                raise ApplyError(f"{edit.path} is missing from the checkout {target}.")
            continue  # a package copy has no docs, CI or pyproject.toml
        text = edited.get(edit.path, path.read_text())
        edited[edit.path] = _insert(text, edit)
    for rel, new in edited.items():
        old = (target / rel).read_text()
        if new != old:
            out[rel] = (old, new, False)
    return out


def apply(target: Path) -> list[str]:
    """Applies the pull request to ``target`` in place; returns the paths written."""
    todo = changes(target)  # every check first: nothing is written on an error
    for rel, (_, new, executable) in todo.items():
        path = Path(target) / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(new)
        if executable:
            path.chmod(0o755)
    return sorted(todo)


def patch(target: Path) -> str:
    """The pull request as a git patch against ``target`` (left unchanged)."""
    chunks = []
    for rel, (old, new, executable) in sorted(changes(target).items()):
        a = old.splitlines(keepends=True) if old is not None else []
        b = new.splitlines(keepends=True)
        head = f"diff --git a/{rel} b/{rel}\n"
        if old is None:
            head += f"new file mode {'100755' if executable else '100644'}\n"
        diff = difflib.unified_diff(
            a,
            b,
            "/dev/null" if old is None else f"a/{rel}",
            f"b/{rel}",
            n=3,
        )
        chunks.append(head + "".join(diff))
    return "".join(chunks)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("target", type=Path, help="a TorchRL checkout or package copy")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--check", action="store_true", help="change nothing")
    group.add_argument(
        "--patch", type=Path, help="write the pull request as a patch here"
    )
    args = parser.parse_args(argv)
    try:
        if args.patch is not None:
            text = patch(args.target)
            args.patch.write_text(text)
            print(f"wrote {args.patch} ({text.count('diff --git')} files)")
        elif args.check:
            for rel in sorted(changes(args.target)):
                print(f"would change {rel}")
        else:
            for rel in apply(args.target):
                print(f"wrote {rel}")
    except ApplyError as err:
        print(f"apply.py: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
