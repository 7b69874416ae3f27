"""One host-to-device copy per step for the tensors of a nested dict: what a CPU-sim env feeding
an accelerator moves up (:class:`~maniskill_torchrl.ManiSkillEnv` with ``device="cuda"``), and the
episode sums that :class:`~maniskill_torchrl.transforms.EpisodeMetrics` makes on the host."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

__all__ = ["HostGather"]

# Bytes: the buffer's size is a multiple of it.
ALIGN = 16


class HostGather:
    """Moves the tensors of a nested dict onto ``device`` with one host-to-device copy.

    Host tensors are written into one reused host buffer (pinned on CUDA), which is
    copied whole, without blocking; the device leaves are views of that fresh copy,
    so nothing handed out is written again. ``TensorDict.to`` would copy leaf by
    leaf, and its consolidated form allocates a host buffer per call. Tensors
    already on an accelerator (``sapien_cuda`` pictures) are copied on the device.
    Two buffers are taken in turn, each behind an event, so that a copy still
    reading one is never overwritten. The layout is learnt from the first calls and
    grows when new leaves appear.
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
        pending: list[tuple[dict, Any, tuple, torch.Tensor]] = []
        out = self._walk(source, (), pending)
        if not pending:
            return out
        for _, _, path, value in pending:
            slot = self._slots.get(path)
            if slot is None or slot[0] != value.dtype or slot[1] != value.shape:
                self._grow(pending)
                break
        slots = self._slots
        buf, views, event = self._buffers[self._turn]
        self._turn ^= 1
        if event is not None:
            event.synchronize()  # the copy out of this buffer two calls ago
        for _, _, path, value in pending:
            views[path].copy_(value)
        moved = buf.to(self.device, non_blocking=self._pin, copy=True)
        if event is not None:
            event.record()
        typed = {dtype: moved.view(dtype) for dtype in self._dtypes}
        pairs = []
        for container, key, path, _ in pending:
            dtype, shape, stride, offset = slots[path]
            container[key] = leaf = typed[dtype].as_strided(shape, stride, offset)
            pairs.append((leaf, views[path]))
        self._pairs = pairs
        return out

    def host_value(self, tensor: torch.Tensor) -> torch.Tensor | None:
        """The host values of ``tensor``, a leaf of the last call, else None."""
        for leaf, host in self._pairs:
            if leaf is tensor:
                return host
        return None

    def _walk(self, source: Mapping, prefix: tuple, pending: list) -> dict:
        out = {}
        for key, value in source.items():
            if isinstance(value, torch.Tensor):
                if value.device.type == "cpu":
                    out[key] = None
                    pending.append((out, key, (*prefix, key), value))
                else:
                    out[key] = value.to(self.device, copy=True)
            elif isinstance(value, Mapping):
                out[key] = self._walk(value, (*prefix, key), pending)
            else:
                out[key] = value
        return out

    def _grow(self, pending: list) -> None:
        for _, _, event in self._buffers:
            if event is not None:
                event.synchronize()  # a copy may still read the old buffers
        leaves = {path: (d, s) for path, (d, s, _, _) in self._slots.items()}
        leaves.update({path: (v.dtype, v.shape) for _, _, path, v in pending})
        # Widest dtypes first: every leaf starts at a multiple of its element size.
        slots, offset = {}, 0
        for path in sorted(leaves, key=lambda p: -leaves[p][0].itemsize):
            dtype, shape = leaves[path]
            stride = contiguous_strides(shape)
            slots[path] = (dtype, shape, stride, offset // dtype.itemsize)
            offset += shape.numel() * dtype.itemsize
        self._slots = slots
        self._dtypes = tuple(dict.fromkeys(d for d, _ in leaves.values()))
        size = max(-(-offset // ALIGN) * ALIGN, ALIGN)
        self._buffers = []
        for _ in range(2):
            buf = torch.empty(size, dtype=torch.uint8, pin_memory=self._pin)
            typed = {d: buf.view(d) for d in self._dtypes}
            views = {path: typed[d].as_strided(shape, stride, off) for path, (d, shape, stride, off) in slots.items()}
            event = self._event_type() if self._event_type is not None else None
            self._buffers.append((buf, views, event))
        self._turn = 0


def contiguous_strides(shape: torch.Size) -> tuple[int, ...]:
    strides, step = [], 1
    for n in reversed(shape):
        strides.append(step)
        step *= max(n, 1)
    return tuple(reversed(strides))
