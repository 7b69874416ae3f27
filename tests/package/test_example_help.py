"""Every option of every example has help text, and its parser shows the defaults (issue 61, point 10)."""

from __future__ import annotations

import argparse
import importlib

import pytest

EXAMPLES = ["ppo_torchrl", "sac_torchrl", "bc_torchrl", "evaluate_gym", "distributed_ray"]


class _Parsed(Exception):
    def __init__(self, parser):
        self.parser = parser


@pytest.mark.parametrize("name", EXAMPLES)
def test_every_option_has_help(name, monkeypatch):
    module = importlib.import_module(name)

    def capture(self, *args, **kwargs):
        raise _Parsed(self)

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    entry = getattr(module, "parse_args", None) or module.main
    with pytest.raises(_Parsed) as parsed:
        entry([])
    parser = parsed.value.parser
    missing = [a.option_strings[0] for a in parser._actions if a.option_strings and not a.help and a.dest != "help"]
    assert not missing, f"{name}: options without help: {missing}"
    assert issubclass(parser.formatter_class, argparse.ArgumentDefaultsHelpFormatter), name
