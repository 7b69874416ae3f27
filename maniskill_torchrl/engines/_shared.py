"""The shared-memory block of :class:`~maniskill_torchrl.CPUVectorEnv`: every sub-env's step
results and actions, ``[N, ...]`` per leaf, in one segment that every process maps.

A worker (and sub-env 0, in the parent) writes its step into its own row of each result leaf;
the parent writes the whole batch of actions before it wakes the workers, and reads the whole
batch of results with one copy. Nothing is pickled and nothing is concatenated per step.

The layout is a flat list of leaves, each ``[N, *shape]`` C-contiguous at an offset aligned to
64 bytes, so that each leaf is a view of the block with its own dtype. Results come first, then
actions. A split-phase block (``autoreset=True``) has ``2N`` result rows, row ``N + i`` for the
reset that sub-env ``i`` ran after its episode ended, and one int64 reset seed per sub-env after
the actions. Only numpy, torch, gymnasium's spaces and the standard library: the workers load it.
"""

from __future__ import annotations

from multiprocessing import shared_memory
from typing import Any

import gymnasium as gym
import numpy as np
import torch

__all__ = ["Layout", "SharedBlock"]

_ALIGN = 64


def _leaves(space: gym.Space, path: tuple = ()) -> list[tuple[tuple, np.dtype, tuple]]:
    """(path, dtype, shape) of every Box of a (nested) Dict space, in the space's key order."""
    if isinstance(space, gym.spaces.Dict):
        return [leaf for key, sub in space.spaces.items() for leaf in _leaves(sub, (*path, key))]
    if not isinstance(space, gym.spaces.Box):
        raise TypeError(f"CPUVectorEnv: a {type(space).__name__} space at {path} has no fixed-size layout.")
    return [(path, np.dtype(space.dtype), tuple(space.shape))]


def _torch_dtype(dtype: np.dtype) -> torch.dtype:
    return torch.from_numpy(np.zeros((), dtype)).dtype


def _nest(paths: list[tuple], values: list) -> Any:
    """Nested dicts from (path, value) pairs; a single leaf at path ``()`` is the value itself."""
    if len(paths) == 1 and paths[0] == ():
        return values[0]
    tree: dict = {}
    for path, value in zip(paths, values):
        node = tree
        for key in path[:-1]:
            node = node.setdefault(key, {})
        node[path[-1]] = value
    return tree


def _flatten(tree: Any, paths: list[tuple]) -> list:
    """The values at ``paths`` of a tree of nested dicts (or the value itself at ``()``)."""
    out = []
    for path in paths:
        node = tree
        for key in path:
            node = node[key]
        out.append(node)
    return out


class Layout:
    """Where each leaf of the results (``result_space``: one sub-env's step) and of the actions
    (``action_space``: one sub-env's action) lies in a block for ``num_envs`` sub-envs. Picklable:
    the parent sends it to every worker."""

    def __init__(
        self, result_space: gym.Space, action_space: gym.Space, num_envs: int, autoreset: bool = False
    ) -> None:
        self.num_envs = int(num_envs)
        self.autoreset = bool(autoreset)
        #: rows of each result leaf: one per sub-env, and one more for its reset with ``autoreset``
        self.result_rows = 2 * self.num_envs if self.autoreset else self.num_envs
        offset = 0
        self.results, self.actions = [], []
        for part, space, rows in (
            (self.results, result_space, self.result_rows),
            (self.actions, action_space, self.num_envs),
        ):
            for path, dtype, shape in _leaves(space):
                offset = -(-offset // _ALIGN) * _ALIGN
                size = rows * int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
                part.append((path, dtype, shape, offset, size, _torch_dtype(dtype), rows))
                offset += size
            if part is self.results:
                self.result_bytes = offset  # what the parent copies per lockstep step
        self.seeds_offset = None
        if self.autoreset:
            self.seeds_offset = -(-offset // _ALIGN) * _ALIGN
            offset = self.seeds_offset + 8 * self.num_envs
        self.nbytes = max(offset, 1)
        self.result_paths = [leaf[0] for leaf in self.results]
        self.action_paths = [leaf[0] for leaf in self.actions]

    def arrays(self, buf: Any, part: list) -> list[np.ndarray]:
        """``[N, *shape]`` numpy views of ``part``'s leaves over ``buf``."""
        return [
            np.ndarray((rows, *shape), dtype, buffer=buf, offset=offset) for _, dtype, shape, offset, _, _, rows in part
        ]

    def read(self, block: torch.Tensor) -> Any:
        """The results as a tree of ``[N, ...]`` torch tensors: views of one fresh copy of the
        block's result bytes (``block``: a uint8 tensor over the whole segment)."""
        fresh = block[: self.result_bytes].clone()
        values = [
            fresh[offset : offset + size].view(dtype).view(rows, *shape)[: self.num_envs]
            for _, _, shape, offset, size, dtype, rows in self.results
        ]
        return _nest(self.result_paths, values)


class SharedBlock:
    """One shared-memory segment laid out by a :class:`Layout`: made by the parent
    (``name=None``), attached by name in a worker. ``results`` and ``actions`` are flat lists of
    ``[N, ...]`` numpy views, in the layout's leaf order."""

    def __init__(self, layout: Layout, name: str | None = None) -> None:
        self.layout = layout
        self._owner = name is None
        self._shm = shared_memory.SharedMemory(name=name, create=self._owner, size=layout.nbytes)
        self.results = layout.arrays(self._shm.buf, layout.results)
        self.actions = layout.arrays(self._shm.buf, layout.actions)
        #: split-phase blocks: the seed of each sub-env's next reset after an episode's end (-1: none)
        self.seeds = None
        if layout.seeds_offset is not None:
            self.seeds = np.ndarray((layout.num_envs,), np.int64, buffer=self._shm.buf, offset=layout.seeds_offset)
        if self._owner:
            self.tensor = torch.frombuffer(self._shm.buf, dtype=torch.uint8)
            self.tensor.zero_()

    @property
    def name(self) -> str:
        return self._shm.name

    def write_actions(self, action: Any) -> None:
        """The batch's ``[N, ...]`` actions (numpy, or a dict of them) into the block."""
        for path, dst, src in zip(self.layout.action_paths, self.actions, _flatten(action, self.layout.action_paths)):
            if src.shape != dst.shape:  # numpy would broadcast a [1, ...] action to every sub-env
                where = f" {'/'.join(path)!r}" if path else ""
                raise ValueError(f"CPUVectorEnv: action{where} of shape {tuple(src.shape)}, expected {dst.shape}.")
            dst[...] = src

    def write_action_rows(self, rows: np.ndarray, action: Any) -> None:
        """The ``[k, ...]`` actions (numpy, or a dict of them) of the sub-envs ``rows`` into the block."""
        for path, dst, src in zip(self.layout.action_paths, self.actions, _flatten(action, self.layout.action_paths)):
            if src.shape != (len(rows), *dst.shape[1:]):
                where = f" {'/'.join(path)!r}" if path else ""
                raise ValueError(
                    f"CPUVectorEnv: action{where} of shape {tuple(src.shape)} for {len(rows)} sub-envs, expected "
                    f"{(len(rows), *dst.shape[1:])}."
                )
            dst[rows] = src

    def read_rows(self, rows: np.ndarray) -> Any:
        """The results of the rows ``rows`` as a tree of ``[k, ...]`` torch tensors (copies)."""
        return _nest(self.layout.result_paths, [torch.from_numpy(a[rows]) for a in self.results])

    def views(self, start: int, stop: int) -> Any:
        """The result rows ``start:stop`` as a tree of torch tensors that are views of the block (no
        copy: they change with the block)."""
        return _nest(self.layout.result_paths, [torch.from_numpy(a[start:stop]) for a in self.results])

    def action_row(self, index: int) -> Any:
        """Sub-env ``index``'s action: copies (the block is rewritten at the next step)."""
        return _nest(self.layout.action_paths, [a[index].copy() for a in self.actions])

    def write_row(self, index: int, result: Any) -> None:
        """Sub-env ``index``'s unbatched results (a tree as the layout's result space) into its row,
        cast to the leaves' dtypes."""
        for dst, src in zip(self.results, _flatten(result, self.layout.result_paths)):
            dst[index] = src

    def read(self) -> Any:
        """The whole batch's results, one copy (parent only)."""
        return self.layout.read(self.tensor)

    def close(self) -> None:
        self.results = self.actions = None
        self.tensor = None
        try:
            self._shm.close()
        except BufferError:  # a view still alive somewhere: the mapping goes with the process
            pass
        if self._owner:
            self._shm.unlink()
