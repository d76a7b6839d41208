"""Helpers for the tests that run real base-station processes with a SQLite record."""

from __future__ import annotations

import sqlite3
import time
from collections.abc import Callable
from pathlib import Path

from collabslam.supervisor import Child, ProcessGroup


def stored_keyframes(db: Path) -> int:
    """Keyframes in a base station's database (read-only; 0 while it does not exist)."""
    try:
        with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5) as con:
            return int(con.execute("SELECT count(*) FROM keyframes").fetchone()[0])
    except sqlite3.Error:
        return 0


def wait_for(
    pred: Callable[[], bool], timeout: float, what: str, group: ProcessGroup, running: list[Child]
) -> None:
    """Poll `pred` until true; fail on timeout or if a running child died."""
    deadline = time.monotonic() + timeout
    while not pred():
        group.check(running)
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)
