"""An exclusive advisory lock (flock) a process holds on a file or folder: one base
station per database, one agent per state folder."""

from __future__ import annotations

import fcntl
import os
from pathlib import Path


def exclusive(path: str | Path, flags: int = os.O_RDONLY) -> int | None:
    """A descriptor of `path` (opened with `flags`; created 0o644 with `os.O_CREAT`) with
    an exclusive flock held until it is closed (on Linux apart from SQLite's own POSIX
    locks), or None if another process holds it. OSError if it cannot be opened."""
    fd = os.open(path, flags, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd
