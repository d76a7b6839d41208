"""HeapTrimmer: freed heap memory goes back to the operating system."""

from __future__ import annotations

import os
import sqlite3
import time

from common.memory import HeapTrimmer


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_trim_returns_freed_heap_pages() -> None:
    # 64 kB blocks come from the heap (below glibc's mmap threshold); the last one
    # stays, so the heap's top cannot shrink by itself and only a trim gives pages back
    blocks = [bytearray(64 * 1024) for _ in range(3000)]  # ~190 MB, touched (zeroed)
    keep = blocks[-1]
    del blocks
    held = _rss_mb()
    trimmer = HeapTrimmer(period_s=0.0)
    assert trimmer.maybe_trim() and trimmer.trims == 1
    assert _rss_mb() < held - 100, (held, _rss_mb())
    assert len(keep) == 64 * 1024


def test_trim_at_most_once_per_period() -> None:
    trimmer = HeapTrimmer(period_s=3600.0)
    assert not trimmer.maybe_trim()  # the period starts when it is made
    trimmer._last = time.monotonic() - 3601.0
    assert trimmer.maybe_trim() and not trimmer.maybe_trim()
    assert trimmer.trims == 1


def test_trim_now_restarts_the_period() -> None:
    trimmer = HeapTrimmer(period_s=3600.0)
    assert trimmer.trim() and trimmer.trims == 1  # whatever the period
    trimmer._last -= 3599.0
    assert not trimmer.maybe_trim()  # the forced trim started a new period


def test_each_trim_notes_where_the_memory_is() -> None:
    n = [0]
    trimmer = HeapTrimmer(
        count=lambda: n[0], arrays=[lambda: 2**20, lambda: 2 * 2**20], factors=lambda: 12,
        period_s=3600.0,
    )  # fmt: skip
    assert trimmer.series_json()["rows"] == []
    n[0] = 7
    held = [bytearray(64 * 1024) for _ in range(200)]  # ~13 MB in glibc's heap
    db = sqlite3.connect(":memory:")  # SQLite's page cache: its own heap, counted apart
    db.execute("CREATE TABLE t (x BLOB)")
    db.executemany("INSERT INTO t VALUES (?)", [(bytes(1000),)] * 1000)
    assert trimmer.trim()
    cols = trimmer.series_json()["columns"]
    row = dict(zip(cols, trimmer.series_json()["rows"][-1], strict=True))
    assert row["count"] == 7 and row["t_s"] >= 0.0 and row["arrays_mb"] == 3.0
    assert row["factors"] == 12
    assert row["rss_mb"] > 13.0 and row["py_blocks_k"] > 0.0
    assert row["heap_in_use_mb"] > 12.0, row  # glibc (Linux): the blocks just made
    assert 0.9 < row["sqlite_mb"] < row["heap_in_use_mb"], row  # 1000 rows of 1 kB
    del held
    assert trimmer.trim()
    after = dict(zip(cols, trimmer.series_json()["rows"][-1], strict=True))
    assert after["heap_in_use_mb"] < row["heap_in_use_mb"] - 12.0, (row, after)


_ARENAS_SCRIPT = """
import ctypes, ctypes.util, sys, threading
from common.memory import limit_malloc_arenas
limited = limit_malloc_arenas(int(sys.argv[1]))
barrier = threading.Barrier(4)
held = []
def work():
    barrier.wait()  # all four threads allocate at once
    held.append([bytearray(64 * 1024) for _ in range(20)])
threads = [threading.Thread(target=work) for _ in range(4)]
for t in threads: t.start()
for t in threads: t.join()
ctypes.CDLL(ctypes.util.find_library("c")).malloc_stats()  # one "Arena n:" per arena
print(limited, flush=True)
"""


def _arenas(limit: int, env: dict[str, str] | None = None) -> tuple[bool, int]:
    """(limit set?, arenas in use) of a fresh process whose 4 threads allocate at once."""
    import subprocess
    import sys

    base = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    run = subprocess.run(
        [sys.executable, "-c", _ARENAS_SCRIPT, str(limit)],
        capture_output=True, text=True, check=True, env={**base, **(env or {})},
    )  # fmt: skip
    return run.stdout.strip() == "True", run.stderr.count("Arena ")


def test_malloc_arenas_are_capped_before_threads_start() -> None:
    assert _arenas(1) == (True, 1)
    limited, default = _arenas(0)
    assert not limited and default > 1  # glibc gives each new thread its own arena
    # an explicit MALLOC_ARENA_MAX wins (the limit is not set)
    assert _arenas(1, {"MALLOC_ARENA_MAX": "3"})[0] is False


_MMAP_SCRIPT = """
import ctypes, sys
import numpy as np
from common.memory import _MALLINFO2, fix_mmap_threshold
fixed = fix_mmap_threshold(int(sys.argv[1]))
big = np.ones(4 * 2**20 // 8); del big  # a mapped 4 MB block freed: glibc raises its threshold
before = _MALLINFO2().hblks
held = np.ones(2**20 // 8)  # 1 MB: mapped on its own only below the threshold
print(fixed, _MALLINFO2().hblks - before, flush=True)
"""


def _mapped_blocks(kib: int, env: dict[str, str] | None = None) -> tuple[bool, int]:
    """(threshold set?, blocks malloc mapped on its own for a 1 MB array made after a
    4 MB one was freed), in a fresh process."""
    import subprocess
    import sys

    base = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_MMAP")}
    run = subprocess.run(
        [sys.executable, "-c", _MMAP_SCRIPT, str(kib)],
        capture_output=True, text=True, check=True, env={**base, **(env or {})},
    )  # fmt: skip
    fixed, blocks = run.stdout.split()
    return fixed == "True", int(blocks)


def test_mmap_threshold_stays_where_it_was_fixed() -> None:
    fixed, blocks = _mapped_blocks(256)
    assert fixed and blocks == 1  # the 1 MB block is mapped (given back when freed)
    fixed, blocks = _mapped_blocks(0)
    assert not fixed and blocks == 0  # glibc's threshold rose to 4 MB: the heap took it
    assert _mapped_blocks(256, {"MALLOC_MMAP_THRESHOLD_": "131072"})[0] is False
