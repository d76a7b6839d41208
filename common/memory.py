"""Giving freed heap memory back to the operating system.

numpy's temporaries (scan matching, map redraws) come and go in several threads, and
glibc keeps what they freed in per-thread arenas: the resident size of a long-running
process then creeps up with the work done, not with what it holds. `HeapTrimmer`
calls glibc's ``malloc_trim(0)`` at most once per period, which returns every free
page of every arena. Elsewhere (macOS, musl) it does nothing.

`limit_malloc_arenas` caps the arenas themselves (glibc's ``mallopt(M_ARENA_MAX)``),
called before the process starts its threads: fewer arenas, less free memory stranded
in them between trims. `fix_mmap_threshold` pins the size from which malloc maps a
block on its own (``M_MMAP_THRESHOLD``): glibc otherwise raises it to the size of every
mapped block freed (up to 32 MB), after which the base station's per-update arrays over
all keyframes (megabytes late in a mission) come from the heap and their freed pages
stay resident until the next trim.

After every trim it also notes where the process's memory is (`memory_sample`): the
resident size, glibc's heap in use and free (``mallinfo2``, every arena; blocks that
malloc mapped on their own counted apart), SQLite's own heap (``sqlite3_memory_used``:
page caches and statements of every connection, part of the heap in use) and Python's
allocated blocks, with the caller's per-keyframe arrays, its factor count (the base
station: iSAM2's factor slots) and a count from it (the base station: keyframes
admitted), so a soak can tell live data from fragmentation, SQLite and what Python
holds (`HeapTrimmer.series_json`, in basestation.json).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

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


M_ARENA_MAX = -8  # glibc's mallopt parameter


def limit_malloc_arenas(arenas: int) -> bool:
    """At most `arenas` glibc malloc arenas in this process from now on (0: leave glibc's
    default); call it before starting threads. An explicit ``MALLOC_ARENA_MAX`` in the
    environment wins. True if the limit was set."""
    if arenas <= 0 or "MALLOC_ARENA_MAX" in os.environ:
        return False
    return _mallopt(M_ARENA_MAX, arenas)


M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter


def _mallopt(param: int, value: int) -> bool:
    name = ctypes.util.find_library("c")
    try:
        fn = ctypes.CDLL(name).mallopt if name else None
    except (OSError, AttributeError):
        fn = None
    if fn is None:
        return False
    fn.argtypes, fn.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(fn(param, value))


def fix_mmap_threshold(kib: int) -> bool:
    """Blocks of `kib` KiB and more are mapped on their own from now on, and given back
    to the system when freed (0: leave glibc's dynamic threshold). An explicit
    ``MALLOC_MMAP_THRESHOLD_`` in the environment wins. True if the threshold was set."""
    if kib <= 0 or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return False
    return _mallopt(M_MMAP_THRESHOLD, kib * 1024)


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                     "uordblks", "fordblks", "keepcost")
    ]  # fmt: skip


def _mallinfo2() -> Callable[[], _MallInfo2] | None:
    name = ctypes.util.find_library("c")
    try:
        fn = ctypes.CDLL(name).mallinfo2 if name else None  # glibc >= 2.33
    except (OSError, AttributeError):
        return None
    if fn is not None:
        fn.argtypes, fn.restype = [], _MallInfo2
    return fn


def _sqlite_memory_used() -> Callable[[], int] | None:
    """SQLite's heap in use, every connection of this process (``sqlite3_memory_used``
    of the library Python's sqlite3 module uses); None where it cannot be reached."""
    try:
        import _sqlite3

        fn = ctypes.CDLL(_sqlite3.__file__).sqlite3_memory_used
    except (ImportError, OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = [], ctypes.c_int64
    return fn


_MALLINFO2 = _mallinfo2()
_SQLITE_MEMORY_USED = _sqlite_memory_used()
MEMORY_COLUMNS = [
    "t_s", "rss_mb", "rss_anon_mb", "heap_in_use_mb", "heap_free_mb", "malloc_mmap_mb", "sqlite_mb",
    "py_blocks_k", "arrays_mb", "factors", "count",
]  # fmt: skip


def memory_sample() -> list[float]:
    """[rss_mb, rss_anon_mb, heap_in_use_mb, heap_free_mb, malloc_mmap_mb, sqlite_mb,
    py_blocks_k] of this process now (rss_anon_mb: the resident pages not backed by a
    file, which the kernel cannot drop; the heap columns NaN without glibc's mallinfo2,
    sqlite_mb without a reachable SQLite library)."""
    try:
        with open("/proc/self/statm") as f:
            resident, shared = (int(v) for v in f.read().split()[1:3])  # shared: file-backed
        mb = os.sysconf("SC_PAGE_SIZE") / 2**20
        rss, anon = resident * mb, (resident - shared) * mb
    except OSError:
        rss = anon = float("nan")
    heap = [float("nan")] * 3
    if _MALLINFO2 is not None:
        m = _MALLINFO2()
        heap = [m.uordblks / 2**20, m.fordblks / 2**20, m.hblkhd / 2**20]
    sqlite = float("nan") if _SQLITE_MEMORY_USED is None else _SQLITE_MEMORY_USED() / 2**20
    return [rss, anon, *heap, sqlite, sys.getallocatedblocks() / 1000.0]


class HeapTrimmer:
    def __init__(
        self,
        count: Callable[[], int] | None = None,
        arrays: Sequence[Callable[[], int]] = (),
        factors: Callable[[], int] | None = None,
        period_s: float = TRIM_PERIOD_S,
    ) -> None:
        """`count`: the caller's count for each row (the base station: keyframes admitted);
        `arrays`: the bytes each of its per-keyframe arrays holds (capacity, not just the
        rows used; summed);
        `factors`: the size of its factor graph (the base station: iSAM2's factor slots)."""
        self.period_s = period_s
        self._trim = _malloc_trim()
        self._last = time.monotonic()
        self.trims = 0
        self._t0 = self._last
        self._t0_unix = time.time()
        self._count = count
        self._arrays = arrays
        self._factors = factors
        self.series: list[list[float]] = []  # a MEMORY_COLUMNS row after every trim
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
        count = float(self._count()) if self._count is not None else float("nan")
        arrays = sum(f() for f in self._arrays) / 2**20 if self._arrays else float("nan")
        factors = float(self._factors()) if self._factors is not None else float("nan")
        row = [self._last - self._t0, *memory_sample(), arrays, factors, count]
        self.series.append([round(v, 3) for v in row])
        return True

    def series_json(self) -> dict[str, Any]:
        """{"t0_unix", "columns", "rows"}: the samples, t_s in wall seconds since t0_unix
        (NaN, where a column is unknown, as null)."""
        rows = [[None if v != v else v for v in r] for r in self.series]
        return {"t0_unix": self._t0_unix, "columns": MEMORY_COLUMNS, "rows": rows}
