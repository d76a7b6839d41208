"""The base station's crash-safe record: an embedded SQLite database.

What is written, one transaction per processed batch, *before* the batch is
acknowledged or published:

- every keyframe admitted to the pose graph, as its encoded protocol bytes
  (`protocol.codec`, as its agent sent it), keyed by (robot segment, seq) (a run of
  the robot's agent: basestation/robot_segments.py), in admission order;
- every verified match handed to the loop-closure manager (robot pair, node
  indices, T_a_b, covariance, kind) and whether it is in the graph now (PCM may
  take it out again later: that removal is written too);
- the correction-epoch high-water mark (epochs are reserved in blocks, so an
  epoch is never reused after a restart without one write per correction);
- the latest exploration path per robot and the path-id counter;
- every GNSS fix given to the graph (robot segment, stamp, east-north in `map`, sigmas)
  and the map's WGS84 origin: a restart had lost them, and its robots started from a
  heading and a fix floated, their later fixes ignored;
- where each robot segment's chain started (`T_map_odom` prior and sigmas, or none: it
  floated): a start from a GNSS fix used the robot's state then, which a restart has
  not (placed from its first keyframe instead, tens of metres off).

Durability: WAL journal with ``synchronous=FULL``: a commit returns only after
the WAL is fsynced, so an acknowledged keyframe survives SIGKILL *and* power
loss (``NORMAL`` would survive a killed process but could lose the last commits
on power loss, after the agent had already dropped them from its outbox).

`NullDatabase` is the do-nothing stand-in when no path is configured.
"""

from __future__ import annotations

import logging
import os
import sqlite3
import time
import weakref
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from basestation.pcm import LoopMeasurement
from basestation.robot_segments import as_sent
from basestation.scan_archive import ScanReader
from common.errors import PersistenceError, ProtocolError
from common.file_lock import exclusive
from protocol import Keyframe, decode, encode

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
# s the base station waits for another program's write lock on its database before it gives up
LOCK_WAIT_S = 600.0
READ_PAGE = 1000  # stored keyframes decoded at a time while recovering
EPOCH_BLOCK = 1000  # correction epochs reserved per write

_SCHEMA = """
CREATE TABLE IF NOT EXISTS schema (version INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS keyframes (
    robot_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    batch INTEGER NOT NULL,
    payload BLOB NOT NULL,
    PRIMARY KEY (robot_id, seq)
);
CREATE TABLE IF NOT EXISTS constraints (
    id INTEGER PRIMARY KEY,
    batch INTEGER NOT NULL,
    robot_a TEXT NOT NULL, index_a INTEGER NOT NULL,
    robot_b TEXT NOT NULL, index_b INTEGER NOT NULL,
    x REAL NOT NULL, y REAL NOT NULL, yaw REAL NOT NULL,
    covariance BLOB NOT NULL,
    kind TEXT NOT NULL,
    in_graph INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS paths (
    robot_id TEXT PRIMARY KEY,
    path_id INTEGER NOT NULL,
    payload BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS gnss_fixes (
    batch INTEGER NOT NULL,
    robot_id TEXT NOT NULL,
    stamp REAL NOT NULL,
    x REAL NOT NULL, y REAL NOT NULL,
    sigmas BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS gnss_origin (lat_deg REAL, lon_deg REAL, alt_m REAL);
CREATE TABLE IF NOT EXISTS chain_starts (robot_id TEXT PRIMARY KEY, start BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS backfilled (
    robot_a TEXT NOT NULL, robot_b TEXT NOT NULL, PRIMARY KEY (robot_a, robot_b)
);
"""
# a GNSS fix as the graph took it: (robot segment, stamp, east-north in map, ENU sigmas)
Fix = tuple[str, float, np.ndarray, np.ndarray]
# a chain's start: T_map_first [x, y, yaw] and its sigmas (None: it floats; the default)
Start = tuple[np.ndarray | None, np.ndarray | None]


@dataclass
class StoredConstraint:
    """A verified match as it went into the loop-closure manager."""

    measurement: LoopMeasurement
    kind: str
    in_graph: bool
    batch: int


@dataclass
class Batch:
    """Everything one processing step wants on disk before it acks or publishes."""

    keyframes: list[Keyframe] = field(default_factory=list)  # admitted, in order
    constraints: list[tuple[LoopMeasurement, str]] = field(default_factory=list)
    in_graph: dict[int, bool] = field(default_factory=dict)  # constraint id -> in graph now
    paths: list[tuple[str, int, bytes]] = field(default_factory=list)  # (robot, path_id, Path)
    fixes: list[Fix] = field(default_factory=list)  # given to the graph, in order
    origin: list[float] | None = None  # the map's WGS84 origin, once set: [lat, lon, alt]
    chain_starts: dict[str, Start] = field(default_factory=dict)  # chains started
    backfilled: list[tuple[str, str]] = field(default_factory=list)  # joins' backfills done

    def __bool__(self) -> bool:
        return bool(
            self.keyframes or self.constraints or self.in_graph or self.paths or self.fixes
            or self.origin or self.chain_starts or self.backfilled
        )  # fmt: skip


class StoredKeyframes:
    """The stored keyframes as (batch, keyframe) in admission order, read and decoded
    `READ_PAGE` at a time each time they are iterated: a long mission's keyframes,
    scans included (~2.5 kB each), need not all be in memory while a restart replays
    them (`GlobalSlam.restore` lets each batch's scans go once it is admitted)."""

    def __init__(self, db: sqlite3.Connection, path: Path) -> None:
        self._db, self._path = db, path
        self._count = int(db.execute("SELECT count(*) FROM keyframes").fetchone()[0])

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[tuple[int, Keyframe]]:
        last = -1
        while True:
            rows = self._db.execute(
                "SELECT rowid, robot_id, batch, payload FROM keyframes WHERE rowid > ? "
                "ORDER BY rowid LIMIT ?",
                (last, READ_PAGE),
            ).fetchall()
            if not rows:
                return
            for rowid, segment, b, payload in rows:  # as its robot's segment (robot_segments.py)
                try:
                    kf = decode(payload, Keyframe, max_bytes=len(payload) + 1)
                except (ProtocolError, TypeError) as exc:  # (a damaged page: None, bytes)
                    raise PersistenceError(f"{self._path}: keyframe row {rowid} is damaged "
                                           f"({exc}): restore from a backup") from None  # fmt: skip
                yield int(b), kf if kf.robot_id == segment else replace(kf, robot_id=segment)
            last = rows[-1][0]


@dataclass
class Recovered:
    """The stored state, in the order it was written."""

    # (batch, keyframe) in admission order (batches ascending)
    keyframes: StoredKeyframes | list[tuple[int, Keyframe]]
    constraints: list[StoredConstraint]  # by id (= the order they were added)
    epoch: int  # every epoch sent before is below this
    path_id: int  # highest path id sent
    paths: dict[str, bytes]  # robot -> its latest encoded Path
    starts: int  # how many times a base station opened this database (this one included)
    fixes: list[tuple[int, Fix]] = field(default_factory=list)  # (batch, fix) in order
    gnss_origin: list[float] | None = None  # the map's WGS84 origin, if it was set
    chain_starts: dict[str, Start] = field(default_factory=dict)  # where each chain began
    backfilled: set[tuple[str, str]] = field(default_factory=set)  # pairs, names in order

    @property
    def empty(self) -> bool:
        return not self.keyframes and not self.fixes


def _exclusive(path: Path) -> int:
    """A descriptor of `path` with an exclusive flock held (Linux: apart from SQLite's
    own locks), or PersistenceError: a second base station on one file had resumed the
    running mission, and one of the two died at its next commit; two fleets mixed."""
    try:
        fd = exclusive(path, os.O_RDWR | os.O_CREAT)
    except OSError as exc:
        raise PersistenceError(f"cannot open database {path}: {exc.strerror}") from None
    if fd is None:
        raise PersistenceError(f"{path}: in use by another base station (a database is "
                               "one mission's, of one process)")  # fmt: skip
    return fd


class KeyframeDatabase:
    """One SQLite file; use from one thread (the base station's processing thread)."""

    def __init__(self, path: str | Path, synchronous: str = "FULL") -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # the lock goes with close(), or with this object (a database opened to read)
        self._unlock = weakref.finalize(self, os.close, _exclusive(self.path))
        try:
            self._open(synchronous)
        except BaseException:
            if hasattr(self, "_db"):
                self._db.close()
            self._unlock()
            raise

    def _open(self, synchronous: str) -> None:
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None)
            tables = sorted(r[0] for r in self._db.execute("SELECT name FROM sqlite_master"))
            if tables and "schema" not in tables:  # another program's file: not written to
                raise PersistenceError(
                    f"{self.path}: not a collabslam database (it holds {', '.join(tables)})"
                )
            mode = self._db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            self._db.execute(f"PRAGMA synchronous={synchronous}")
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT version FROM schema").fetchone()
            if row is None:
                self._db.execute("INSERT INTO schema VALUES (?)", (SCHEMA_VERSION,))
            elif row[0] != SCHEMA_VERSION:
                raise PersistenceError(
                    f"{self.path}: database schema version {row[0]}, this build "
                    f"reads version {SCHEMA_VERSION}"
                )
        except sqlite3.Error as exc:
            raise PersistenceError(f"cannot open database {self.path}: {exc}") from None
        if mode != "wal":
            raise PersistenceError(f"{self.path}: WAL journal mode refused ({mode})")
        self._batch = self._meta("batch", 0)
        self.starts = self._meta("starts", 0) + 1
        with self._transaction():  # a read-only file fails here, with one line
            self._set_meta("starts", self.starts)
        self.commits = 0
        self._inode = self.path.stat().st_ino  # the file this connection writes
        self._reader: ScanReader | None = None

    # --- writing ------------------------------------------------------------------------
    def commit(self, batch: Batch) -> None:
        """Write one batch in one transaction (durable when this returns)."""
        if not batch:
            return
        self._check_file()
        self._batch += 1
        b = self._batch
        try:
            with self._transaction():
                self._db.executemany(
                    "INSERT INTO keyframes VALUES (?, ?, ?, ?)",
                    [(k.robot_id, k.seq, b, encode(as_sent(k))) for k in batch.keyframes],
                )
                self._db.executemany(
                    "INSERT INTO constraints VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, 0)",
                    [
                        (
                            m.id, b, m.robot_a, m.index_a, m.robot_b, m.index_b,
                            *(float(v) for v in m.T_a_b),
                            np.asarray(m.covariance, "<f8").tobytes(), kind,
                        )
                        for m, kind in batch.constraints
                    ],
                )  # fmt: skip
                self._db.executemany(
                    "UPDATE constraints SET in_graph = ? WHERE id = ?",
                    [(int(v), i) for i, v in batch.in_graph.items()],
                )
                self._db.executemany("INSERT OR REPLACE INTO paths VALUES (?, ?, ?)", batch.paths)
                self._db.executemany(
                    "INSERT INTO gnss_fixes VALUES (?, ?, ?, ?, ?, ?)",
                    [(b, r, float(t), float(xy[0]), float(xy[1]),
                      np.asarray(sig, "<f8").tobytes()) for r, t, xy, sig in batch.fixes],
                )  # fmt: skip
                self._db.executemany(
                    "INSERT OR REPLACE INTO chain_starts VALUES (?, ?)",
                    [(r, _start_blob(*st)) for r, st in batch.chain_starts.items()],
                )
                self._db.executemany(
                    "INSERT OR IGNORE INTO backfilled VALUES (?, ?)", batch.backfilled
                )
                if batch.origin is not None:
                    self._db.execute("DELETE FROM gnss_origin")
                    self._db.execute("INSERT INTO gnss_origin VALUES (?, ?, ?)", batch.origin)
                if batch.paths:
                    top = max(p[1] for p in batch.paths)
                    self._db.execute(
                        "INSERT INTO meta VALUES ('path_id', ?) ON CONFLICT(key) "
                        "DO UPDATE SET value = max(value, excluded.value)",
                        (top,),
                    )
                self._db.execute("INSERT OR REPLACE INTO meta VALUES ('batch', ?)", (b,))
        except sqlite3.IntegrityError as exc:
            raise PersistenceError(
                f"{self.path}: batch {b} conflicts with stored data: {exc}"
            ) from None
        self.commits += 1

    def _check_file(self) -> None:
        """The file is still the one opened: one deleted (or replaced) while the base
        station ran had taken commits and acks into an unlinked inode, lost on exit."""
        try:
            same = self.path.stat().st_ino == self._inode
        except OSError:
            same = False
        if not same:
            raise PersistenceError(f"{self.path}: the database file was removed or replaced")

    def reserve_epochs(self, upto: int) -> None:
        """Record that epochs below `upto` may be sent (a restart starts at `upto`)."""
        with self._transaction():
            self._set_meta("epoch", upto)

    # --- reading ------------------------------------------------------------------------
    def load(self) -> Recovered:
        """Everything stored; keyframes in admission order, decoded as they are read
        (`StoredKeyframes`: iterate them before anything is written again)."""
        keyframes = StoredKeyframes(self._db, self.path)
        constraints = []
        for row in self._db.execute(
            "SELECT id, batch, robot_a, index_a, robot_b, index_b, x, y, yaw, covariance, "
            "kind, in_graph FROM constraints ORDER BY id"
        ):
            i, b, ra, ia, rb, ib, x, y, yaw, cov, kind, in_graph = row
            m = LoopMeasurement(
                i, ra, ia, rb, ib, np.array([x, y, yaw]),
                np.frombuffer(cov, "<f8").reshape(3, 3).copy(),
            )  # fmt: skip
            constraints.append(StoredConstraint(m, kind, bool(in_graph), int(b)))
        paths = dict(self._db.execute("SELECT robot_id, payload FROM paths").fetchall())
        fixes = [
            (int(b), (r, float(t), np.array([x, y]), np.frombuffer(sig, "<f8").copy()))
            for b, r, t, x, y, sig in self._db.execute(
                "SELECT batch, robot_id, stamp, x, y, sigmas FROM gnss_fixes ORDER BY rowid"
            )
        ]
        origin = self._db.execute("SELECT lat_deg, lon_deg, alt_m FROM gnss_origin").fetchone()
        rows = self._db.execute("SELECT robot_id, start FROM chain_starts").fetchall()
        chain_starts = {r: _start_of(blob) for r, blob in rows}
        backfilled = set(self._db.execute("SELECT robot_a, robot_b FROM backfilled").fetchall())
        return Recovered(
            keyframes,
            constraints,
            self._meta("epoch", 0),
            self._meta("path_id", 0),
            paths,
            self.starts,
            fixes,
            None if origin is None else [float(v) for v in origin],
            chain_starts,
            backfilled,
        )

    def counts(self) -> dict[str, int]:
        """Stored keyframes per robot."""
        rows = self._db.execute("SELECT robot_id, count(*) FROM keyframes GROUP BY robot_id")
        return {r: int(n) for r, n in rows}

    def stats(self) -> dict[str, Any] | None:
        """For basestation.json: where it is, how often opened, transactions."""
        return {"db": str(self.path), "starts": self.starts, "commits": self.commits}

    def scan_reader(self) -> ScanReader:
        """Reads committed keyframes' scans back (its own connection per thread)."""
        if self._reader is None:
            self._reader = ScanReader(self.path)
        return self._reader

    def journal_mode(self) -> str:
        return str(self._db.execute("PRAGMA journal_mode").fetchone()[0])

    def close(self) -> None:
        """Close the writer and the scan reader's connections (a later read through the
        reader opens a new one: the map written after a drain reads old scans)."""
        self._db.close()
        if self._reader is not None:
            self._reader.close()
        self._unlock()  # (last: closing a descriptor of the file drops SQLite's locks)

    # --- helpers ------------------------------------------------------------------------
    def _transaction(self) -> _Transaction:
        return _Transaction(self._db, self.path)

    def _meta(self, key: str, default: int) -> int:
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return default if row is None else int(row[0])

    def _set_meta(self, key: str, value: int) -> None:
        self._db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)", (key, value))


def _start_blob(start: np.ndarray | None, sigmas: np.ndarray | None) -> bytes:
    """A chain's start as 6 float64 [x, y, yaw, sx, sy, syaw]; NaN for what is None."""
    v = np.full(6, np.nan)
    if start is not None:
        v[:3] = start
    if sigmas is not None:
        v[3:] = sigmas
    return v.astype("<f8").tobytes()


def _start_of(blob: bytes) -> Start:
    v = np.frombuffer(blob, "<f8")
    return (None if np.isnan(v[0]) else v[:3].copy()), (None if np.isnan(v[3]) else v[3:].copy())


def _cannot_write(path: Path, exc: BaseException) -> PersistenceError:
    """The error of a failed write, naming the database's files that are not writable:
    a `-shm` left read-only by a start on a read-only file had failed every later start
    with the same "readonly database" after the file was made writable again."""
    files = (path, Path(f"{path}-wal"), Path(f"{path}-shm"))
    writable = [f.exists() and f.stat().st_mode & 0o200 and os.access(f, os.W_OK) for f in files]
    stuck = [f.name for f, ok in zip(files, writable, strict=True) if f.exists() and not ok]
    hint = f" (not writable: {', '.join(stuck)}; all three must be)" if stuck else ""
    return PersistenceError(f"{path}: cannot write: {exc}{hint}")


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, or ROLLBACK if the block raises."""

    def __init__(self, db: sqlite3.Connection, path: Path) -> None:
        self._db = db
        self._path = path

    def __enter__(self) -> None:
        """Waits while another program holds the file's write lock (an operator's sqlite3
        shell in a transaction, a VACUUM), up to `LOCK_WAIT_S`, with a warning now and
        then: a lock held past SQLite's 5 s had ended the base station. Nothing waiting
        is acknowledged yet, so waiting loses nothing."""
        t0 = time.monotonic()
        while True:
            try:
                self._db.execute("BEGIN IMMEDIATE")  # (each try waits 5 s for the lock)
                return
            except sqlite3.OperationalError as exc:
                waited = time.monotonic() - t0
                if "locked" not in str(exc) or waited > LOCK_WAIT_S:
                    raise _cannot_write(self._path, exc) from None
                log.warning("%s is locked by another program for %.0f s: waiting to write "
                            "(nothing is acknowledged meanwhile)", self._path, waited)  # fmt: skip
            except sqlite3.Error as exc:
                raise _cannot_write(self._path, exc) from None

    def __exit__(self, exc_type: type[BaseException] | None, exc: object, tb: object) -> None:
        """A write that fails (disk full, file made read-only) is a PersistenceError: it
        had ended the base station in a traceback. Nothing of it was acknowledged."""
        try:
            self._db.execute("ROLLBACK" if exc_type else "COMMIT")
        except sqlite3.Error as err:
            if exc_type is None:
                raise PersistenceError(f"{self._path}: cannot commit: {err}") from None
        if exc_type is not None and issubclass(exc_type, sqlite3.Error):
            if not issubclass(exc_type, sqlite3.IntegrityError):  # commit() words that one
                raise _cannot_write(self._path, exc) from None


class NullDatabase:
    """No persistence: the same interface, nothing written, nothing recovered."""

    path = None
    starts = 1
    commits = 0

    def commit(self, batch: Batch) -> None:
        pass

    def reserve_epochs(self, upto: int) -> None:
        pass

    def load(self) -> Recovered:
        return Recovered([], [], 0, 0, {}, 1)

    def counts(self) -> dict[str, int]:
        return {}

    def stats(self) -> None:
        return None

    def scan_reader(self) -> None:
        """Nothing to read scans back from: they stay in memory."""
        return None

    def close(self) -> None:
        pass


def open_database(path: str | Path | None) -> KeyframeDatabase | NullDatabase:
    """A `KeyframeDatabase` at `path`, or a `NullDatabase` when path is empty/None."""
    return KeyframeDatabase(path) if path else NullDatabase()
