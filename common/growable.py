"""Growable arrays for per-keyframe numbers (no Python object per keyframe).

Capacity grows by a quarter (`grown_capacity`), not by doubling: at most a fifth of
an array is unused, and a long mission's memory rises with its keyframes instead of
in doubling steps (a 10-robot soak's per-robot arrays doubling at 8,192 keyframes
each added ~10 MB at once).

A process may keep these arrays on disk (`keep_on_disk`, the base station does): each
is then a shared memory map of its own unnamed temporary file, which grows in place
(the file is extended and mapped again: no copy). Their pages are the kernel's page
cache, not the process's heap: written back to the file and dropped from memory when
the machine needs it, read in again when touched. A mission's private memory then
does not grow with its keyframes (~150 bytes a keyframe in the base station, ~15 MB
an hour for 10 drones); arrays made before the call, or from `np.zeros` rather than
`empty`, stay in memory.
"""

from __future__ import annotations

import logging
import mmap
import os
import tempfile

import numpy as np
from numpy.typing import ArrayLike

from common.errors import ConfigError

log = logging.getLogger(__name__)

GROWTH = 1.25  # new capacity / old when an array is full
MIN_CAPACITY = 64

_disk_dir: str | None = None  # where new arrays are kept (None: in memory)


def keep_on_disk(directory: str | None) -> None:
    """Arrays made by `empty` from now on live in memory-mapped temporary files in
    `directory` ("": the system's temporary directory; None: in memory again). Each
    holds two file descriptors (its file and its map), so the process's soft limit on
    open files is raised to the hard one."""
    global _disk_dir
    if directory:
        if not os.path.isdir(directory) or not os.access(directory, os.W_OK):
            raise ConfigError(f"per-keyframe arrays: {directory!r} is not a writable directory")
    _disk_dir = None if directory is None else (directory or tempfile.gettempdir())
    if _disk_dir is not None:
        try:
            import resource

            soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
            if soft != resource.RLIM_INFINITY and (hard == resource.RLIM_INFINITY or hard > soft):
                resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
        except (ImportError, ValueError, OSError):  # not on this system: keep the limit
            pass


class _File:
    """An unnamed temporary file (removed from its directory at once), closed when no
    map of it is left."""

    fd = -1

    def __init__(self, directory: str) -> None:
        fd, path = tempfile.mkstemp(prefix="collabslam-arrays-", dir=directory)
        os.unlink(path)
        self.fd = fd

    def __del__(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)


class _Mapping(mmap.mmap):
    """A shared map of a whole temporary file, which it keeps to grow it."""

    file: _File


def _mapped(file: _File, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    """The file's first rows as an array of `shape` (the file extended to hold them)."""
    count = int(np.prod(shape))
    size = max(count * dtype.itemsize, mmap.PAGESIZE)  # an empty map is not allowed
    if os.fstat(file.fd).st_size < size:
        # the room reserved now: a full disk is an OSError here, not a SIGBUS when a page
        # of a sparse file is first written; new bytes read as zeros
        if hasattr(os, "posix_fallocate"):
            os.posix_fallocate(file.fd, 0, size)
        else:
            os.ftruncate(file.fd, size)
    m = _Mapping(file.fd, size)
    m.file = file
    return np.frombuffer(m, dtype, count=count).reshape(shape)


def _mapping_of(a: np.ndarray) -> _Mapping | None:
    base = a
    while isinstance(base, np.ndarray):
        base = base.base
    if isinstance(base, memoryview):
        base = base.obj
    return base if isinstance(base, _Mapping) else None


def on_disk(a: np.ndarray) -> bool:
    """True if `a` lives in a memory-mapped file (`keep_on_disk`)."""
    return _mapping_of(a) is not None


def empty(tail: tuple[int, ...], dtype: type | np.dtype, memory: bool = False) -> np.ndarray:
    """A (0, *tail) array of `dtype` to grow with `grown`: on disk after `keep_on_disk`
    unless `memory` (arrays of a few rows, not one per keyframe: not worth a file)."""
    dtype = np.dtype(dtype)
    if _disk_dir is not None and not memory:
        try:
            return _mapped(_File(_disk_dir), (0, *tail), dtype)
        except OSError as exc:
            log.warning(
                "per-keyframe arrays: no file in %s (%s): this one in memory", _disk_dir, exc
            )
    return np.zeros((0, *tail), dtype)


def grown_capacity(capacity: int, needed: int) -> int:
    """The capacity to grow to when `needed` rows do not fit in `capacity`."""
    return max(needed, int(capacity * GROWTH), MIN_CAPACITY)


def grown(a: np.ndarray, needed: int, fill: float = 0) -> np.ndarray:
    """`a` (rows along axis 0) with room for `needed` rows, new rows set to `fill`;
    `a` itself when it has room. An array on disk grows in its file (`a`'s rows and
    every view of them stay valid: they share the file)."""
    if needed <= len(a):
        return a
    capacity = grown_capacity(len(a), needed)
    m = _mapping_of(a)
    if m is not None:
        try:
            out = _mapped(m.file, (capacity, *a.shape[1:]), a.dtype)
        except OSError as exc:  # e.g. the disk is full: go on in memory
            log.warning("per-keyframe arrays: cannot grow on disk (%s): in memory from now on", exc)
        else:
            if fill != 0:
                out[len(a) :] = fill
            return out
    out = np.full((capacity, *a.shape[1:]), fill, dtype=a.dtype)
    out[: len(a)] = a
    return out


class Rows:
    """A growable (n, k) array: rows appended one at a time (on disk after
    `keep_on_disk`, unless `memory`)."""

    def __init__(self, k: int, dtype: type = np.float64, memory: bool = False) -> None:
        self._a = empty((k,), dtype, memory)
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
