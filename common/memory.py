"""Giving freed heap memory back to the operating system.

numpy's temporaries (scan matching, map redraws) come and go in several threads, and
glibc keeps what they freed in per-thread arenas: the resident size of a long-running
process then creeps up with the work done, not with what it holds. `HeapTrimmer`
calls glibc's ``malloc_trim(0)`` at most once per period, which returns every free
page of every arena. Elsewhere (macOS, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import time

log = logging.getLogger(__name__)

TRIM_PERIOD_S = 10.0  # wall time between two trims (one takes ~1-20 ms)


def _malloc_trim() -> ctypes._CFuncPtr | None:  # type: ignore[name-defined]
    name = ctypes.util.find_library("c")
    try:
        fn = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        fn = None
    if fn is not None:
        fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


class HeapTrimmer:
    def __init__(self, period_s: float = TRIM_PERIOD_S) -> None:
        self.period_s = period_s
        self._trim = _malloc_trim()
        self._last = time.monotonic()
        self.trims = 0
        if self._trim is None:
            log.debug("no malloc_trim here: freed heap memory stays with the process")

    def maybe_trim(self) -> bool:
        """Trim if the period has passed since the last trim; True if it trimmed."""
        if time.monotonic() - self._last < self.period_s:
            return False
        return self.trim()

    def trim(self) -> bool:
        """Trim now (e.g. between the chunks of a long burst of work); True if it did."""
        if self._trim is None:
            return False
        self._last = time.monotonic()
        self._trim(0)
        self.trims += 1
        return True
