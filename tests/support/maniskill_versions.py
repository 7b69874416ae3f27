"""Which ManiSkill the suite runs against, for marks on known upstream bugs.

ManiSkill's users install the release (``mani-skill`` 3.0.x, this library's ``maniskill``
extra) or the nightly (``mani-skill-nightly``); both install the same ``mani_skill`` package,
so only the distribution name tells them apart.
"""

from __future__ import annotations

import importlib.metadata
import sys

import pytest

__all__ = ["MANISKILL_DISTRIBUTION", "MANISKILL_NIGHTLY", "nightly_action_repeat_bug"]


def _maniskill_distribution() -> str | None:
    for name in ("mani-skill-nightly", "mani-skill"):
        try:
            return f"{name} {importlib.metadata.version(name)}"
        except importlib.metadata.PackageNotFoundError:
            pass
    return None


MANISKILL_DISTRIBUTION = _maniskill_distribution()
MANISKILL_NIGHTLY = MANISKILL_DISTRIBUTION is not None and MANISKILL_DISTRIBUTION.startswith("mani-skill-nightly")

# mani-skill-nightly 2026.8.x: ActionRepeatWrapper._update_dict_values tests ``isinstance(v, Array)`` with
# ``Array = Union[torch.Tensor, np.ndarray[Any], Sequence]`` (3.0.x: ``np.ndarray``). For a value that is not a
# tensor (a python info value, merged when some envs of a batch are done and others not), CPython 3.10-3.13
# raise "TypeError: issubclass() argument 2 cannot be a parameterized generic" (the typing rule checked on
# 3.10.13, 3.11.7, 3.12.1 and 3.13.0; the suite ran on 3.11.7). Release 3.0.x is not affected.
NIGHTLY_ACTION_REPEAT_BUG = MANISKILL_NIGHTLY and (3, 10) <= sys.version_info[:2] <= (3, 13)

nightly_action_repeat_bug = pytest.mark.xfail(
    NIGHTLY_ACTION_REPEAT_BUG,
    reason=(
        f"{MANISKILL_DISTRIBUTION} on Python {sys.version_info.major}.{sys.version_info.minor}: ManiSkill's own "
        "ActionRepeatWrapper (the oracle) raises TypeError in _update_dict_values on a non-tensor value "
        "(isinstance against Union[..., np.ndarray[Any], ...])"
    ),
    raises=TypeError,
    strict=False,
)
