"""The modules that moved, importable under their old names for one release, with a warning.

``import maniskill_torchrl.specs`` (say) finds no file any more; the finder below, last on
``sys.meta_path``, answers for the names in :data:`MOVED`: a module of that name holding the
public names of the modules it moved to, and a ``DeprecationWarning`` that says where to
import from. One table instead of a stub file per old path.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings

__all__ = ["MOVED", "install"]

_P = "maniskill_torchrl"
# old module -> (the modules its public names now live in, what to do instead)
MOVED: dict[str, tuple[tuple[str, ...], str]] = {
    f"{_P}.env": ((f"{_P}.envs.maniskill",), f"Import `from {_P} import ManiSkillEnv, ManiSkillWrapper` instead."),
    f"{_P}.maniskill_env": ((f"{_P}.envs.maniskill",), f"Import `from {_P} import ManiSkillEnv` instead."),
    f"{_P}.maniskill_wrapper": ((f"{_P}.envs.maniskill",), f"Import `from {_P} import ManiSkillWrapper` instead."),
    f"{_P}.cpu_vector": ((f"{_P}.engines.cpu_vector",), f"Import `from {_P} import CPUVectorEnv` instead."),
    f"{_P}.assertions": (
        (f"{_P}._assertions",),
        f"Import `from {_P}.testing import assert_tensordict_equal, assert_on_device` instead.",
    ),
    f"{_P}.errors": ((f"{_P}.envs._checks",), "It is internal: its names may change."),
    f"{_P}.specs": (
        (f"{_P}.envs._specs",),
        "It is internal: read the env's specs (`env.observation_spec`, ...) instead.",
    ),
    f"{_P}.host_gather": ((f"{_P}._host_gather",), "It is internal: its names may change."),
    f"{_P}.masked_merge": (
        (f"{_P}._masked_merge", f"{_P}._repeat"),
        f"It is internal: use `{_P}.ActionRepeat` instead.",
    ),
    f"{_P}.numpy_sum": ((f"{_P}._numpy_sum",), f"It is internal: use `{_P}.EpisodeMetrics` instead."),
    f"{_P}.episode_stats": ((f"{_P}._episode_stats",), f"It is internal: use `{_P}.EpisodeMetrics` instead."),
    f"{_P}.cli.demo": ((f"{_P}.cli",), f"Import `{_P}.cli` instead."),
}


class _MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname: str, path=None, target=None):
        if fullname not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec):
        return types.ModuleType(spec.name)

    def exec_module(self, module: types.ModuleType) -> None:
        targets, instead = MOVED[module.__name__]
        names: list[str] = []
        for target in targets:
            new = importlib.import_module(target)
            public = getattr(new, "__all__", [n for n in vars(new) if not n.startswith("_")])
            module.__dict__.update({n: getattr(new, n) for n in public})
            names += public
        module.__all__ = names
        warnings.warn(
            f"{module.__name__} is deprecated and will be removed in the next release: it moved to "
            f"{' and '.join(targets)}. {instead}",
            DeprecationWarning,
            stacklevel=2,
        )


def install() -> None:
    """Puts the finder last on ``sys.meta_path`` (once): real modules are always found first."""
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedFinder())
