"""Growable arrays for per-keyframe numbers (no Python object per keyframe).

Capacity grows by a quarter (`grown_capacity`), not by doubling: at most a fifth of
an array is unused, and a long mission's memory rises with its keyframes instead of
in doubling steps (a 10-robot soak's per-robot arrays doubling at 8,192 keyframes
each added ~10 MB at once).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

GROWTH = 1.25  # new capacity / old when an array is full
MIN_CAPACITY = 64


def grown_capacity(capacity: int, needed: int) -> int:
    """The capacity to grow to when `needed` rows do not fit in `capacity`."""
    return max(needed, int(capacity * GROWTH), MIN_CAPACITY)


def grown(a: np.ndarray, needed: int, fill: float = 0) -> np.ndarray:
    """`a` (rows along axis 0) with room for `needed` rows, new rows set to `fill`;
    `a` itself when it has room."""
    if needed <= len(a):
        return a
    out = np.full((grown_capacity(len(a), needed), *a.shape[1:]), fill, dtype=a.dtype)
    out[: len(a)] = a
    return out


class Rows:
    """A growable (n, k) array: rows appended one at a time."""

    def __init__(self, k: int, dtype: type = np.float64) -> None:
        self._a = np.zeros((0, k), dtype)
        self._n = 0

    def append(self, row: ArrayLike) -> None:
        self._a = grown(self._a, self._n + 1)
        self._a[self._n] = row
        self._n += 1

    def drop(self, i: int) -> None:
        """Remove row `i` (the rows after it move up one)."""
        self._a[i : self._n - 1] = self._a[i + 1 : self._n]
        self._n -= 1

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):  # noqa: ANN001, ANN204 (numpy indexing)
        return self.view()[i]

    @property
    def nbytes(self) -> int:
        """Bytes held (the capacity, not just the rows used)."""
        return self._a.nbytes

    def view(self) -> np.ndarray:
        """The rows so far (a view: valid until the next append)."""
        return self._a[: self._n]
