"""GNSS fixes over real Zenoh into the base station's graph (basestation.gps.enabled)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from basestation.global_slam import GlobalSlam
from basestation.node import BaseStationNode
from common.bus import Bus
from common.config import Config, ZenohConfig, load_config
from common.geodesy import GeoOrigin, enu_to_geodetic
from common.geometry import pose4_to_pose7
from common.map_io import GridMap, write_map
from common.scenario import RobotScenario, Scenario
from protocol import GnssFix, Keyframe, Scan2D

ORIGIN = GeoOrigin(45.8118, 16.0106, 160.0)
SIG = np.array([1.5, 1.5, 3.0])


def _cfg(**extra: object) -> Config:
    return load_config(
        overrides={
            "basestation.gps.enabled": True,
            "basestation.gps.batch_period_s": 0.0,
            "basestation.constraints.enabled": False,
            **extra,
        }
    )


def _keyframe(seq: int) -> Keyframe:
    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = 2.0 / np.maximum(np.cos(angles), 0.2)
    return Keyframe(
        "r0",
        seq,
        0.5 * seq,
        pose4_to_pose7([0.2 * seq, 0, 1, 0]),
        pose4_to_pose7([0.2 if seq else 0.0, 0, 0, 0]),
        np.eye(6) * 1e-4,
        Scan2D.from_ranges(-np.pi / 2, np.pi / 180, 30.0, ranges),
        None,
    )


def _fix(t: float, east: float, north: float) -> GnssFix:
    return GnssFix("r0", t, enu_to_geodetic([east, north, 1.0], ORIGIN), SIG)


def test_global_slam_turns_fixes_into_factors() -> None:
    slam = GlobalSlam(_cfg(), {"r0": np.zeros(3)})
    slam.add_gps_fix("r0", 0.0, np.zeros(2), SIG)  # before the first keyframe: waits for it
    for seq in range(20):
        slam.admit(_keyframe(seq))
        slam.add_gps_fix("r0", 0.5 * seq - 0.25, np.array([0.1 * seq - 0.05, 0.0]), SIG)
        slam.optimize()
    stats = slam.stats()["gps"]
    assert stats["fixes_ignored"] == 0 and stats["gps_factors"] == 20
    assert stats["gps_dropped_before_start"] == 1  # the one at -0.25 s
    np.testing.assert_allclose(slam.graph.poses("r0")[-1, :2], [3.8, 0.0], atol=0.05)


def test_fixes_travel_over_zenoh_to_the_graph(tmp_path: Path, endpoint: str) -> None:
    grid = GridMap(np.zeros((10, 10), np.int8), 0.1, (0.0, 0.0, 0.0), wgs84_origin=ORIGIN)
    write_map(grid, tmp_path / "w.yaml")
    scenario = Scenario(str(tmp_path / "w.yaml"), [RobotScenario("r0", np.zeros(3))])
    cfg = _cfg()
    with Bus(ZenohConfig(listen=[endpoint]), "default") as base_bus:
        node = BaseStationNode(cfg, base_bus, scenario)
        node.start()
        assert node.gnss.origin == ORIGIN
        with Bus(ZenohConfig(connect=[endpoint]), "default") as robot_bus:
            time.sleep(0.5)
            kf_key = robot_bus.keys.robot("r0", "keyframe")
            gnss_key = robot_bus.keys.sensor("r0", "gnss")
            for seq in range(10):
                robot_bus.publish(kf_key, _keyframe(seq))
                robot_bus.publish(gnss_key, _fix(0.5 * seq + 0.25, 0.1 * seq + 0.05, 0.0))
            deadline = time.monotonic() + 15.0
            while time.monotonic() < deadline:
                node.step(timeout=0.05)
                gps = node.slam.graph.gps_stats()
                if gps["gps_factors"] >= 9 and gps["gps_pending"] >= 1:
                    break  # the last fix can come in after the last keyframe was taken
        stats = node.stats()
        assert stats["gps"]["gps_factors"] == 9  # the fix after the last keyframe waits
        assert stats["gps"]["gps_pending"] == 1
        node.write_outputs(tmp_path / "out")
    text = (tmp_path / "out" / "trajectories" / "r0.tum").read_text()
    assert "# wgs84_origin: 45.8118 16.0106 160.0" in text


def test_fixes_of_robots_without_known_start_are_ignored() -> None:
    slam = GlobalSlam(_cfg(), {})  # the first robot defines map: not an ENU frame
    for seq in range(5):
        slam.admit(_keyframe(seq))
        slam.add_gps_fix("r0", 0.5 * seq - 0.25, np.array([0.1 * seq, 0.0]), SIG)
    slam.optimize()
    assert slam.stats()["gps"]["fixes_ignored"] == 5
    assert slam.graph.gps_stats()["gps_factors"] == 0


def test_known_heading_starts_the_robot_at_its_fix() -> None:
    # seed 000 III-C: no start pose, the autopilot's heading (here 0.5 rad) and GNSS fixes
    heading = 0.5
    slam = GlobalSlam(_cfg(), {}, {"r0": heading, "r1": 0.0})
    truth0 = np.array([12.0, -7.0])
    direction = np.array([np.cos(heading), np.sin(heading)])
    slam.add_gps_fix("r0", -0.1, truth0 + [0.8, -0.5], SIG)  # first fix, 1 m off
    rng = np.random.default_rng(0)
    for seq in range(60):
        slam.admit(_keyframe(seq))
        t = 0.5 * seq + 0.25
        slam.add_gps_fix("r0", t, truth0 + 0.4 * t * direction + rng.normal(0, 0.3, 2), SIG)
        slam.optimize()
    slam.graph.flush_gps()
    slam.optimize()
    assert slam.graph.is_anchored("r0")
    est = slam.graph.poses("r0")
    np.testing.assert_allclose(est[0, :2], truth0, atol=0.4)
    assert abs(est[-1, 2] - heading) < 0.05
    kf = _keyframe(0)
    slam.admit(Keyframe("r1", 0, 0.0, kf.pose_odom, kf.delta, kf.delta_cov, kf.scan2d, None))
    assert not slam.graph.is_anchored("r1")  # no fix yet: floats (never defines map)


def test_a_chain_starting_on_the_way_is_placed_back_from_the_latest_fix() -> None:
    """A new base station (no database) gets a robot's keyframes from the first again
    (a new chain) while its fixes are of now: the chain's first node had been put at the
    latest fix, as far off as the robot had flown since (here 10 m along its heading)."""
    heading = 0.5
    slam = GlobalSlam(_cfg(), {}, {"r0": heading})
    slam.odom_now = lambda rid: np.array([10.0, 0.0, 0.0])  # its latest state: 10 m on
    slam.add_gps_fix("r0", 100.0, np.array([30.0, 20.0]), SIG)  # where it is now
    slam.admit(_keyframe(0))  # the mission's first keyframe, at its odom origin
    np.testing.assert_allclose(
        slam.graph.poses("r0")[0], [30.0 - 10 * np.cos(heading), 20.0 - 10 * np.sin(heading),
                                    heading], atol=1e-6)  # fmt: skip
    fresh = GlobalSlam(_cfg(), {}, {"r0": heading})  # no state yet: the first node at the fix
    fresh.add_gps_fix("r0", 0.0, np.array([30.0, 20.0]), SIG)
    fresh.admit(_keyframe(0))
    np.testing.assert_allclose(fresh.graph.poses("r0")[0], [30.0, 20.0, heading], atol=1e-6)


def test_a_robot_whose_first_keyframe_beats_its_first_fix_is_georeferenced_then(
    tmp_path: Path,
) -> None:
    """Fixes are held until the map's WGS84 origin is set (five fixes): a robot's first
    keyframe came first, it floated, and every later fix was ignored. With every robot
    so, nothing was ever on the map. Now its first fix puts it there, and a restart on
    the database starts it there."""
    from basestation.persistence import KeyframeDatabase

    heading = 0.5
    truth0 = np.array([12.0, -7.0])
    direction = np.array([np.cos(heading), np.sin(heading)])
    slam = GlobalSlam(_cfg(), {}, {"r0": heading})
    db = KeyframeDatabase(tmp_path / "base.db")
    for seq in range(60):
        slam.admit(_keyframe(seq))  # 0.4 m/s along its heading
        if seq >= 10:  # fixes from 5 s on
            t = 0.5 * seq + 0.25
            slam.add_gps_fix("r0", t, truth0 + 0.4 * t * direction, SIG)
        slam.optimize()
        db.commit(slam.take_journal())
    slam.graph.flush_gps()
    slam.optimize()
    assert slam.graph.is_anchored("r0") and slam.gps_fixes_ignored == 0
    assert slam.graph.gps_stats()["gps_factors"] > 40
    est = slam.graph.poses("r0")
    np.testing.assert_allclose(est[0, :2], truth0, atol=0.5)
    assert abs(est[-1, 2] - heading) < 0.05
    db.close()
    back = GlobalSlam(_cfg(), {}, {"r0": heading})
    back.restore(KeyframeDatabase(tmp_path / "base.db").load())
    assert back.graph.is_anchored("r0") and back.gps_fixes_ignored == 0
    np.testing.assert_allclose(back.graph.poses("r0")[0], est[0], atol=0.1)


def test_time_going_backwards_does_not_stop_the_graph() -> None:
    """Keyframe 3 claims an older time, or keyframe 2 one in ms (1.7e12 s, where 1e-6 s
    more is the same float: "node stamps must increase" had stopped the base station,
    and again after each restart)."""
    for glitch in ({3: 1.0}, {2: 1.7e12}):
        slam = GlobalSlam(_cfg(), {"r0": np.zeros(3)})
        for seq in range(5):
            kf = _keyframe(seq)
            stamp = glitch.get(seq, kf.stamp)
            slam.admit(
                Keyframe("r0", seq, stamp, kf.pose_odom, kf.delta, kf.delta_cov, kf.scan2d, None)
            )
        slam.optimize()
        assert slam.graph.num_nodes("r0") == 5


def test_origin_from_the_first_fixes_median_and_far_fixes_dropped() -> None:
    """Taken from the first fix, one bad fix (-45, -170) had set the map's origin for
    good; a fix 465 km off had pulled its robot there and the map allocated TiB."""
    from basestation.gnss_intake import ORIGIN_FIXES, GnssIntake

    intake = GnssIntake(None, 1000.0)
    bad = GnssFix("r0", 0.0, np.array([-45.0, -170.0, 0.0]), SIG)
    assert intake.take(bad) == [] and intake.origin is None
    got = [intake.take(_fix(0.1 * k, 2.0 * k, 1.0)) for k in range(1, ORIGIN_FIXES)]
    assert got[:-1] == [[]] * (ORIGIN_FIXES - 2) and intake.dropped == 1  # the bad one
    east = [xy[0] for _, xy in got[-1]]
    assert len(east) == ORIGIN_FIXES - 1 and abs(np.ptp(east) - 2.0 * (ORIGIN_FIXES - 2)) < 1e-6
    far = GnssFix("r0", 1.0, enu_to_geodetic([465e3, 0.0, 1.0], ORIGIN), SIG)
    assert intake.take(far) == [] and intake.dropped == 2
    assert len(intake.take(_fix(1.1, 3.0, 1.0))) == 1
    known = GnssIntake(ORIGIN, 1000.0)  # the world's origin: fixes go at once
    ((f, xy),) = known.take(_fix(0.0, 3.0, 4.0))
    assert np.allclose(xy, [3.0, 4.0], atol=1e-6)


def test_no_fix_outputs_have_no_say_in_the_origin() -> None:
    """A receiver's output before lock: (0, 0) with ~4e6 m sigmas. Three of the first
    five had set the map's origin in the sea, stored for good, every real fix then
    dropped as 4,700 km away."""
    from basestation.gnss_intake import ORIGIN_FIXES, GnssIntake
    from common.errors import ProtocolError

    with pytest.raises(ProtocolError, match="without a fix"):
        GnssFix("r0", 0.0, np.array([0.0, 0.0, 0.0]), np.full(3, 4.3e6)).validate()
    intake = GnssIntake(None, 1000.0)
    unsure = GnssFix("r0", 0.0, enu_to_geodetic([3e5, 0.0, 1.0], ORIGIN), np.full(3, 4.3e4))
    for _ in range(3):
        assert intake.take(unsure) == []
    for k in range(ORIGIN_FIXES):
        got = intake.take(_fix(0.1 * k, 1.0, 2.0))
    assert intake.origin is not None and abs(intake.origin.lat_deg - ORIGIN.lat_deg) < 1e-3
    assert len(got) == ORIGIN_FIXES and intake.dropped == 3  # the unsure ones, 300 km off


def test_a_later_run_matched_onto_the_georeferenced_map_uses_its_fixes() -> None:
    """A drone's second flight (its agent restarted afresh) starts a new run of it,
    which floats until matches join it to the map; its fixes had all been ignored
    even then (outdoors, where matches are scarce, the fixes matter most)."""
    import dataclasses

    slam = GlobalSlam(_cfg(), {"r0": np.zeros(3)})
    for seq in range(10):
        slam.admit(_keyframe(seq))
        slam.optimize()
    later = "r0~2"
    for seq in range(10):
        slam.admit(dataclasses.replace(_keyframe(seq), robot_id=later, session=1))
    slam.optimize()
    assert not slam.graph.is_anchored(later)
    slam.add_gps_fix(later, 2.25, np.array([0.9, 0.0]), SIG)  # floating: not usable
    assert slam.gps_fixes_ignored == 1
    for k in (3, 6, 9):  # matches put it on the map (as the loop-closure manager would)
        slam.graph.add_constraint(("r0", k), (later, k), [0.0, 0.0, 0.0], np.eye(3) * 1e-4)
    slam.graph.update()
    for seq in range(10, 30):
        slam.admit(dataclasses.replace(_keyframe(seq), robot_id=later, session=1))
        slam.add_gps_fix(later, 0.5 * seq - 0.25, np.array([0.2 * seq - 0.1, 0.0]), SIG)
        slam.optimize()
    assert slam.gps_fixes_ignored == 1 and slam.stats()["gps"]["gps_factors"] >= 18


def test_gps_options_reach_the_pose_graph() -> None:
    """Every [basestation.gps] choice (weighting, a, b, huber, sigma_min_m, the antenna's
    lever arm) reaches the graph's GPS factors: replacing the wiring with the defaults
    had passed every test (`bench gps` builds its weighting directly)."""
    from basestation.isam2_params import pose_graph_options

    cfg = load_config(
        overrides={
            "basestation.gps.enabled": True,
            "basestation.gps.weighting": "isotropic",
            "basestation.gps.a": 2.0,
            "basestation.gps.b": 0.5,
            "basestation.gps.huber": False,
            "basestation.gps.sigma_min_m": 0.3,
            "basestation.gps.antenna_x_m": 0.25,
            "basestation.gps.antenna_y_m": -0.1,
        }
    )
    w = pose_graph_options(cfg.basestation)["gps_weighting"]
    assert (w.mode, w.a, w.b, w.huber_k, w.sigma_min_m) == ("isotropic", 2.0, 0.5, None, 0.3)
    assert tuple(w.lever_arm) == (0.25, -0.1)


def test_a_heading_robot_matched_onto_the_map_before_its_first_fix_keeps_its_fixes() -> None:
    """Two robots started from a heading, their first keyframes before any fix, joined
    by matches while floating: at r0's first fix the map is put in ENU, r1 with it. r1's
    fixes had then all been ignored for the rest of the mission."""
    import dataclasses

    slam = GlobalSlam(_cfg(), {}, {"r0": 0.0, "r1": 0.0})
    for seq in range(10):  # both fly along x, r1 2 m to the left; no fix yet
        for rid in ("r0", "r1"):
            slam.admit(dataclasses.replace(_keyframe(seq), robot_id=rid))
        slam.optimize()
    for k in (3, 6, 9):  # matches join their maps (as the loop-closure manager would)
        slam.graph.add_constraint(("r0", k), ("r1", k), [0.0, 2.0, 0.0], np.eye(3) * 1e-4)
    slam.graph.update()
    for seq in range(10, 40):
        t = 0.5 * seq + 0.25
        for rid, y in (("r0", 0.0), ("r1", 2.0)):
            slam.admit(dataclasses.replace(_keyframe(seq), robot_id=rid))
            slam.add_gps_fix(rid, t, np.array([0.2 * seq + 10.0, y - 5.0]), SIG)
        slam.optimize()
    slam.graph.flush_gps()
    slam.optimize()
    assert slam.graph.is_anchored("r1") and slam.gps_fixes_ignored == 0
    assert np.allclose(slam.graph.poses("r1")[-1, :2], [0.2 * 39 + 10.0, -3.0], atol=0.5)


def test_fixes_are_not_taken_where_the_map_is_not_enu(
    tmp_path: Path, endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Known starts on a world with no WGS84 origin: the map is the world frame, but where
    it is on Earth is not known. The first fixes' median had been taken for the world's
    (0, 0), and a robot starting at (20, 10) was bent 3.25 m and 21 degrees. Without a
    scenario the map is the first robot's odom frame: its files had claimed a WGS84
    georeference. Now the fixes are ignored, named once, and no file claims one."""
    grid = GridMap(np.zeros((10, 10), np.int8), 0.1, (0.0, 0.0, 0.0))  # no wgs84_origin
    write_map(grid, tmp_path / "w.yaml")
    start = np.array([20.0, 10.0, 0.0])
    scenario = Scenario(str(tmp_path / "w.yaml"), [RobotScenario("r0", start)])
    for sc, why in ((scenario, "whose WGS84 origin is not known"), (None, "without a scenario")):
        caplog.clear()
        with Bus(ZenohConfig(listen=[endpoint]), "default") as bus, caplog.at_level("ERROR"):
            node = BaseStationNode(_cfg(), bus, sc)
            for seq in range(30):
                node._on_keyframe(_keyframe(seq), "k")
                t = 0.5 * seq + 0.25
                node.gnss_inbox.put(_fix(t, start[0] + 0.4 * t, start[1]))
                node.step(timeout=0.01)
            node.step(timeout=0.01)
            stats = node.stats()
            assert stats["gps"]["gps_factors"] == 0 and stats["gnss_fixes_not_enu"] == 30
            assert node.gnss.origin is None
            node.write_outputs(tmp_path / "out")
        assert caplog.text.count("GNSS fixes ignored") == 1 and why in caplog.text
        est = node.slam.graph.poses("r0")[-1, :2]
        if sc is not None:  # the world frame: where the known start and odometry put it
            assert np.allclose(est, start[:2] + [0.2 * 29, 0.0], atol=0.05)
        assert "wgs84_origin" not in (tmp_path / "out" / "trajectories" / "r0.tum").read_text()
        assert "wgs84_origin" not in (tmp_path / "out" / "map.yaml").read_text()


def test_the_ground_truth_is_georeferenced_where_the_fixes_are_made(
    tmp_path: Path, endpoint: str
) -> None:
    """A scenario's own WGS84 origin: the simulator makes its fixes there, and its ground
    truth had named the world YAML's origin (45.8118, 16.0106) instead."""
    from common.trajectory_io import read_tum
    from simulation.simulator import Simulator
    from simulation.world import World

    own = GeoOrigin(46.0, 15.0, 200.0)
    cfg = load_config(overrides={"sim.gnss.enabled": True})
    sc = Scenario("bshape", [RobotScenario("r0", np.array([1.0, 1.0, 0.0]))], 0, own)
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        sim = Simulator(cfg, bus, sc, World.load("bshape"), 1.0)
        assert sim.robots["r0"].gnss.origin == own
        sim.robots["r0"].gt.append([0.0, 1.0, 1.0, 1.0, 0.0])
        sim.write_outputs(tmp_path)
    assert read_tum(tmp_path / "ground_truth" / "r0.tum").wgs84_origin == own


def test_fixes_an_earlier_version_stored_are_not_replayed_where_the_map_is_not_enu(
    tmp_path: Path, endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A database written before fixes were ignored on a map that is not ENU: restored,
    its stored fixes had been replayed as GPS factors, and the bend stayed (4.99 m)."""
    from basestation.persistence import KeyframeDatabase

    grid = GridMap(np.zeros((10, 10), np.int8), 0.1, (0.0, 0.0, 0.0))  # no wgs84_origin
    write_map(grid, tmp_path / "w.yaml")
    start = np.array([20.0, 10.0, 0.0])
    old = GlobalSlam(_cfg(), {"r0": start})  # as the earlier version took them
    db = KeyframeDatabase(tmp_path / "base.db")
    for seq in range(10):
        old.admit(_keyframe(seq))
        old.add_gps_fix("r0", 0.5 * seq + 0.25, np.array([0.2 * seq, 0.0]), SIG)
        db.commit(old.take_journal())
    old.close()
    db.close()
    assert len(KeyframeDatabase(tmp_path / "base.db").load().fixes) == 10
    cfg = _cfg()
    cfg.basestation.db_path = str(tmp_path / "base.db")
    scenario = Scenario(str(tmp_path / "w.yaml"), [RobotScenario("r0", start)])
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus, caplog.at_level("WARNING"):
        node = BaseStationNode(cfg, bus, scenario)
        node.recover()
        assert node.slam.graph.num_gps_factors == 0 and node.slam.graph.is_anchored("r0")
        node.db.close()
    assert "10 stored GNSS fixes not replayed" in caplog.text


def test_a_mission_with_gps_resumes_with_gps_off_and_keeps_its_origin(
    tmp_path: Path, endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Restarted with basestation.gps.enabled off (a misbehaving receiver), the base
    station had replayed the stored fixes onto nodes without stamps and exited, at
    every restart. And a world whose WGS84 origin changed between two starts had put
    the new fixes 111 m from the stored ones, without a word."""
    from basestation.gnss_intake import GnssIntake
    from basestation.persistence import KeyframeDatabase

    start = np.array([1.0, 2.0, 0.0])
    old = GlobalSlam(_cfg(), {"r0": start})
    db = KeyframeDatabase(tmp_path / "base.db")
    for seq in range(10):
        old.admit(_keyframe(seq))
        old.add_gps_fix("r0", 0.5 * seq + 0.25, np.array([1.0 + 0.2 * seq, 2.0]), SIG)
        old.optimize()
        db.commit(old.take_journal())
    old.close()
    db.close()
    cfg = _cfg(**{"basestation.gps.enabled": False})
    cfg.basestation.db_path = str(tmp_path / "base.db")
    scenario = Scenario("bshape", [RobotScenario("r0", start)], wgs84_origin=ORIGIN)
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus, caplog.at_level("WARNING"):
        node = BaseStationNode(cfg, bus, scenario)
        node.recover()
        assert node.slam.graph.num_nodes("r0") == 10 and node.slam.graph.num_gps_factors == 0
        node.db.close()
    assert "10 stored GNSS fixes not replayed: basestation.gps.enabled is off" in caplog.text
    moved = GeoOrigin(ORIGIN.lat_deg + 0.001, ORIGIN.lon_deg, ORIGIN.alt_m)  # 111 m north
    intake = GnssIntake(moved, 1000.0)
    intake.restore(ORIGIN.as_list())
    assert intake.origin == ORIGIN and "111.2 m from the one this mission's" in caplog.text
    same = GnssIntake(ORIGIN, 1000.0)
    same.restore(ORIGIN.as_list())
    assert same.origin == ORIGIN
