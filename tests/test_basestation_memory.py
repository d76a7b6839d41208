"""Base-station memory by size (tracemalloc, no timing): what a keyframe costs in the
keyframe store (with and without a database to read old scans back from), that scan
points are a bounded cache, and that nothing grows while no new keyframe arrives
(robots hovering: states and resent duplicates only)."""

from __future__ import annotations

import dataclasses
import gc
import json
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from process_helpers import synthetic_keyframe

from basestation.inbox import KeyframeInbox
from basestation.keyframe_store import KeyframeStore, scan_points
from basestation.node import BaseStationNode
from basestation.persistence import Batch, KeyframeDatabase
from basestation.scan_archive import ScanArchive
from common.bus import Bus
from common.config import Config
from common.geometry import se2_compose
from protocol import Cloud3D, Keyframe, RobotState

BEAMS = 1081  # the simulated lidar's


def _keyframe(robot: str, seq: int, pose: np.ndarray, delta: np.ndarray) -> Keyframe:
    return synthetic_keyframe(robot, seq, pose, delta, BEAMS, 1.5 * np.pi, 3.0, 0.5, 0.1)


def _tour(robot: str, n: int, step: float = 0.2) -> list[Keyframe]:
    """Back and forth along a 4 m line, 0.2 m apart (keyframe_distance_m)."""
    out, T = [], np.zeros(3)
    for k in range(n):
        d = np.zeros(3) if k == 0 else np.array([step, 0.0, np.pi if k % 20 == 0 else 0.0])
        T = se2_compose(T, d)
        out.append(_keyframe(robot, k, T, d))
    return out


def test_store_keeps_scans_and_a_bounded_points_cache() -> None:
    store = KeyframeStore(points_cache=100)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    kfs = _tour("r0", 600)
    for kf in kfs:
        assert len(store.admit(kf)) == 1
    scan0 = kfs[0].scan2d
    del kf, kfs  # what the store keeps of them stays
    per_kf = (tracemalloc.get_traced_memory()[0] - before) / 600
    tracemalloc.stop()
    # the uint16 scan (2 x 1081 bytes) and a few hundred bytes; no Keyframe object, no
    # float64 scan points (before: ~14 kB per keyframe)
    assert 2 * BEAMS < per_kf < 2 * BEAMS + 500, per_kf
    r = store.robot("r0")
    assert r.next_seq == 600 and store.scan("r0", 0) is scan0
    first = store.points("r0", 0)
    assert first.dtype == np.float32 and first.shape[1] == 2 and not first.flags.writeable
    for i in range(600):
        store.points("r0", i)
    assert len(store._points) == 100 and store.points_made == 600
    again = store.points("r0", 0)  # evicted: made again from the scan, same points
    assert store.points_made == 601
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(again, scan_points(scan0))
    assert store.points("r0", 0) is again and store.points_made == 601  # cached now


def test_a_robot_sending_3d_clouds_is_named_once(caplog: pytest.LogCaptureFixture) -> None:
    """The base station maps 2-D scans only: a cloud keyframe joins the graph's chain
    (admitted, acknowledged) and the robot is named once in a warning (before, its
    clouds were dropped without a word)."""
    store = KeyframeStore()
    rng = np.random.default_rng(0)
    cloud = Cloud3D(rng.uniform(-5.0, 5.0, (500, 3)).astype(np.float32))
    kfs = [dataclasses.replace(k, scan2d=None, cloud3d=cloud) for k in _tour("r0", 5)]
    with caplog.at_level("WARNING"):
        assert sum(len(store.admit(kf)) for kf in kfs) == 5
    assert caplog.text.count("robot r0 sends 3-D clouds") == 1
    assert store.robot("r0").next_seq == 5 and not any(store.robot("r0").has_scan)


def test_store_with_a_database_keeps_a_bounded_number_of_scans(tmp_path: Path) -> None:
    """With a database, a committed keyframe's scan leaves memory beyond `capacity`
    and is read back unchanged when asked for; an uncommitted one never leaves."""
    db = KeyframeDatabase(tmp_path / "base.db", synchronous="OFF")
    store = KeyframeStore(points_cache=10, scans=ScanArchive(db.scan_reader(), capacity=100))
    kfs = _tour("r0", 700)  # for comparison; the store gets fresh copies
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    fresh = _tour("r0", 600)
    for k in range(0, 600, 50):  # batches admitted, committed, then marked saved
        batch = Batch([kf for kf in fresh[k : k + 50] if store.admit(kf)])
        db.commit(batch)
        store.saved([(kf.robot_id, kf.seq) for kf in batch.keyframes])
    del fresh, batch
    gc.collect()
    grown = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    # 100 scans (2.2 kB each) and < 200 bytes per keyframe (all 600 scans: > 1.3 MB)
    assert grown < 100 * (2 * BEAMS + 400) + 600 * 200, grown
    assert store.scan_archive.in_memory == 100 and store.scan_archive.reads == 0
    for i in (0, 250, 599):  # old ones from the database, as sent
        np.testing.assert_array_equal(store.scan("r0", i).ranges_mm, kfs[i].scan2d.ranges_mm)
        assert store.scan("r0", i).angle_increment == kfs[i].scan2d.angle_increment
    assert store.scan_archive.reads == 2  # 599 was still in memory
    np.testing.assert_array_equal(store.points("r0", 3), scan_points(kfs[3].scan2d))
    for kf in kfs[600:]:  # admitted, not committed: kept whatever the capacity
        assert len(store.admit(kf)) == 1
    reads = store.scan_archive.reads
    assert [s.ranges_mm.tobytes() for s in store.scans([("r0", i) for i in range(600, 700)])] == [
        kf.scan2d.ranges_mm.tobytes() for kf in kfs[600:]
    ]
    assert store.scan_archive.reads == reads
    db.close()


def _settle(node: BaseStationNode) -> None:
    """Let the verification worker finish its jobs (their memory is in flight) and
    take its results in."""
    for _ in range(600):
        if node.slam.idle():
            break
        time.sleep(0.05)
    assert node.slam.idle()
    node.step(timeout=0.0)


def test_node_does_not_grow_while_no_keyframe_arrives(cfg: Config, endpoint: str) -> None:
    cfg.zenoh.listen = [endpoint]
    cfg.basestation.map_update_period_s = 0.0
    # exploration steps by count, not by the wall clock (1 s): how many of them fall in
    # the warm-up and how many in the measured steps must not depend on machine load
    cfg.exploration.period_s = 1e9
    kfs = _tour("r0", 120)
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node = BaseStationNode(cfg, bus, None)
        for k in range(0, len(kfs), 20):
            node.process(kfs[k : k + 20])
            node.refresh_map()
        node.map.finish()
        pose = kfs[-1].pose_odom
        state = RobotState("r0", 60.0, "holding", node.epochs.current, 120, 119, 0, pose, pose)
        _settle(node)
        tracemalloc.start()  # before the warm-up: what it frees must be counted too
        for k in range(50):  # warm up caches (logging, zenoh publishers, exploration)
            node._on_state(state, "")
            node.process([kfs[-1]])
            node.step(timeout=0.0)
            if k % 5 == 4:
                node.explore()
        _settle(node)
        gc.collect()
        before = tracemalloc.get_traced_memory()[0]
        for k in range(500):  # hovering: states and resent (duplicate) keyframes only
            node._on_state(state, "")
            node.process([kfs[-1]])
            node.step(timeout=0.0)
            if k % 50 == 49:  # exploring now and then (its latencies: a bounded deque)
                node.explore()
        _settle(node)
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.stop()
        assert node.slam.store.robot("r0").duplicates == 550
        assert node.slam.graph.num_nodes("r0") == 120
        node.drain(1.0)
        json.dumps(node.stats())  # plain numbers
    assert abs(grown) < 8_000, grown  # nothing per step (a leak: >= 500 x 32 B)


def test_full_inbox_drops_and_the_agents_resends_fill_the_gap(cfg: Config, endpoint: str) -> None:
    """A base station that is behind holds at most INBOX_MAX keyframes; what it drops is
    still in the agent's outbox (not acknowledged), and once sent again every keyframe
    ends up in the graph exactly once."""
    cfg.zenoh.listen = [endpoint]
    kfs = _tour("r0", 60)
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node = BaseStationNode(cfg, bus, None)
        node.inbox = KeyframeInbox(max_keyframes=25)
        accepted = [node.inbox.put(kf) for kf in kfs]  # all arrive while it is busy
        assert accepted == [True] * 25 + [False] * 35
        assert len(node.inbox) == 25 and node.inbox.drops == 35
        while node.step(timeout=0.0):
            pass
        store = node.slam.store
        assert store.acked_seq("r0") == 24  # the ack tells the agent where to resume
        rest = kfs[store.acked_seq("r0") + 1 :]  # the outbox sends the rest again
        for k in range(0, len(rest), 20):
            assert all(node.inbox.put(kf) for kf in rest[k : k + 20])
            while node.step(timeout=0.0):
                pass
        assert node.slam.graph.num_nodes("r0") == 60 and store.robot("r0").duplicates == 0
        assert node.stats()["inbox_drops"] == 35
        node.drain(1.0)
