"""Bit-for-bit and device assertions over TensorDicts, the core of :mod:`maniskill_torchrl.testing`
(which exports them): :func:`assert_tensordict_equal` and :func:`assert_on_device`. No TorchRL
import, no ManiSkill import."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

__all__ = ["assert_on_device", "assert_tensordict_equal"]

# Element size -> the integer dtype whose values are a float's bits.
_BITS = {1: torch.uint8, 2: torch.int16, 4: torch.int32, 8: torch.int64}


def leaf_keys(td: TensorDictBase) -> list:
    return sorted(td.keys(include_nested=True, leaves_only=True), key=str)


def _bits(x: torch.Tensor) -> torch.Tensor:
    flat = x.detach().cpu().contiguous().reshape(-1)
    if flat.dtype == torch.bool:
        return flat.view(torch.uint8)
    as_int = _BITS.get(flat.element_size())
    return flat.view(as_int) if as_int is not None else flat.view(torch.uint8)


def tensor_difference(actual: torch.Tensor, expected: torch.Tensor) -> str | None:
    """What differs between two tensors (shape, dtype, device or bits), or None."""
    for what in ("shape", "dtype", "device"):
        a, e = getattr(actual, what), getattr(expected, what)
        if a != e:
            return f"{what} {tuple(a) if what == 'shape' else a} != expected {tuple(e) if what == 'shape' else e}"
    a, e = _bits(actual), _bits(expected)
    if torch.equal(a, e):
        return None
    if a.shape != e.shape:  # an element size without an integer view: bytes compared
        return "bytes differ"
    diff = (a != e).nonzero().reshape(-1)
    first = int(diff[0])
    index = tuple(int(i) for i in np.unravel_index(first, tuple(actual.shape))) if actual.ndim else ()
    got = actual.detach().cpu().reshape(-1)[first].item()
    want = expected.detach().cpu().reshape(-1)[first].item()
    return (
        f"{diff.numel()} of {actual.numel()} values differ in their bits, first at index {index}: "
        f"{got!r} != expected {want!r}"
    )


def assert_tensordict_equal(actual: TensorDictBase, expected: TensorDictBase, *, msg: str = "") -> None:
    """Asserts that two TensorDicts are the same to the bit: the same leaf keys and batch size, and
    for every leaf the same shape, dtype, device and bits.

    Unlike :func:`tensordict.assert_close` (``torch.testing.assert_close`` per leaf), nothing is
    within a tolerance: ``0.0`` and ``-0.0`` differ, a NaN equals only the same NaN bits, and a
    float32 entry never equals a float64 one. The :class:`AssertionError` names the first
    differing key path (in sorted order) and what differs.

    Args:
        actual: the TensorDict under test.
        expected: the reference.

    Keyword Args:
        msg (str): prefixed to the error message.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from maniskill_torchrl.testing import assert_tensordict_equal
        >>> a = TensorDict({"obs": torch.zeros(2, 3), ("next", "reward"): torch.ones(2, 1)}, [2])
        >>> assert_tensordict_equal(a, a.clone())
        >>> b = a.clone()
        >>> b["next", "reward"][1] = 2.0
        >>> assert_tensordict_equal(b, a)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        AssertionError: ('next', 'reward'): 1 of 2 values differ in their bits, first at index (1, 0): 2.0 != ...
    """
    prefix = f"{msg}: " if msg else ""
    for name, td in (("actual", actual), ("expected", expected)):
        if not isinstance(td, TensorDictBase):
            raise TypeError(f"assert_tensordict_equal compares TensorDicts; {name} is a {type(td).__name__}.")
    keys, other = leaf_keys(actual), leaf_keys(expected)
    if keys != other:
        missing = [k for k in other if k not in keys]
        extra = [k for k in keys if k not in other]
        raise AssertionError(f"{prefix}keys differ: missing {missing}, unexpected {extra}")
    if actual.batch_size != expected.batch_size:
        raise AssertionError(f"{prefix}batch size {list(actual.batch_size)} != expected {list(expected.batch_size)}")
    for key in keys:
        a, e = actual.get(key), expected.get(key)
        if not (isinstance(a, torch.Tensor) and isinstance(e, torch.Tensor)):
            if a != e:
                raise AssertionError(f"{prefix}{key!r}: {a!r} != expected {e!r}")
            continue
        difference = tensor_difference(a, e)
        if difference is not None:
            raise AssertionError(f"{prefix}{key!r}: {difference}")


def _same_device(actual: torch.device, wanted: torch.device) -> bool:
    """One device, however named: ``"cuda"`` is the current CUDA device, and a device type
    without an index (``"cpu"``) matches any index of that type."""
    from maniskill_torchrl._internal.sim import canonical_device

    actual, wanted = canonical_device(actual), canonical_device(wanted)
    if actual.type != wanted.type:
        return False
    return actual.index is None or wanted.index is None or actual.index == wanted.index


def _off_device(data: Any, device: torch.device, path: tuple, found: list) -> None:
    """Appends ``(path, device)`` for every leaf of ``data`` not on ``device``."""
    if isinstance(data, torch.Tensor):
        if not _same_device(data.device, device):
            found.append((path, data.device))
    elif isinstance(data, TensorDictBase):
        if data.device is not None and not _same_device(data.device, device):
            found.append((path + ("<TensorDict device>",), data.device))
        for key, value in data.items(include_nested=True):
            key = key if isinstance(key, tuple) else (key,)
            if isinstance(value, TensorDictBase):
                if value.device is not None and not _same_device(value.device, device):
                    found.append((path + key + ("<TensorDict device>",), value.device))
            elif isinstance(value, torch.Tensor) and not _same_device(value.device, device):
                found.append((path + key, value.device))
    elif isinstance(data, Mapping):
        for key, value in data.items():
            _off_device(value, device, path + (key,), found)
    elif isinstance(data, (tuple, list)):
        for i, value in enumerate(data):
            _off_device(value, device, path + (i,), found)
    elif isinstance(data, np.ndarray) and torch.device(device).type != "cpu":
        found.append((path, "numpy (host memory)"))


def assert_on_device(data: Any, device: torch.device | str, *, msg: str = "") -> None:
    """Asserts that every leaf of ``data`` is on ``device``.

    ``data`` is a TensorDict, a tensor, a (nested) mapping, or a tuple or list of them (what an
    env's ``reset``, ``step``, ``render`` or a gym ``step`` returns). Every tensor leaf counts,
    nested ones included, and so does the device label of every TensorDict in it (a TensorDict
    said to be on the CPU whose leaves are on CUDA fails on the leaves). Numpy arrays are host
    memory: they fail unless ``device`` is the CPU. Other values (numbers, strings) have no
    device and pass. ``"cuda"`` is the current CUDA device, ``"cuda:0"`` names it too.

    The :class:`AssertionError` lists every offending key path with its device. Use it on every
    output of an env to check TorchRL's rule that outputs are on ``env.device``
    (:func:`check_maniskill_env` does, at every reset and step).

    Args:
        data: what to check.
        device: where every leaf must be.

    Keyword Args:
        msg (str): prefixed to the error message.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from maniskill_torchrl.testing import assert_on_device
        >>> td = TensorDict({"obs": torch.zeros(2, 3), ("next", "reward"): torch.ones(2, 1)}, [2])
        >>> assert_on_device(td, "cpu")
        >>> assert_on_device({"pixels": torch.zeros(2, device="meta"), "t": torch.ones(1)}, "cpu")
        Traceback (most recent call last):
        ...
        AssertionError: 1 leaf not on cpu: 'pixels' on meta
    """
    if not isinstance(data, (torch.Tensor, Mapping, TensorDictBase, tuple, list)):
        raise TypeError(
            "assert_on_device checks a TensorDict, a tensor, a mapping, or a tuple or list of them; "
            f"got a {type(data).__name__}."
        )
    device = torch.device(device)
    found: list = []
    _off_device(data, device, (), found)
    if not found:
        return
    prefix = f"{msg}: " if msg else ""

    def name(path: tuple) -> str:
        if not path:
            return "the tensor"
        return repr(path[0]) if len(path) == 1 and isinstance(path[0], str) else repr(path)

    listed = ", ".join(f"{name(path)} on {where}" for path, where in found[:20])
    more = f", and {len(found) - 20} more" if len(found) > 20 else ""
    leaves = "leaf" if len(found) == 1 else "leaves"
    raise AssertionError(f"{prefix}{len(found)} {leaves} not on {device}: {listed}{more}")
