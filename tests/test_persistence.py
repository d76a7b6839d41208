"""The base station's SQLite record (real sqlite3 files): round trips, WAL, one
transaction per batch, and a GlobalSlam rebuilt from it equal to the one that wrote it."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from process_helpers import synthetic_keyframe

from basestation import persistence
from basestation.global_slam import GlobalSlam
from basestation.node import BaseStationNode
from basestation.pcm import LoopMeasurement
from basestation.persistence import Batch, KeyframeDatabase, NullDatabase, open_database
from common.bus import Bus
from common.config import Config
from common.errors import PersistenceError
from common.geometry import se2_compose
from common.map_io import GridMap, write_map
from common.scenario import RobotScenario, Scenario
from protocol import GnssFix, Keyframe, RobotState, encode
from protocol import Path as PathMsg


def _keyframe(robot: str, seq: int, pose: np.ndarray, delta: np.ndarray) -> Keyframe:
    return synthetic_keyframe(robot, seq, pose, delta)


def _square_keyframes(robot: str, start: np.ndarray, n: int) -> list[Keyframe]:
    """A robot driving a 5 m square in 1 m steps, odometry frame = its start."""
    out, T = [], np.zeros(3)
    for k in range(n):
        d = np.zeros(3) if k == 0 else np.array([1.0, 0.0, np.pi / 2 if k % 5 == 0 else 0.0])
        T = se2_compose(T, d)
        out.append(_keyframe(robot, k, T, d))
    return out


def _measurement(i: int) -> LoopMeasurement:
    return LoopMeasurement(i, "r0", i, "r1", i + 3, np.array([0.1, -0.2, 0.3]), np.eye(3) * 0.01)


def test_round_trip_and_wal(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(persistence, "READ_PAGE", 4)  # keyframes are read in pages
    path = tmp_path / "base.db"
    db = KeyframeDatabase(path)
    assert db.journal_mode() == "wal"
    assert db._db.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    kfs = _square_keyframes("r0", np.zeros(3), 4) + _square_keyframes("r1", np.zeros(3), 2)
    path_msg = PathMsg("r1", 7, 1.0, "map", 3, np.ones((5, 4), np.float32))
    db.commit(Batch(kfs[:3], [(_measurement(0), "loop")]))
    paths = [("r1", 7, encode(path_msg))]
    db.commit(Batch(kfs[3:], [(_measurement(1), "inter")], {0: True}, paths))
    db.commit(Batch(in_graph={1: True, 0: False}))
    db.commit(Batch())  # nothing to write: no transaction
    db.reserve_epochs(1000)
    assert db.commits == 3 and db.counts() == {"r0": 4, "r1": 2}
    db.close()

    again = KeyframeDatabase(path)
    rec = again.load()
    assert rec.starts == 2 and rec.epoch == 1000 and rec.path_id == 7
    assert len(rec.keyframes) == 6 and not rec.empty
    assert [(b, k.robot_id, k.seq) for b, k in rec.keyframes] == [
        (1, "r0", 0), (1, "r0", 1), (1, "r0", 2), (2, "r0", 3), (2, "r1", 0), (2, "r1", 1)
    ]  # fmt: skip
    for (_, got), want in zip(rec.keyframes, kfs, strict=True):
        assert encode(got) == encode(want)
    c0, c1 = rec.constraints
    assert (c0.kind, c0.in_graph, c0.batch) == ("loop", False, 1)
    assert (c1.kind, c1.in_graph, c1.batch) == ("inter", True, 2)
    assert np.array_equal(c1.measurement.T_a_b, _measurement(1).T_a_b)
    assert np.array_equal(c1.measurement.covariance, _measurement(1).covariance)
    assert (c1.measurement.robot_b, c1.measurement.index_b) == ("r1", 4)
    assert rec.paths["r1"] == encode(path_msg)
    again.close()


def test_a_full_disk_is_a_persistence_error_and_nothing_is_half_written(
    tmp_path: Path,
) -> None:
    """ "database or disk is full" had ended the base station in a traceback; now it is a
    PersistenceError (the node writes its outputs and exits 1, having acked nothing of
    the batch), and the stored batches stay whole."""
    db = KeyframeDatabase(tmp_path / "base.db")
    db.commit(Batch(_square_keyframes("r0", np.zeros(3), 3)))
    pages = db._db.execute("PRAGMA page_count").fetchone()[0]
    db._db.execute(f"PRAGMA max_page_count = {pages}")  # the disk is full now
    many = _square_keyframes("r1", np.zeros(3), 200)
    with pytest.raises(PersistenceError, match="base.db: cannot write: database or disk is full"):
        db.commit(Batch(many))
    assert db.counts() == {"r0": 3}
    db.close()
    assert KeyframeDatabase(tmp_path / "base.db").counts() == {"r0": 3}


def test_a_write_lock_held_by_another_program_is_waited_for(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An operator's sqlite3 shell inside a transaction (or a VACUUM) holding the write
    lock past SQLite's busy timeout (5 s) had ended the base station: "cannot write:
    database is locked". It now waits, with a warning, and writes once it is free."""
    import sqlite3
    import threading

    db = KeyframeDatabase(tmp_path / "base.db")
    db._db.execute("PRAGMA busy_timeout = 100")  # (each try: 0.1 s instead of 5 s)
    other = sqlite3.connect(tmp_path / "base.db", isolation_level=None, check_same_thread=False)
    other.execute("BEGIN IMMEDIATE")  # holds the write lock
    threading.Timer(1.0, lambda: other.execute("COMMIT")).start()
    with caplog.at_level("WARNING"):
        db.commit(Batch(_square_keyframes("r0", np.zeros(3), 3)))
    assert db.counts() == {"r0": 3} and "locked by another program" in caplog.text
    other.close()
    db.close()


def test_a_batch_is_one_transaction(tmp_path: Path) -> None:
    db = KeyframeDatabase(tmp_path / "base.db")
    kfs = _square_keyframes("r0", np.zeros(3), 3)
    db.commit(Batch(kfs[:1]))
    # the batch's last keyframe repeats a stored one: nothing of the batch may stay
    with pytest.raises(PersistenceError, match="conflicts"):
        db.commit(Batch(kfs[1:] + kfs[:1], [(_measurement(0), "loop")]))
    assert db.counts() == {"r0": 1} and db.load().constraints == []
    # a reader on another connection sees only whole batches
    db.commit(Batch(kfs[1:]))
    other = sqlite3.connect(tmp_path / "base.db")
    assert other.execute("SELECT count(*) FROM keyframes").fetchone()[0] == 3
    other.close()
    db.close()


def test_wrong_schema_version_is_refused(tmp_path: Path) -> None:
    KeyframeDatabase(tmp_path / "base.db").close()
    con = sqlite3.connect(tmp_path / "base.db")
    con.execute("UPDATE schema SET version = 99")
    con.commit()
    con.close()
    with pytest.raises(PersistenceError, match="schema version 99"):
        KeyframeDatabase(tmp_path / "base.db")


def test_one_database_is_one_base_stations(tmp_path: Path) -> None:
    """A second base station on a database in use had resumed the running mission
    without a word, and one of the two died at its next commit."""
    first = KeyframeDatabase(tmp_path / "base.db")
    with pytest.raises(PersistenceError, match="in use by another base station"):
        KeyframeDatabase(tmp_path / "base.db")
    first.close()
    KeyframeDatabase(tmp_path / "base.db").close()  # free again


def test_an_older_versions_payloads_and_a_damaged_row_are_read_or_named(tmp_path: Path) -> None:
    """A database from before protocol version 2 (which only added fields with
    defaults) had failed its restore with "unsupported schema version 1", naming no
    file; a damaged row had ended in a TypeError."""
    import msgpack

    db = KeyframeDatabase(tmp_path / "base.db")
    kfs = _square_keyframes("r0", np.zeros(3), 3)
    db.commit(Batch(kfs))
    db.close()
    con = sqlite3.connect(tmp_path / "base.db")
    rows = con.execute("SELECT rowid, payload FROM keyframes").fetchall()
    for rowid, payload in rows:  # as version 1 wrote them
        env = msgpack.unpackb(payload, raw=False)
        env["v"] = 1
        con.execute("UPDATE keyframes SET payload = ? WHERE rowid = ?",
                    (msgpack.packb(env, use_bin_type=True), rowid))  # fmt: skip
    con.commit()
    db = KeyframeDatabase(tmp_path / "base.db")
    got = [k for _, k in db.load().keyframes]
    assert [encode(k) for k in got] == [encode(k) for k in kfs]
    db.close()
    con.execute("UPDATE keyframes SET payload = ? WHERE rowid = ?", (b"\xc1 torn", rows[1][0]))
    con.commit()
    con.close()
    db = KeyframeDatabase(tmp_path / "base.db")
    with pytest.raises(PersistenceError, match=f"base.db: keyframe row {rows[1][0]} is damaged"):
        list(db.load().keyframes)
    db.close()


def test_another_programs_database_is_refused_untouched(tmp_path: Path) -> None:
    """A SQLite file of another program had been stamped with our schema version, and
    the base station died at its first keyframe on the foreign `keyframes` table."""
    path = tmp_path / "other.db"
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE keyframes (x)")
    con.commit()
    con.close()
    with pytest.raises(PersistenceError, match="not a collabslam database .*keyframes"):
        KeyframeDatabase(path)
    con = sqlite3.connect(path)
    names = [r[0] for r in con.execute("SELECT name FROM sqlite_master")]
    mode = con.execute("PRAGMA journal_mode").fetchone()[0]
    con.close()
    assert names == ["keyframes"] and mode == "delete"


def test_null_database() -> None:
    db = open_database("")
    assert isinstance(db, NullDatabase)
    db.commit(Batch(_square_keyframes("r0", np.zeros(3), 1)))
    assert db.load().empty


def test_global_slam_rebuilt_from_database(
    tmp_path: Path, cfg: Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Keyframes and matches written as the base station writes them (one batch per
    step) give, replayed, the same graph: same nodes, same accepted matches, same poses;
    the keyframes read 5 at a time, across batches."""
    monkeypatch.setattr(persistence, "READ_PAGE", 5)
    cfg.basestation.constraints.enabled = False  # matches are fed by hand below
    starts = {"r0": np.zeros(3), "r1": np.array([0.5, 0.5, 0.0])}
    db = KeyframeDatabase(tmp_path / "base.db")
    slam = GlobalSlam(cfg, starts)
    r0, r1 = _square_keyframes("r0", starts["r0"], 21), _square_keyframes("r1", starts["r1"], 12)
    cov = np.diag([0.03**2, 0.03**2, 0.01**2])
    for step in range(0, 21, 4):
        for kf in r0[step : step + 4] + r1[step : step + 4]:
            slam.admit(kf)
        db.commit(slam.take_journal())
        slam.optimize()
        if step == 20:  # back at the start: a loop closure, and a wrong one
            slam.loops.add(("r0", 0), ("r0", 20), np.zeros(3), cov, "loop")
            slam.loops.add(("r0", 2), ("r0", 18), np.array([3.0, 1.0, 1.0]), cov, "loop")
        if step == 8:  # r1 seen from r0: both at their own odometry origin + offset
            slam.loops.add(("r0", 1), ("r1", 1), np.array([0.5, 0.5, 0.0]), cov, "inter")
        db.commit(slam.take_journal())
        slam.optimize()
    assert slam.loops.accepted, "the test needs accepted matches"
    db.close()

    db2 = KeyframeDatabase(tmp_path / "base.db")
    rec = db2.load()
    back = GlobalSlam(cfg, starts)
    stored, held = rec.keyframes, []

    def watched():  # what the replay holds while it reads on
        for item in stored:
            held.append(len(back._unsaved))
            yield item

    rec.keyframes = watched()
    back.restore(rec)
    assert len(held) == 33 and max(held) <= 8  # one batch at most, never all of them
    for rid in ("r0", "r1"):
        assert back.graph.num_nodes(rid) == slam.graph.num_nodes(rid)
        assert back.store.acked_seq(rid) == slam.store.acked_seq(rid)
        assert np.allclose(back.graph.poses(rid), slam.graph.poses(rid), atol=1e-3)
    assert back.loops.accepted == slam.loops.accepted
    assert back.loops.offered == slam.loops.offered
    assert back.loops.counts() == slam.loops.counts()
    assert {c.measurement.id for c in rec.constraints if c.in_graph} == slam.loops.accepted
    assert not back.take_journal()  # nothing new to write after a replay
    # a resent keyframe after the restart is a duplicate, never a second node
    assert back.admit(r0[5]) == 0 and back.store.robot("r0").duplicates == 1
    db2.close()


def test_a_restore_relinearizes_after_matches_as_the_live_run_did(
    tmp_path: Path, cfg: Config
) -> None:
    """A drifted square closed by two loop closures: the live graph takes a forced
    relinearization step after matches; the replay had not (0.72 m, 0.13 rad apart)."""
    cfg.basestation.constraints.enabled = False
    kfs, T = [], np.zeros(3)
    for k in range(41):  # 1 m steps, a quarter turn every 10, and 0.02 rad of drift a step
        d = np.zeros(3) if k == 0 else np.array([1.0, 0.0, np.pi / 2 * (k % 10 == 0) + 0.02])
        kfs.append(_keyframe("r0", k, T := se2_compose(T, d), d))
    cov = np.diag([0.03**2, 0.03**2, 0.01**2])
    db = KeyframeDatabase(tmp_path / "base.db")
    live = GlobalSlam(cfg, {"r0": np.zeros(3)})
    for step in range(0, 41, 4):
        for kf in kfs[step : step + 4]:
            live.admit(kf)
        db.commit(live.take_journal())
        live.optimize()
    live.loops.add(("r0", 0), ("r0", 40), np.zeros(3), cov, "loop")
    live.loops.add(("r0", 1), ("r0", 40), np.array([-1.0, 0.0, 0.0]), cov, "loop")
    live._constraints_added = True  # (as `integrate_constraints` sets it)
    db.commit(live.take_journal())
    live.optimize()
    db.close()
    back = GlobalSlam(cfg, {"r0": np.zeros(3)})
    back.restore(KeyframeDatabase(tmp_path / "base.db").load())
    assert back.loops.accepted == live.loops.accepted == {0, 1}
    np.testing.assert_allclose(back.graph.poses("r0"), live.graph.poses("r0"), atol=1e-6)


def test_gnss_fixes_and_the_map_origin_are_restored(
    tmp_path: Path, cfg: Config, endpoint: str
) -> None:
    """A robot started from a heading at its first fix: restored without its fixes it
    floated (no GPS factors, its later fixes ignored), and a map origin taken from the
    first fixes was set again from the next five. Its start used its state then (a
    restart has none: its first keyframe's pose put it 20 m off)."""
    cfg.basestation.constraints.enabled = False
    cfg.basestation.gps.enabled = True
    db, headings, sig = KeyframeDatabase(tmp_path / "base.db"), {"r0": 0.3}, np.ones(3)
    live = GlobalSlam(cfg, None, headings)
    live.odom_now = lambda r: np.array([20.0, 5.0, 0.3])  # its state then, 20 m on
    live.add_gps_fix("r0", -0.1, np.array([100.0, 50.0]), sig)
    T = np.zeros(3)
    for k in range(10):
        d = np.zeros(3) if k == 0 else np.array([0.5, 0.0, 0.0])
        live.admit(_keyframe("r0", k, T := se2_compose(T, d), d))
        live.add_gps_fix("r0", 0.5 * k + 0.25, se2_compose([100, 50, 0.3], T)[:2], sig)
        db.commit(live.take_journal())
        live.optimize()
    db.close()
    back = GlobalSlam(cfg, None, headings)
    back.restore(KeyframeDatabase(tmp_path / "base.db").load())
    assert back.graph.is_anchored("r0") and back.graph.num_gps_factors == 8
    np.testing.assert_allclose(back.T_map_odom("r0"), live.T_map_odom("r0"), atol=1e-6)
    cfg.basestation.db_path, cfg.zenoh.listen = str(tmp_path / "node.db"), [endpoint]
    cfg.basestation.known_start_poses = False  # robots started from GNSS headings
    write_map(GridMap(np.zeros((10, 10), np.int8), 0.1, (0.0, 0.0, 0.0)), tmp_path / "w.yaml")
    scenario = Scenario(str(tmp_path / "w.yaml"), [RobotScenario("r0", np.array([0, 0, 0.3]))])
    origins = []
    for start in range(2):  # a node whose world gives no WGS84 origin, then its restart
        with Bus(cfg.zenoh, cfg.fleet) as bus:
            node = BaseStationNode(cfg, bus, scenario)
            node.recover()
            for i in range(5):  # the first five fixes' median is the origin
                lat = 48.0 + 1e-4 * (i + 5 * start)
                node.gnss_inbox.put(GnssFix("r0", float(i), np.array([lat, 11.0, 500.0]), sig))
            node._take_fixes()
            node._persist()
            origins.append(node.gnss.origin)
            node.db.close()
    assert origins[0] is not None and origins[1] == origins[0]


def test_node_resumes_epochs_paths_and_acks(tmp_path: Path, cfg: Config, endpoint: str) -> None:
    """A base-station node on an existing database continues above every epoch and path
    id sent before, gives the robot back its path, and acks what is stored."""
    db = KeyframeDatabase(tmp_path / "base.db")
    wp = np.array([[0, 0, 1, 0], [2, 1, 1, 0], [4, 1, 1, 0]], np.float32)
    path = PathMsg("r0", 7, 1.0, "map", 3, wp)
    db.commit(Batch(_square_keyframes("r0", np.zeros(3), 3), paths=[("r0", 7, encode(path))]))
    db.reserve_epochs(1000)
    db.close()
    cfg.exploration.enabled = True
    cfg.basestation.db_path = str(tmp_path / "base.db")
    cfg.zenoh.listen = [endpoint]
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node = BaseStationNode(cfg, bus, None)
        node.recover()
        assert node.slam.store.acked_seq("r0") == 2 and node.slam.graph.num_nodes("r0") == 3
        assert node.epochs.current == 1000 and node._path_id == 7
        assert node.explorer is not None
        assert np.allclose(node.explorer.tasks["r0"].path, wp[:, :2])
        node.publish_corrections()
        assert node.epochs.current == 1001
        pose = np.array([0, 0, 0, 0, 0, 0, 1.0])
        for epoch in (5000, 5000 + 200_000):  # another base station's (a new database),
            node._on_state(RobotState("r0", 9.0, "flying", epoch, 3, 3, 0, pose, pose), "")
        node.publish_corrections()  # ... which it took; not one no base station counts to
        assert node.epochs.current == 5001  # else its corrections would be dropped
        node.drain(1.0)
    again = KeyframeDatabase(tmp_path / "base.db")
    assert again.load().epoch >= 5002 + 999 and again.starts == 3  # the next epoch block
    again.close()


def test_a_database_file_removed_while_running_stops_the_commits(tmp_path: Path) -> None:
    """Deleted under a running base station, it had taken commits (and so acks) into an
    unlinked file, lost on exit."""
    db = KeyframeDatabase(tmp_path / "base.db")
    db.commit(Batch(_square_keyframes("r0", np.zeros(3), 2)))
    for name in ("base.db", "base.db-wal", "base.db-shm"):
        (tmp_path / name).unlink(missing_ok=True)
    with pytest.raises(PersistenceError, match="removed or replaced"):
        db.commit(Batch(_square_keyframes("r1", np.zeros(3), 2)))


def test_a_write_error_names_the_databases_files_that_are_not_writable(tmp_path: Path) -> None:
    """A `-shm` left read-only (SQLite gives it the database's mode) by a start on a
    read-only file failed every later start with "attempt to write a readonly database",
    after the database itself was made writable again."""
    path = tmp_path / "mission.db"
    for f in (path, tmp_path / "mission.db-shm"):
        f.write_bytes(b"")
    (tmp_path / "mission.db-shm").chmod(0o444)
    err = persistence._cannot_write(path, sqlite3.OperationalError("readonly database"))
    assert str(err).endswith("readonly database (not writable: mission.db-shm; all three must be)")
