"""A robot's trajectory segments: each run of its agent (`session`) is a robot of the
pose graph of its own (`r0`, `r0~2`, ...), its keyframes admitted and acknowledged to
that run, kept across a base-station restart. Before, a second run's keyframes were
refused for good (their seqs clashed with the first run's). End to end with real
processes: tests/test_agent_restart.py."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from process_helpers import poll_until, synthetic_keyframe

from agent.fresh_start import FreshStart, nearest_waypoint
from agent.resume import ResumePoint
from agent.uplink import KeyframeUplink
from basestation.global_slam import GlobalSlam
from basestation.node import BaseStationNode
from basestation.robot_segments import RobotSegments, as_sent, robot_of
from common.bus import Bus
from common.config import Config, ZenohConfig, load_config
from common.geometry import se2_compose, se2_inverse
from protocol import Keyframe, KeyframeAck, OdomOrigin, PoseCorrection, RobotState, encode


def _kf(seq: int, session: int, t0: float = 0.0) -> Keyframe:
    kf = synthetic_keyframe("r0", seq, np.array([0.5 * seq, 0.0, 0.0]), np.array([0.5, 0, 0]))
    return dataclasses.replace(kf, stamp=t0 + kf.stamp, session=session)


def test_each_run_of_an_agent_is_a_segment_of_its_robot() -> None:
    seg = RobotSegments()
    assert seg.segment("r0", 11) == ("r0", None)
    assert seg.segment("r1", 12) == ("r1", None)
    assert seg.segment("r0", 11) == ("r0", None)  # the same run
    assert seg.segment("r0", 22) == ("r0~2", "r0")  # a new run: r0 is past
    assert seg.segment("r0", 11) == ("r0", None)  # the old run still sends: still its own
    assert seg.current("r0") == "r0~2" and seg.current("r1") == "r1"
    assert seg.current("r7") == "r7"  # not heard from yet
    ack = seg.address(KeyframeAck("r0~2", 4))
    assert (ack.robot_id, ack.session, ack.acked_seq) == ("r0", 22, 4)
    assert seg.address(KeyframeAck("r0", 4)).session == 11
    assert robot_of("r0~2") == robot_of("r0") == "r0"
    kf = _kf(0, 22)
    assert encode(as_sent(dataclasses.replace(kf, robot_id="r0~2"))) == encode(kf)
    assert as_sent(kf) is kf
    assert seg.stats() == {"r0": {"r0": 11, "r0~2": 22}}
    assert seg.served("r0~2") and seg.served("r0")  # r0's run was heard just now
    seg._heard["r0"] -= 31.0  # quiet for 31 s: dead (restarted), not another drone
    assert not seg.served("r0") and seg.served("r0~2") and seg.served("r1")
    again = RobotSegments()  # a base station restarted on its database
    again.restore({"r0~2": 22, "r1": 12, "r0": 11})  # r0~2 admitted first (two drones)
    assert again.segment("r0", 22) == ("r0~2", None) and again.current("r0") == "r0~2"
    assert again.segment("r0", 33) == ("r0~3", "r0~2")


def test_an_agent_takes_what_is_sent_to_its_session(cfg: Config) -> None:
    got: list[int] = []
    with Bus(ZenohConfig(), cfg.fleet) as bus:
        up = KeyframeUplink(cfg.agent, "r0", bus)
        on = up.mine(lambda m, k: got.append(m.session))
        for session in (up.session, 0, up.session ^ 1):
            on(PoseCorrection("r0", 1, 0.0, np.array([0, 0, 0, 0, 0, 0, 1.0]), session), "")
    assert 0 < up.session < 2**32 and got == [up.session, 0]
    assert up.stats()["other_session_drops"] == 1


def test_base_station_maps_a_second_run_and_keeps_it(
    cfg: Config, endpoint: str, tmp_path: Path
) -> None:
    """A robot's agent restarted afresh sends seq 0 again in a new session: mapped as
    r0~2 and acknowledged to that session (before: refused as another source, and
    nothing more of the robot mapped); a restart of the base station keeps both."""
    cfg.zenoh.listen = [endpoint]
    cfg.basestation.db_path = str(tmp_path / "base.db")
    acks: list[KeyframeAck] = []
    with Bus(cfg.zenoh, cfg.fleet) as bus:
        node = BaseStationNode(cfg, bus, None)
        node.start()
        with Bus(ZenohConfig(connect=[endpoint]), cfg.fleet) as agent:
            agent.subscribe(agent.keys.robot("r0", "ack"), KeyframeAck, lambda m, k: acks.append(m))
            agent.declare_alive("agent", "r0")  # after the subscription: it implies its route
            assert poll_until(lambda: node.links.get("r0", {}).get("joins") == 1)
            for session, t0 in ((11, 0.0), (22, 100.0)):  # the second run, later
                state = RobotState("r0", t0, "flying", -1, 0, 0, 0, _kf(0, 0).pose_odom,
                                   _kf(0, 0).pose_odom, session=session)  # fmt: skip
                node._on_state(state, "")
                for seq in range(5):
                    node.inbox.put(node._to_segment(_kf(seq, session, t0)))
                node.step()

                def acked(s: int = session) -> bool:
                    return any(a.session == s and a.acked_seq == 4 for a in acks)

                assert poll_until(acked), acks
            store = node.slam.store
            assert [store.acked_seq(r) for r in ("r0", "r0~2")] == [4, 4]
            assert not store.robot("r0").foreign and not store.robot("r0~2").foreign
            assert set(node.states) == {"r0~2"}  # the first run's state forgotten
            assert node.stats()["robot_segments"] == {"r0": {"r0": 11, "r0~2": 22}}
        node.drain(2.0)
    with Bus(cfg.zenoh, cfg.fleet) as bus:  # restarted on its database
        again = BaseStationNode(cfg, bus, None)
        again.recover()
        assert again.recovered["in_graph"] == {"r0": 5, "r0~2": 5}
        assert again.segments.segment("r0", 22) == ("r0~2", None)
        again.drain(1.0)


def test_a_later_segment_starts_where_the_one_before_left_off() -> None:
    """r0~2 began in flight 4 m along its odometry's frame, which r0 began at: its first
    node is placed by r0's T_map_odom and both origins, loosely, and it takes GNSS fixes
    as r0 does. Before, it floated, and a hovering drone's matches from one place never
    joined it to the map. A run that began where its odometry did floats."""
    cfg = load_config(
        overrides={
            "basestation.gps.enabled": True,
            "basestation.gps.batch_period_s": 0.0,
            "basestation.constraints.enabled": False,
        }
    )
    start = np.array([2.0, 1.0, 0.5])
    slam = GlobalSlam(cfg, {"r0": start})
    for seq in range(10):  # along x in its odom frame; the odometry drifts from it
        origin = OdomOrigin(3.0 + 0.02 * seq, -1.0, 0.8 + 0.01 * seq)
        slam.admit(dataclasses.replace(_kf(seq, 11), odom_origin=origin))
    slam.optimize()
    latest = [origin.x, origin.y, origin.yaw]  # paired with r0's latest T_map_odom

    def run(origin: OdomOrigin | None) -> list[Keyframe]:  # from the identity, new session
        return [dataclasses.replace(_kf(j, 22, 100.0), robot_id="r0~2", odom_origin=origin)
                for j in range(4)]  # fmt: skip

    for kf in run(OdomOrigin(4.0, 2.0, -0.3)):
        slam.admit(kf)
    slam.optimize()
    assert slam.graph.is_anchored("r0~2")
    source = se2_compose(slam.T_map_odom("r0"), se2_inverse(latest))  # its frame in map
    expected = se2_compose(source, [4.0, 2.0, -0.3])  # no matches yet: the prior holds
    np.testing.assert_allclose(slam.T_map_odom("r0~2"), expected, atol=1e-6)
    slam.add_gps_fix("r0~2", 104.5, np.array([5.0, 3.5]), np.array([1.5, 1.5, 3.0]))
    assert slam.stats()["gps"]["fixes_ignored"] == 0  # georeferenced as r0 is
    for origin in (OdomOrigin(0.3, 0.0, 0.0), None):  # began where its odometry did: floats
        other = GlobalSlam(cfg, {"r0": start})
        for kf in [dataclasses.replace(_kf(s, 11), odom_origin=OdomOrigin(3, -1, 0.8)) for s
                   in range(3)] + run(origin):  # fmt: skip
            other.admit(kf)
        assert not other.graph.is_anchored("r0~2") and other.T_map_odom("r0~2") is None


def test_segments_beyond_the_graphs_chains_are_refused(caplog) -> None:
    """The 27th run had raised out of the base station's loop (26 chains), and again
    after every restart on its database."""
    seg = RobotSegments(capacity=3)
    assert [seg.segment("r0", s)[0] for s in (1, 2, 3, 4, 4)] == ["r0", "r0~2", "r0~3", None, None]
    assert seg.refused == {("r0", 4)} and caplog.text.count("is not mapped") == 1
    assert seg.refused_runs() == {"r0": [4]}  # (in basestation.json and summary.json)
    assert RobotSegments().capacity == 62


def test_a_fresh_agent_waits_for_its_odometry_and_knows_it_is_in_flight() -> None:
    """A scan before any odometry had started the agent's frame unplaced on the
    source's, and a drone restarted in flight had flown its tour from the first
    waypoint, into a wall. Its scans are taken meanwhile; its first keyframe waits."""
    f, here = FreshStart.of(None), np.array([0.1, 0.0, 1.0, 0.0])  # local pose at the scans
    assert not f.take(10.0, None, None, here) and not f.begun  # no odometry yet
    assert not f.take(10.1, np.array([6.1, 2.0, 0.3]), None, here) and f.begun
    source_at_origin = se2_compose([6.1, 2.0, 0.3], [-0.1, 0.0, 0.0])  # at local (0, 0, 0)
    np.testing.assert_allclose(f.as_list(), source_at_origin)
    assert not f.settled and f.take(10.2, np.array([6.1, 2.0, 0.3]), 1.0, here)  # airborne
    assert f.settled and f.in_flight
    T = f.start_in_map(np.array([1.0, 1.0, 1.0, 0.0]))  # the start pose: the source's frame
    np.testing.assert_allclose(T, [*(source_at_origin[:2] + 1.0), 1.0, 0.3])
    tour = np.array([[0.0, 0.0], [7.5, 3.0], [20.0, 0.0]])
    assert nearest_waypoint(tour, T[:2]) == 1 and nearest_waypoint(np.zeros((0, 2)), T[:2]) == 0
    ground = FreshStart.of(None)  # carried from where the autopilot began: not a restart
    assert not ground.take(0.0, np.array([6.0, 2.0, 0.3]), 0.0, np.zeros(4))
    assert ground.settled and not ground.in_flight and ground.origin is not None
    blind = FreshStart.of(None)  # no odometry source and no altimeter: on after ODOM_WAIT_S
    assert not blind.take(0.0, None, None, np.zeros(4)) and not blind.begun
    assert not blind.take(0.6, None, None, np.zeros(4)) and blind.begun and blind.settled
    assert blind.origin is None and not blind.in_flight
    resumed = FreshStart.of(ResumePoint(odom_origin=[1.0, 2.0, 3.0]))
    assert resumed.settled and resumed.as_list() == [1.0, 2.0, 3.0]


def test_a_new_base_station_places_a_run_begun_in_flight_along_its_odometry(caplog) -> None:
    """A base station started on an empty database (a new laptop) first hears a drone's
    run that began in flight (its agent restarted afresh): it had placed that run at the
    drone's known start pose, 4-10 m off, and the drone flew by it into walls. The run
    starts where its odometry says, loosely, as the agent itself takes it."""
    cfg = load_config(overrides={"basestation.constraints.enabled": False})
    start = np.array([2.0, 1.0, 0.5])
    slam = GlobalSlam(cfg, {"r0": start})
    for seq in range(4):
        slam.admit(dataclasses.replace(_kf(seq, 22), odom_origin=OdomOrigin(6.0, -2.0, 0.3)))
    slam.optimize()
    expected = se2_compose(start, [6.0, -2.0, 0.3])
    np.testing.assert_allclose(slam.T_map_odom("r0"), expected, atol=1e-6)
    assert "began in flight, 6.3 m along its odometry" in caplog.text
