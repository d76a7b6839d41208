"""Admitted keyframes' scans: the recent ones in memory, older ones read back from the
database (basestation/persistence.py), so the base station's memory does not grow by a
scan (2.2 kB) per keyframe.

Every admitted keyframe is written to the database, whole, before it is acknowledged.
`ScanArchive` holds a scan in memory until its keyframe is committed (`saved`), then in
a least-recently-used cache of `capacity` scans; a scan asked for after it left the
cache (a loop-closure target, a map tile redrawn after a correction) is read back with
`ScanReader`. Without a database (no reader) every scan stays in memory.

Threads: `ScanArchive` is used from one thread (the base station's processing thread);
`ScanReader` opens one read-only SQLite connection per calling thread (WAL: readers see
every committed batch and never block the writer).
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections import OrderedDict
from collections.abc import Sequence
from pathlib import Path

from common.errors import PersistenceError, ProtocolError
from protocol import Keyframe
from protocol.codec import decode_field
from protocol.messages import Scan2D

NodeKey = tuple[str, int]  # (robot_id, seq)
MAX_PARAMS = 500  # seqs per query (SQLite allows 999 parameters in old builds)


class ScanReader:
    """Keyframes' scans read back from the base station's SQLite database."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._local = threading.local()
        self._connections: list[sqlite3.Connection] = []
        self._lock = threading.Lock()
        self.reads = 0  # scans read so far
        self.read_s = 0.0  # s spent reading them

    def _connection(self) -> sqlite3.Connection:
        con = getattr(self._local, "con", None)
        if con is None:
            try:  # used by this thread only; closed by close() (any thread)
                con = sqlite3.connect(
                    f"file:{self.path}?mode=ro", uri=True, check_same_thread=False
                )
            except sqlite3.Error as exc:
                raise PersistenceError(f"cannot read {self.path}: {exc}") from None
            self._local.con = con
            with self._lock:
                self._connections.append(con)
        return con

    def read(self, keys: Sequence[NodeKey]) -> list[Scan2D | None]:
        """The scans of keyframes `keys` (committed ones; None: a keyframe without a scan),
        one query per robot. Raises PersistenceError if one is not in the database or
        cannot be decoded."""
        t0 = time.perf_counter()
        con = self._connection()
        by_robot: dict[str, list[int]] = {}
        for rid, seq in keys:
            by_robot.setdefault(rid, []).append(seq)
        found: dict[NodeKey, Scan2D | None] = {}
        for rid, seqs in by_robot.items():
            for i in range(0, len(seqs), MAX_PARAMS):
                part = seqs[i : i + MAX_PARAMS]
                rows = con.execute(  # fetchall: the statement ends, no snapshot stays open
                    "SELECT seq, payload FROM keyframes WHERE robot_id = ? AND seq IN "
                    f"({', '.join('?' * len(part))})",
                    (rid, *part),
                ).fetchall()
                for seq, payload in rows:
                    try:
                        found[(rid, seq)] = decode_field(payload, Keyframe, "scan2d")
                    except ProtocolError as exc:
                        raise PersistenceError(
                            f"{self.path}: keyframe {rid}/{seq}: {exc}"
                        ) from None
        try:
            out = [found[key] for key in keys]
        except KeyError as exc:
            raise PersistenceError(f"{self.path}: keyframe {exc} is not stored") from None
        self.reads += len(keys)
        self.read_s += time.perf_counter() - t0
        return out

    def close(self) -> None:
        with self._lock:
            for con in self._connections:
                con.close()
            self._connections.clear()
        self._local = threading.local()


class ScanArchive:
    def __init__(self, reader: ScanReader | None = None, capacity: int = 5000) -> None:
        """`reader`: where committed scans are read back (None: all stay in memory);
        `capacity`: committed scans kept in memory, least recently used dropped first."""
        self.reader = reader
        self.capacity = capacity
        self._unsaved: dict[NodeKey, Scan2D | None] = {}  # not committed yet: kept
        self._cache: OrderedDict[NodeKey, Scan2D | None] = OrderedDict()
        self._all: dict[str, list[Scan2D | None]] = {}  # without a reader: robot -> by seq

    def add(self, key: NodeKey, scan: Scan2D | None) -> None:
        """A newly admitted keyframe's scan (kept until `saved`); keyframes of a robot
        are added in seq order from 0."""
        if self.reader is None:
            scans = self._all.setdefault(key[0], [])
            if key[1] != len(scans):
                raise KeyError(f"scan {key} added out of order (expected seq {len(scans)})")
            scans.append(scan)
        else:
            self._unsaved[key] = scan

    def saved(self, keys: Sequence[NodeKey]) -> None:
        """Keyframes `keys` are committed to the database: their scans may leave memory."""
        for key in keys:
            if key in self._unsaved:
                self._put(key, self._unsaved.pop(key))

    def get(self, keys: Sequence[NodeKey]) -> list[Scan2D | None]:
        """The scans of admitted keyframes `keys` (None: a keyframe without a scan)."""
        if self.reader is None:
            return [self._all[rid][seq] for rid, seq in keys]
        out: list[Scan2D | None] = []
        missing: list[int] = []
        for n, key in enumerate(keys):
            if key in self._unsaved:
                out.append(self._unsaved[key])
            elif key in self._cache:
                self._cache.move_to_end(key)
                out.append(self._cache[key])
            else:
                out.append(None)
                missing.append(n)
        if missing:
            wanted = [keys[n] for n in missing]
            for n, key, scan in zip(missing, wanted, self.reader.read(wanted), strict=True):
                out[n] = scan
                self._put(key, scan)
        return out

    def _put(self, key: NodeKey, scan: Scan2D | None) -> None:
        self._cache[key] = scan
        self._cache.move_to_end(key)
        while len(self._cache) > self.capacity:
            self._cache.popitem(last=False)

    @property
    def in_memory(self) -> int:
        """Scans held in memory now."""
        return len(self._unsaved) + len(self._cache) + sum(map(len, self._all.values()))

    @property
    def reads(self) -> int:
        """Scans read back from the database so far."""
        return 0 if self.reader is None else self.reader.reads

    def stats(self) -> dict[str, float]:
        return {
            "in_memory": self.in_memory,
            "read_back": self.reads,
            "read_s": 0.0 if self.reader is None else round(self.reader.read_s, 3),
        }
