"""pip's settings that choose where packages come from, as ``uv pip install`` options.

uv reads neither pip's configuration files nor its ``PIP_*`` variables; ``scripts/setup.sh``
installs with uv, so it passes them on::

    python -m pip config list | python scripts/uv_args.py

prints one argument per line: ``--default-index``, ``--extra-index-url``, ``--find-links``,
``--constraints`` (each with its value on the next line), ``--no-index``, and
``SSL_CERT_FILE=<path>`` for pip's ``cert`` (uv reads that variable). Among the lines of
``pip config list``, a ``PIP_*`` variable (``:env:``) wins over an ``[install]`` value, which
wins over a ``[global]`` one, as in pip.
"""

from __future__ import annotations

import ast
import sys

_RANK = {"global": 0, "install": 1, ":env:": 2}
_FLAGS = {
    "index-url": "--default-index",
    "extra-index-url": "--extra-index-url",
    "find-links": "--find-links",
    "constraint": "--constraints",
}
_TRUE = ("1", "true", "yes", "on")


def settings(config_list: str) -> dict[str, str]:
    """The value pip uses for each name in ``pip config list``'s output (``section.name='value'``)."""
    best: dict[str, tuple[int, str]] = {}
    for line in config_list.splitlines():
        key, sep, value = line.strip().partition("=")
        section, _, name = key.rpartition(".")
        if sep and section in _RANK and _RANK[section] >= best.get(name, (-1, ""))[0]:
            best[name] = (_RANK[section], ast.literal_eval(value))
    return {name: value for name, (_, value) in best.items()}


def uv_args(config_list: str) -> list[str]:
    """``uv pip install`` arguments (and ``SSL_CERT_FILE=...``) for ``pip config list``'s output."""
    found = settings(config_list)
    args = []
    for name, flag in _FLAGS.items():
        for value in found.get(name, "").split():  # pip splits multi-valued settings on whitespace
            args += [flag, value]
    if found.get("no-index", "").lower() in _TRUE:
        args.append("--no-index")
    if found.get("cert"):
        args.append(f"SSL_CERT_FILE={found['cert']}")
    return args


if __name__ == "__main__":
    print("\n".join(uv_args(sys.stdin.read())))
