"""Agent outbox, keyframe selection and the base station's in-order admission."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from agent.keyframe_selector import KeyframeSelector
from agent.outbox import Outbox
from agent.path_follower import PathFollower
from basestation.keyframe_store import KeyframeStore
from common.geometry import pose4_to_pose7
from protocol import Keyframe, Scan2D


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_outbox_acks_and_resends_in_order() -> None:
    clock = FakeClock()
    ob = Outbox(max_len=10, warn_fraction=0.8, resend_timeout_s=1.0, resend_batch=3, clock=clock)
    for s in range(5):
        ob.add(s, bytes([s]))
    assert ob.due_for_resend() == []
    clock.t = 1.5
    assert ob.due_for_resend() == [b"\x00", b"\x01", b"\x02"]
    assert ob.due_for_resend() == []  # timer restarted
    assert ob.ack(2) == 3 and len(ob) == 2 and ob.acked_seq == 2
    assert ob.ack(1) == 0  # a stale ack changes nothing
    # an ack past anything queued (a broken or hostile sender) would release keyframes
    # the base station never had: ignored
    assert ob.ack(10**9) == 0 and len(ob) == 2 and ob.acked_seq == 2 and ob.bad_acks == 1
    clock.t = 3.0
    assert ob.due_for_resend() == [b"\x03", b"\x04"]
    # still no progress: the wait doubles (2 s, then 4 s), an ack resets it
    clock.t = 4.5
    assert ob.due_for_resend() == []
    clock.t = 5.1
    assert ob.due_for_resend() == [b"\x03", b"\x04"]
    clock.t = 8.5
    assert ob.due_for_resend() == []
    clock.t = 9.2
    assert len(ob.due_for_resend()) == 2
    ob.add(5, b"\x05")
    assert ob.ack(3) == 1
    clock.t = 10.3
    assert ob.due_for_resend() == [b"\x04", b"\x05"]
    with pytest.raises(ValueError):
        ob.add(9, b"x")


def test_outbox_drains_at_ack_pace_after_an_outage() -> None:
    clock = FakeClock()
    ob = Outbox(max_len=100, warn_fraction=0.8, resend_timeout_s=1.0, resend_batch=3, clock=clock)
    for s in range(8):  # sent while the base station was gone
        ob.add(s, bytes([s]))
    clock.t = 5.0
    assert ob.due_for_resend() == [b"\x00", b"\x01", b"\x02"]
    ob.ack(1)  # part of the batch: wait for the rest
    assert ob.due_for_resend() == []
    ob.ack(2)  # the whole batch: the next one goes at once, in order
    assert ob.due_for_resend() == [b"\x03", b"\x04", b"\x05"]
    ob.ack(5)
    assert ob.due_for_resend() == [b"\x06", b"\x07"]
    ob.ack(7)
    assert len(ob) == 0 and ob.due_for_resend() == []
    ob.add(8, b"\x08")  # live again: normal timeout before any resend
    assert ob.due_for_resend() == []


def test_outbox_does_not_flood_a_busy_base_station_with_duplicates() -> None:
    """The base station is slow, not cut off: it had the originals queued, so the ack
    after a resend goes past the resent batch, and nothing more is resent at once."""
    clock = FakeClock()
    ob = Outbox(max_len=100, warn_fraction=0.8, resend_timeout_s=1.0, resend_batch=3, clock=clock)
    for s in range(10):
        ob.add(s, bytes([s]))
    clock.t = 1.5
    assert ob.due_for_resend() == [b"\x00", b"\x01", b"\x02"]
    ob.ack(6)  # its queue, originals included, processed up to 6
    assert ob.due_for_resend() == []
    clock.t = 2.0
    ob.ack(8)
    assert ob.due_for_resend() == []
    assert ob.resent == 3


def test_outbox_timeout_follows_the_measured_ack_delay() -> None:
    """A base station that acks every keyframe ~3 s after it was sent is busy: the
    outbox waits longer than that before resending (RFC 6298's estimate), instead of
    queueing duplicates in front of the originals after the fixed 1 s."""
    clock = FakeClock()
    ob = Outbox(max_len=100, warn_fraction=0.8, resend_timeout_s=1.0, resend_batch=3, clock=clock)
    assert ob.timeout_s == 1.0  # nothing measured yet
    for s in range(40):  # one keyframe per 0.5 s, each acked 3 s later
        clock.t = 0.5 * s
        ob.add(s, bytes([s]))
        if s >= 6:
            ob.ack(s - 6)
            assert ob.due_for_resend() == []
    assert 3.0 <= ob.timeout_s < 6.0 and ob.resent == 0
    clock.t += 2.9  # acks stall for longer than the fixed timeout, less than the delay
    assert ob.due_for_resend() == []
    clock.t += ob.timeout_s
    assert len(ob.due_for_resend()) == 3  # stalled for real: resend
    ob.ack(36)  # its resent keyframes are not sampled (Karn): the estimate stays
    assert 3.0 <= ob.timeout_s < 6.0


def test_outbox_kick_resends_at_once() -> None:
    clock = FakeClock()
    ob = Outbox(max_len=10, warn_fraction=0.8, resend_timeout_s=1.0, resend_batch=5, clock=clock)
    ob.add(0, b"a")
    clock.t = 1.5
    assert ob.due_for_resend() == [b"a"]  # backoff now 2 s
    clock.t = 2.0
    assert ob.due_for_resend() == []
    ob.kick()  # the base station is back
    assert ob.due_for_resend() == [b"a"]


def test_outbox_after_a_kick_retries_on_the_fixed_timeout() -> None:
    """The ack delay measured before an outage (a busy base station: seconds) says
    nothing about the new link: a batch resent at once and lost while its routes formed
    was retried only that late, and the keyframes cut meanwhile overran the base
    station's reorder window."""
    clock = FakeClock()
    ob = Outbox(max_len=100, warn_fraction=0.8, resend_timeout_s=1.0, resend_batch=5, clock=clock)
    for seq in range(3):
        ob.add(seq, b"k")
        clock.t += 6.0
        ob.ack(seq)  # each acked 6 s after it was sent: a busy base station
    assert ob.timeout_s > 6.0
    ob.add(3, b"x")
    ob.add(4, b"y")  # both sent into the outage
    clock.t += 6.0
    ob.kick()  # the link is back
    assert ob.timeout_s == 1.0 and ob.due_for_resend() == [b"x", b"y"]  # lost on the way
    clock.t += 2.0
    assert ob.due_for_resend() == [b"x", b"y"]  # again after 2 x 1 s, not after 2 x > 6 s
    ob.add(5, b"z")
    ob.ack(4)  # past the batch: no delay sampled from keyframes sent into the outage
    assert ob.timeout_s == 1.0


def test_outbox_bound(caplog: pytest.LogCaptureFixture) -> None:
    """Stated policy: warn at warn_fraction, refuse new keyframes when full (the
    agent then cuts none), never drop a queued one."""
    ob = Outbox(max_len=4, warn_fraction=0.5, resend_timeout_s=1.0, resend_batch=3)
    with caplog.at_level(logging.WARNING, logger="agent.outbox"):
        ob.add(0, b"0")
        assert not caplog.records
        ob.add(1, b"1")  # half full: one warning
        assert [r.getMessage() for r in caplog.records] == [
            "outbox is 2/4 full: the base station is not acknowledging"
        ]
        for s in range(2, 4):
            assert ob.has_room()
            ob.add(s, bytes([s]))
        assert not ob.has_room() and not ob.has_room()
        assert ob.high_water == 4 and ob.deferred == 2 and len(ob) == 4
        assert "outbox full" in caplog.records[-1].getMessage()
    ob.ack(0)
    assert ob.has_room() and len(ob) == 3


def test_keyframe_selector_thresholds(cfg) -> None:
    sel = KeyframeSelector(cfg.agent)
    assert sel.is_due(np.zeros(4))
    d, cov = sel.cut(np.zeros(4))
    assert np.allclose(d, 0) and cov.shape == (6, 6)
    assert not sel.is_due(np.array([0.15, 0.0, 0.0, 0.05]))
    assert sel.is_due(np.array([0.21, 0.0, 0.0, 0.0]))
    assert sel.is_due(np.array([0.0, 0.0, 0.0, 0.11]))
    d, cov = sel.cut(np.array([0.3, 0.1, 1.0, 0.2]))
    assert np.allclose(d, [0.3, 0.1, 1.0, 0.2])
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_a_matchs_covariance_is_turned_into_the_keyframes_frame(cfg) -> None:
    """The scan match's covariance is in `odom`, the keyframe's delta in its own frame:
    added unturned, a corridor along y in odom (certain across it, x; unsure along it, y)
    told the graph the opposite about a drone flying the corridor nose first."""
    sel = KeyframeSelector(cfg.agent)
    sel.cut(np.array([0.0, 0.0, 1.0, np.pi / 2]))
    along_y = np.diag([1e-6, 1e-2, 1e-6])  # odom: unsure along y
    _, cov = sel.cut(np.array([0.0, 0.3, 1.0, np.pi / 2]), along_y)
    odo = sel.covariance(np.array([0.3, 0.0, 0.0, 0.0]))
    assert cov[0, 0] - odo[0, 0] == pytest.approx(1e-2)  # along the nose: x of the body
    assert cov[1, 1] - odo[1, 1] == pytest.approx(1e-6)


def _kf(seq: int, robot: str = "r0") -> Keyframe:
    p = pose4_to_pose7([0.2 * seq, 0, 1, 0])
    scan = Scan2D.from_ranges(0.0, 0.1, 30.0, np.ones(3))
    return Keyframe(
        robot, seq, 0.1 * seq, p, pose4_to_pose7([0.2, 0, 0, 0]), np.eye(6) * 1e-4, scan, None
    )


def test_store_dedups_and_reorders() -> None:
    st = KeyframeStore(reorder_window=2)
    assert [k.seq for k in st.admit(_kf(0))] == [0]
    assert st.admit(_kf(2)) == []  # gap: held
    assert st.admit(_kf(0)) == []  # duplicate
    assert st.admit(_kf(2)) == []  # duplicate of a held one
    assert [k.seq for k in st.admit(_kf(1))] == [1, 2]
    assert st.acked_seq("r0") == 2
    assert st.robot("r0").duplicates == 2
    st.admit(_kf(4)), st.admit(_kf(5))
    assert st.admit(_kf(6)) == []  # window full: dropped, will be resent
    assert [k.seq for k in st.admit(_kf(3))] == [3, 4, 5]
    assert [k.seq for k in st.admit(_kf(6))] == [6]
    # far beyond the window (seq 10**9 from a broken or hostile sender): dropped at once,
    # without taking the room the next out-of-order keyframe needs
    assert st.admit(_kf(10**9)) == [] and st.admit(_kf(10)) == []  # 10 > 7 + 2
    assert st.admit(_kf(9)) == [] and st.admit(_kf(8)) == []  # both held
    assert sorted(st.robot("r0").held) == [8, 9]
    assert [k.seq for k in st.admit(_kf(7))] == [7, 8, 9]


def test_path_follower_reaches_waypoints() -> None:
    f = PathFollower(cruise_speed=1.0, tolerance=0.3, yaw_gain=1.5, max_accel=1.0, altitude_m=1.0)
    f.set_path(np.array([[2.0, 0.0], [2.0, 2.0]]))
    pose = np.array([0.0, 0.0, 1.0, 0.0])
    dt = 0.05
    for _ in range(2000):
        vx, vy, vz, wz = f.command(pose)
        c, s = np.cos(pose[3]), np.sin(pose[3])
        pose = pose + dt * np.array([c * vx - s * vy, s * vx + c * vy, vz, wz])
        if f.done:
            break
    assert f.done
    assert np.hypot(pose[0] - 2.0, pose[1] - 2.0) < 0.3
    assert f.command(pose)[:2] == (0.0, 0.0)


def test_path_follower_flies_off_the_nose_only_where_the_laser_sees() -> None:
    """A multirotor flies sideways while it turns, at full speed up to 60 deg off the
    nose and not at all beyond 105 deg (the laser's blind sector is behind)."""
    f = PathFollower(cruise_speed=1.0, tolerance=0.3, yaw_gain=1.5, max_accel=1.0, altitude_m=1.0)
    pose = np.array([0.0, 0.0, 1.0, 0.0])

    def speed_toward(angle_deg: float) -> tuple[float, float]:
        a = np.radians(angle_deg)
        f.set_path(np.array([[10.0 * np.cos(a), 10.0 * np.sin(a)]]))
        vx, vy, _, wz = f.command(pose)
        if np.hypot(vx, vy) > 0:  # along the way to the waypoint
            assert abs(np.arctan2(vy, vx) - a) < 1e-9
        return float(np.hypot(vx, vy)), wz

    assert speed_toward(45.0)[0] == pytest.approx(1.0)
    assert speed_toward(-60.0)[0] == pytest.approx(1.0)
    v90, wz90 = speed_toward(90.0)
    assert 0.2 < v90 < 0.5 and wz90 > 0.0  # slower, and turning toward it
    v_back, wz_back = speed_toward(-150.0)
    assert v_back == 0.0 and wz_back < 0.0  # turns first
    with pytest.raises(ValueError):
        PathFollower(1.0, 0.3, 1.5, 1.0, 1.0, full_speed_off_nose_deg=90.0, max_off_nose_deg=80.0)


def test_path_follower_turns_to_a_last_waypoint_just_behind() -> None:
    """0.15-0.2 m short of the last waypoint with it behind (a correction moved the
    path), the drone neither flew (blind sector) nor turned (close in): it hovered
    there for good, `flying`. It turns to it now, then reaches it."""
    f = PathFollower(cruise_speed=1.0, tolerance=0.3, yaw_gain=1.5, max_accel=1.0, altitude_m=1.0)
    f.set_path(np.array([[-0.18, 0.0]]))
    pose = np.array([0.0, 0.0, 1.0, 0.0])
    assert f.command(pose)[3] != 0.0
    for _ in range(400):
        vx, vy, vz, wz = f.command(pose)
        c, s = np.cos(pose[3]), np.sin(pose[3])
        pose = pose + 0.05 * np.array([c * vx - s * vy, s * vx + c * vy, vz, wz])
    assert f.done and np.hypot(pose[0] + 0.18, pose[1]) <= 0.15


def test_a_keyframe_that_never_comes_is_named(caplog: pytest.LogCaptureFixture) -> None:
    """A base station restarted without its database waits for seq 0, which an agent
    that does not start a new chain (an old one) dropped once the first base station
    acked it: its keyframes had been held without a word."""
    from basestation.keyframe_store import GAP_WARN

    st = KeyframeStore(reorder_window=1000)
    with caplog.at_level(logging.ERROR):
        for seq in range(60, 60 + GAP_WARN):
            st.admit(_kf(seq))
    assert len(st.robot("r0").held) == GAP_WARN
    assert f"still waiting for keyframe seq 0 of chain 0 with {GAP_WARN} later" in caplog.text


def test_a_second_agent_with_the_same_id_is_named(caplog: pytest.LogCaptureFixture) -> None:
    """Two agents started as r0 (or r0's agent restarted) had their keyframes mixed into
    one trajectory, the other's counted as mere duplicates, without a word. Now the
    first sign of another source stops the robot's admission (its frames cannot be
    joined): nothing more is mapped, acknowledged or corrected."""
    import dataclasses

    st = KeyframeStore(reorder_window=100)
    for seq in range(3):
        st.admit(_kf(seq))
    st.admit(_kf(5))  # held
    st.admit(_kf(1))  # resent: the same keyframe
    assert st.robot("r0").id_conflicts == 0
    with caplog.at_level(logging.ERROR):
        st.admit(dataclasses.replace(_kf(1), stamp=1e9 + 0.1))  # another drone's seq 1
        st.admit(dataclasses.replace(_kf(5), stamp=1e9 + 0.5))  # and its seq 5
    r = st.robot("r0")
    assert r.id_conflicts == 2 and r.duplicates == 2 and r.foreign and not r.held
    assert "another agent sends as r0 (restarted, or two with this id)" in caplog.text
    assert st.admit(_kf(3)) == [] and r.next_seq == 3  # seq 3 would have joined the two
    assert st.ack("r0") is None and st.none_of("r0", 0, 3) is None


def test_a_base_station_that_acknowledges_nothing_is_named(
    cfg, endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A drone whose keyframes the access control drops (another drone's certificate,
    another fleet) had resent them all mission long with INFO lines only."""
    import time

    from agent.uplink import NO_ACK_WARN_S, KeyframeUplink
    from common.bus import Bus
    from common.config import ZenohConfig

    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        up = KeyframeUplink(cfg.agent, "r0", bus)
        up.on_base_alive("base-1", True, again=False)
        up._base_up_at = time.monotonic() - NO_ACK_WARN_S - 1.0
        with caplog.at_level(logging.ERROR):
            up.resend()  # nothing to acknowledge (a resumed agent, hovering): nothing said
        assert "acknowledged none" not in caplog.text
        up._base_up_at = time.monotonic()
        kf = _kf(1)
        fields = {k: getattr(kf, k) for k in ("stamp", "pose_odom", "delta", "delta_cov", "scan2d")}
        assert up.send(**fields)
        with caplog.at_level(logging.ERROR):
            up.resend()  # up for less than NO_ACK_WARN_S: nothing said
            assert "acknowledged none" not in caplog.text
            up._base_up_at = time.monotonic() - NO_ACK_WARN_S - 1.0
            up.resend()
            up.resend()
        assert caplog.text.count("acknowledged none of this robot's 1 keyframes") == 1
        # another fleet's agent never sees the base station at all: named too
        alone = KeyframeUplink(cfg.agent, "r1", bus)
        assert alone.send(**fields)
        alone._unseen_since = time.monotonic() - NO_ACK_WARN_S - 1.0
        with caplog.at_level(logging.ERROR):
            alone.resend()
            alone.resend()
        assert caplog.text.count("no base station seen in 60 s") == 1
