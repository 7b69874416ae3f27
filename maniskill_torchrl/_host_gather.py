"""One transfer per step from the host to an accelerator: a step's host tensors gathered into one
reused host buffer (pinned on CUDA), moved with one non-blocking copy, handed out as views of the
copy on the device.

:class:`HostGather` is what :class:`~maniskill_torchrl.ManiSkillWrapper` does with a CPU-sim
step's outputs when ``env.device`` is an accelerator (``device="cuda"``), and what
:class:`~maniskill_torchrl.transforms.EpisodeMetrics` does with its statistics summed on the host.
Without it each leaf is its own blocking copy from pageable memory (9 at batch 1 for state
observations, 17 for rgb).

Why a flat byte buffer with typed views, not ``TensorDict(...).to(device, non_blocking=True)``:
TensorDict's ``to`` copies leaf by leaf (one transfer each), and its consolidated form allocates
a new host buffer per call. The byte buffer is laid out once (leaves grouped by dtype, each at a
multiple of its element size), written with plain host copies (``copy_`` casts and handles
strides) and sent whole; the device leaves are one typed view per dtype and one strided view per
leaf of that one copy.
Every device leaf handed out is a view of that step's own fresh device copy, never of a buffer
written again later: a rollout the user keeps stays as it was.

The host buffer is rewritten at the step after next (two buffers, taken in turn). The copy out of
it may still be running then, so an event is recorded on the current stream after each copy and
waited for before its buffer is written again (in practice long done: the wait costs a query).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

__all__ = ["HostGather"]

_ALIGN = 16


class HostGather:
    """Moves the tensors of a nested dict onto ``device`` with one host-to-device transfer.

    Host tensors go through the buffer; tensors already on an accelerator (``sapien_cuda``
    pictures) are copied there (device to device, never through the host); other values pass
    as they are. The layout is learnt from the first calls and grows when new leaves appear
    (a step's reward after a reset's observation): the buffers are made again then, not per call.
    Leaves are grouped by dtype, so that each call takes one typed view of the copy per dtype
    and one strided view per leaf.

    Args:
        device: the accelerator the outputs go to.
    """

    def __init__(self, device: torch.device) -> None:
        self.device = torch.device(device)
        self._pin = self.device.type == "cuda"
        module = torch.get_device_module(self.device) if self.device.type != "cpu" else None
        self._event_type = getattr(module, "Event", None)
        # path -> (dtype, shape, stride, offset in elements of dtype)
        self._slots: dict[tuple, tuple[torch.dtype, torch.Size, tuple, int]] = {}
        self._dtypes: tuple[torch.dtype, ...] = ()
        self._buffers: list[tuple[torch.Tensor, dict, Any]] = []
        self._turn = 0
        self._pairs: list[tuple[torch.Tensor, torch.Tensor]] = []

    def __call__(self, source: Mapping) -> dict:
        """``source`` with every tensor leaf on ``device`` (a new dict; ``source`` is not changed)."""
        pending: list[tuple[dict, Any, tuple, torch.Tensor]] = []
        out = self._walk(source, (), pending)
        if not pending:
            return out
        slots = self._slots
        for _, _, path, value in pending:
            slot = slots.get(path)
            if slot is None or slot[0] != value.dtype or slot[1] != value.shape:
                self._grow(pending)
                slots = self._slots
                break
        buf, views, event = self._buffers[self._turn]
        self._turn ^= 1
        if event is not None:
            event.synchronize()  # the copy out of this buffer two calls ago has ended
        for _, _, path, value in pending:
            views[path].copy_(value)
        moved = buf.to(self.device, non_blocking=self._pin, copy=True)
        if event is not None:
            event.record()
        typed = {dtype: moved.view(dtype) for dtype in self._dtypes}
        pairs = []
        for container, key, path, _ in pending:
            dtype, shape, stride, offset = slots[path]
            leaf = typed[dtype].as_strided(shape, stride, offset)
            container[key] = leaf
            pairs.append((leaf, views[path]))
        self._pairs = pairs
        return out

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        """The host values of ``tensor`` if it is a leaf of the last call that came from the host
        (else None): read them before the next call, which may rewrite them."""
        for leaf, host in self._pairs:
            if leaf is tensor:
                return host
        return None

    def _walk(self, source: Mapping, prefix: tuple, pending: list) -> dict:
        out = {}
        device = self.device
        for key, value in source.items():
            if isinstance(value, torch.Tensor):
                if value.device.type == "cpu":
                    out[key] = None
                    pending.append((out, key, (*prefix, key), value))
                else:
                    out[key] = value.to(device, copy=True)
            elif isinstance(value, Mapping):
                out[key] = self._walk(value, (*prefix, key), pending)
            else:
                out[key] = value
        return out

    def _grow(self, pending: list) -> None:
        """Lays out the leaves of ``pending`` (beside those already laid out) and makes the buffers."""
        for _, _, event in self._buffers:
            if event is not None:
                event.synchronize()  # a copy may still read the old buffers
        leaves = {path: (dtype, shape) for path, (dtype, shape, _, _) in self._slots.items()}
        leaves.update({path: (value.dtype, value.shape) for _, _, path, value in pending})
        # Widest dtypes first: every leaf starts at a multiple of its element size.
        order = sorted(leaves, key=lambda path: -leaves[path][0].itemsize)
        slots, offset = {}, 0
        for path in order:
            dtype, shape = leaves[path]
            slots[path] = (dtype, shape, _contiguous_strides(shape), offset // dtype.itemsize)
            offset += shape.numel() * dtype.itemsize
        self._slots = slots
        self._dtypes = tuple(dict.fromkeys(dtype for dtype, _ in leaves.values()))
        size = max(-(-offset // _ALIGN) * _ALIGN, _ALIGN)  # a whole number of every element size
        self._buffers = []
        for _ in range(2):
            buf = torch.empty(size, dtype=torch.uint8, pin_memory=self._pin)
            typed = {dtype: buf.view(dtype) for dtype in self._dtypes}
            views = {path: typed[d].as_strided(shape, stride, off) for path, (d, shape, stride, off) in slots.items()}
            event = self._event_type() if self._event_type is not None else None
            self._buffers.append((buf, views, event))
        self._turn = 0


def _contiguous_strides(shape: torch.Size) -> tuple[int, ...]:
    strides, step = [], 1
    for n in reversed(shape):
        strides.append(step)
        step *= max(n, 1)
    return tuple(reversed(strides))
