"""Rows of numbers recorded for the whole of a run, kept on disk instead of in memory.

An agent records a row at every control tick (40 Hz: its local trajectory and its
control poses) for the files it writes when it stops, the simulator each robot's
ground truth (10 Hz). Kept in memory, a row costs
~250 bytes with Python's and numpy's object headers: ~1.3 MB a minute that a drone's
process never gives back. `RowSpool` appends each row's float64 bytes to an unnamed
temporary file (buffered, deleted by the operating system when the process ends) and
reads them all back once, for writing (`rows`). What the process holds stays flat;
the file grows by 8 bytes per number (~30 MB an hour for a control log).
"""

from __future__ import annotations

import os
import tempfile
import weakref

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import ConfigError


class RowSpool:
    """Rows of `columns` float64 numbers appended one at a time, stored in a temporary
    file."""

    def __init__(self, columns: int) -> None:
        if columns < 1:
            raise ConfigError(f"a row spool needs >= 1 column, got {columns}")
        self.columns = int(columns)
        self._file = tempfile.TemporaryFile(prefix="collabslam-rows-")
        self._close = weakref.finalize(self, self._file.close)  # closed with the spool
        self._n = 0

    def append(self, row: ArrayLike) -> None:
        r = np.asarray(row, dtype=np.float64).reshape(-1)
        if len(r) != self.columns:
            raise ValueError(f"expected a row of {self.columns} numbers, got {len(r)}")
        self._file.write(r.tobytes())
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def rows(self) -> NDArray[np.float64]:
        """Every row so far, (n, columns), read back from the file."""
        out = np.empty((self._n, self.columns), dtype=np.float64)
        if self._n == 0:
            return out
        self._file.flush()
        view, done = memoryview(out).cast("B"), 0
        while done < len(view):  # a read may return less than asked for (> 2 GB)
            chunk = os.preadv(self._file.fileno(), [view[done:]], done)
            if chunk <= 0:
                raise OSError(f"row spool: file ended after {done} of {len(view)} bytes")
            done += chunk
        return out

    def close(self) -> None:
        """Delete the file (the rows are gone); also done when the spool is collected."""
        self._close()
