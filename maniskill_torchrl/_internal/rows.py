"""Rows of a TensorDict layout kept as one numpy array per leaf (the asynchronous pool's sent rows).

An indexed write or read of ``k`` rows is one numpy assignment or gather per leaf, without
TensorDict's per-call work (key checks, batch-size arithmetic, nested indexing): on the pool's
critical path that work cost more than the copies.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from maniskill_torchrl._private import new_tensordict

__all__ = ["RowStore"]


class RowStore:
    """``num_rows`` rows laid out as ``example`` (a ``[k]`` TensorDict of CPU tensors), zeros at first.

    :meth:`write` takes a TensorDict with exactly these leaves; :meth:`fits` says whether one has
    them. :meth:`read` gives fresh ``[k]`` TensorDicts (copies).
    """

    def __init__(self, example: TensorDictBase, num_rows: int) -> None:
        self.keys = list(example.keys(True, True))
        self.paths = [(key,) if isinstance(key, str) else tuple(key) for key in self.keys]
        self._leaves = frozenset(self.keys)
        self._top = frozenset(example.keys()) if all(isinstance(k, str) for k in self.keys) else None
        self.arrays = [
            np.zeros((num_rows, *value.shape[1:]), dtype=value.numpy().dtype)
            for value in (example.get(key).detach() for key in self.keys)
        ]

    @staticmethod
    def supports(example: TensorDictBase) -> bool:
        """Whether every leaf of ``example`` is a CPU tensor (what numpy can hold)."""
        return all(type(value) is torch.Tensor and value.device.type == "cpu" for value in example.values(True, True))

    def array(self, key: Any) -> np.ndarray | None:
        """The rows of leaf ``key``, or None if there is no such leaf."""
        try:
            return self.arrays[self.keys.index(key)]
        except ValueError:
            return None

    def fits(self, tensordict: TensorDictBase) -> bool:
        if self._top is not None:  # no nested entries: the top-level names say it (a tenth of the cost)
            return frozenset(tensordict.keys()) == self._top
        return frozenset(tensordict.keys(True, True)) == self._leaves

    def write(self, rows: np.ndarray, tensordict: TensorDictBase, same: dict | None = None) -> None:
        """``tensordict``'s rows into ``rows``. ``same``: nested dicts of fresh tensors whose values
        these rows hold already: a leaf that is still one of them, unedited (its version counter
        untouched by an in-place write), is skipped."""
        for key, path, array in zip(self.keys, self.paths, self.arrays):
            value = tensordict.get(key)
            if same is not None:
                node = same
                for name in path:
                    node = node.get(name) if isinstance(node, dict) else None
                if node is value and value._version == 0:
                    continue
            array[rows] = value.detach().numpy()

    def read(self, rows: np.ndarray) -> TensorDict:
        tree: dict[str, Any] = {}
        for path, array in zip(self.paths, self.arrays):
            node = tree
            for name in path[:-1]:
                node = node.setdefault(name, {})
            node[path[-1]] = torch.from_numpy(array[rows])
        return new_tensordict(tree, batch_size=torch.Size([len(rows)]))
