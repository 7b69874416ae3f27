"""Optional dependencies: each missing one raises an ``ImportError`` that names the extra installing it."""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["EXTRAS", "missing_extra", "require"]

# top-level module -> (distribution, extra of maniskill-torchrl that installs it)
EXTRAS = {
    "hydra": ("hydra-core", "hydra"),
    "omegaconf": ("hydra-core", "hydra"),
    "matplotlib": ("matplotlib", "demo"),
    "imageio": ("imageio", "demo"),
    "ray": ("ray", "distributed"),
    "h5py": ("h5py", "maniskill"),
}


def missing_extra(module: str, what: str) -> ImportError:
    """The error for ``module`` missing: ``what`` needs it, and which ``pip install`` brings it."""
    top = module.split(".")[0]
    dist, extra = EXTRAS[top]
    return ImportError(
        f'{what} needs {dist}, which is not installed: pip install "maniskill-torchrl[{extra}]" (or {dist})',
        name=top,
    )


def require(module: str, what: str) -> ModuleType:
    """``importlib.import_module(module)``; where its distribution is not installed, an ``ImportError``
    naming the extra (:func:`missing_extra`). An installed one that fails to import raises its own error."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        if err.name is None or err.name.split(".")[0] != module.split(".")[0]:
            raise
        raise missing_extra(module, what) from None
