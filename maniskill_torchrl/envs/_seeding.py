"""The seeds of a wrapper's resets: reproducible runs from one ``set_seed(s)``.

No TorchRL import: numpy's ``RandomState`` only.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ResetSeeds"]


class ResetSeeds:
    """After :meth:`set` ``(s)``, :meth:`draw` gives ``s``, then the draws of
    ``numpy.random.RandomState(s)`` (``randint(2**31)``); ``None`` until seeded or after ``set(None)``."""

    def __init__(self) -> None:
        self._rng: np.random.RandomState | None = None
        self._next: int | None = None

    def set(self, seed: int | None) -> None:
        if seed is None:
            self._rng = self._next = None
            return
        seed = int(seed)
        self._next = seed
        self._rng = np.random.RandomState(seed % 2**32)

    def draw(self) -> int | None:
        if self._rng is None:
            return None
        if self._next is not None:
            seed, self._next = self._next, None
            return seed
        return int(self._rng.randint(2**31))
