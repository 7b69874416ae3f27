"""Registers this folder's area marker, ``upstream`` (tests/conftest.py marks each test with its folder's name).

It belongs in pyproject.toml's ``markers`` list, with the others; it is here while that file is edited elsewhere."""

from __future__ import annotations

import pytest


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "upstream: the TorchRL pull request of upstream/, on a copy of torchrl (make test-upstream)"
    )
