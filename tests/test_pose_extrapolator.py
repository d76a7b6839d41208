"""Tests for agent.pose_extrapolator: the pose prediction at the next scan."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from agent.local_trajectory_builder import LocalTrajectoryBuilder
from agent.odometry_tracker import OdometryTracker
from agent.pose_extrapolator import MAX_ODOMETRY, PoseExtrapolator
from common.config import load_config
from common.geometry import se2_compose, wrap_angle
from protocol import LaserScan


def arc(t: float) -> np.ndarray:
    """A vehicle on a circle: 1 m/s, 0.5 rad/s, in the odometry frame."""
    yaw = 0.5 * t
    return np.array([2.0 * np.sin(yaw), 2.0 * (1.0 - np.cos(yaw)), yaw])


def test_the_motion_between_scan_stamps_comes_from_odometry_at_those_stamps() -> None:
    """Odometry at 100 Hz runs ahead of the scans (it has less latency): the prediction
    uses the odometry interpolated at the two scan stamps, not the newest message."""
    ex = PoseExtrapolator()
    odom_stamps = np.arange(0.0, 2.0, 0.01)
    local_from_odom = np.array([5.0, -1.0, 0.3])  # the local frame differs from odometry's
    scan_stamps = [0.1025, 0.2275, 0.3525]
    fed = 0
    for k, (t_prev, t) in enumerate(zip(scan_stamps, scan_stamps[1:], strict=False)):
        if k == 0:
            ex.add_pose(t_prev, se2_compose(local_from_odom, arc(t_prev)))
        while odom_stamps[fed] <= t + 0.05:  # 50 ms of odometry past the scan
            ex.add_odometry(odom_stamps[fed], arc(odom_stamps[fed]))
            fed += 1
        predicted = ex.predict(t)
        truth = se2_compose(local_from_odom, arc(t))
        # linear interpolation within 10 ms of a 2 m circle: well under a millimetre
        assert np.allclose(predicted[:2], truth[:2], atol=1e-4)
        assert predicted[2] == pytest.approx(truth[2], abs=1e-4)
        newest = se2_compose(local_from_odom, arc(odom_stamps[fed - 1]))
        assert np.linalg.norm(newest[:2] - truth[:2]) > 0.04  # the newest message: 5 cm off
        ex.add_pose(t, truth)


def test_odometry_at_interpolates_and_holds_outside() -> None:
    ex = PoseExtrapolator()
    assert ex.odometry_at(1.0) is None
    ex.add_odometry(1.0, np.array([0.0, 0.0, np.pi - 0.1]))
    ex.add_odometry(2.0, np.array([1.0, 2.0, -np.pi + 0.1]))  # across +-pi
    mid = ex.odometry_at(1.5)
    assert mid[:2] == pytest.approx([0.5, 1.0])
    assert abs(abs(mid[2]) - np.pi) < 1e-9  # the short way round, not through 0
    assert ex.odometry_at(0.5) == pytest.approx([0.0, 0.0, np.pi - 0.1])
    assert ex.odometry_at(3.0) == pytest.approx([1.0, 2.0, -np.pi + 0.1])  # too far: held
    ahead = ex.odometry_at(2.25)  # a scan just newer than the newest odometry: extrapolated
    assert ahead[:2] == pytest.approx([1.25, 2.5])
    assert ahead[2] == pytest.approx(-np.pi + 0.15)
    assert ex.odometry_at(2.0) == pytest.approx([1.0, 2.0, -np.pi + 0.1])


def test_odometry_going_back_in_time_is_dropped_with_an_error(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ex = PoseExtrapolator()
    ex.add_pose(0.0, np.zeros(3))
    ex.add_odometry(0.0, np.zeros(3))
    ex.add_odometry(1.0, np.array([1.0, 0.0, 0.0]))
    with caplog.at_level(logging.ERROR):
        ex.add_odometry(0.5, np.array([9.0, 9.0, 0.0]))
    assert ex.rejected_odometry == 1
    assert "before the previous" in caplog.text
    assert ex.predict(1.0) == pytest.approx([1.0, 0.0, 0.0])
    ex.add_odometry(1.0, np.array([2.0, 0.0, 0.0]))  # same stamp again: replaces
    assert ex.rejected_odometry == 1
    assert ex.predict(1.0) == pytest.approx([2.0, 0.0, 0.0])


def test_old_odometry_is_forgotten_but_the_bracket_of_the_last_pose_is_kept() -> None:
    ex = PoseExtrapolator()
    for k in range(3 * MAX_ODOMETRY):  # no pose yet: only the last velocity's are needed
        ex.add_odometry(0.01 * k, np.array([0.01 * k, 0.0, 0.0]))
    assert len(ex._odom_t) <= 7  # (MIN_VELOCITY_BASE_S of odometry: 5-6 steps of 10 ms)
    for k in range(3 * MAX_ODOMETRY, 4 * MAX_ODOMETRY):
        t = 0.01 * k
        ex.add_odometry(t, np.array([t, 0.0, 0.0]))
        if k % 10 == 5:
            ex.add_pose(t + 0.005, np.array([t, 0.0, 0.0]))  # between two odometry stamps
    last_pose_t = ex._poses[-1][0]
    kept = ex._odom_t
    assert any(a < last_pose_t < b for a, b in zip(kept[:-1], kept[1:], strict=True))  # bracket
    assert len(ex._odom_t) <= 11
    t_end = ex._odom_t[-1]
    assert ex.predict(t_end)[0] == pytest.approx(last_pose_t - 0.005 + t_end - last_pose_t)


def test_a_laser_gap_longer_than_the_odometry_kept_loses_no_motion() -> None:
    """Odometry goes on at 100 Hz while the laser is out for 7 s (a driver restart): more
    than `MAX_ODOMETRY` messages. The oldest had been dropped with the one at the last
    matched pose, and the next scan was predicted from the oldest kept: 0.93 m off."""
    ex = PoseExtrapolator()
    for k in range(101):
        ex.add_odometry(0.01 * k, arc(0.01 * k))
    ex.add_pose(1.0, arc(1.0))  # the last scan matched before the gap
    for k in range(101, 801):  # 7 s
        ex.add_odometry(0.01 * k, arc(0.01 * k))
    assert len(ex._odom_t) <= MAX_ODOMETRY + 1
    got, want = ex.predict(8.0), arc(8.0)
    assert np.allclose(got[:2], want[:2], atol=1e-9) and abs(wrap_angle(got[2] - want[2])) < 1e-9


def test_without_odometry_the_last_velocity_is_held() -> None:
    ex = PoseExtrapolator(use_odometry=False)
    ex.add_odometry(0.0, np.zeros(3))  # ignored
    ex.add_pose(0.0, np.zeros(3))
    ex.add_pose(0.1, np.array([0.1, 0.0, 0.0]))
    assert ex.predict(0.2) == pytest.approx([0.2, 0.0, 0.0])


def test_odometry_that_stopped_leaves_the_last_velocity_not_a_frozen_pose(caplog) -> None:  # noqa: ANN001
    """A source that stops publishing (a driver hang): the prediction had held its last
    pose, the matcher followed it, and the pose froze while the drone flew on at 1 m/s
    (3 m off after 4 s, with status `flying` and no line). Odometry that never came
    gives the last velocity; odometry that stopped now does too, and says so."""
    ex = PoseExtrapolator()
    for k in range(5):  # 1 m/s along x
        ex.add_odometry(0.05 * k, np.array([0.05 * k, 0.0, 0.0]))
    ex.add_pose(0.1, np.array([0.1, 0.0, 0.0]))
    ex.add_pose(0.2, np.array([0.2, 0.0, 0.0]))
    assert ex.predict(0.6)[0] == pytest.approx(0.6, abs=1e-9)  # (extrapolated odometry)
    assert ex.predict(2.0)[0] == pytest.approx(2.0, abs=1e-9)  # stopped: the last velocity
    assert ex.stalled_predictions == 1 and "no odometry for 1.8 s" in caplog.text


def test_without_local_slam_an_odometry_reset_is_not_flown_and_a_stall_hovers() -> None:
    """`agent.local_slam.enabled = false`: a 3 m reset of the odometry's frame had been
    taken as motion (the drone flew 3 m off its path, its keyframes carrying the step),
    and odometry that stopped had left the pose standing while the drone flew on."""
    tr = OdometryTracker()
    scan = np.ones(10, np.float32)
    for k in range(5):
        tr.add_odometry(0.025 * k, np.array([0.025 * k, 0.0, 0.0]))
    tr.add_odometry(0.125, np.array([0.125, 3.0, 0.0]))  # a reset: 3 m sideways at once
    tr.add_odometry(0.15, np.array([0.15, 3.0, 0.0]))
    assert tr.pose[:2] == pytest.approx([0.125, 0.0]) and tr.odometry_resets == 1
    assert tr.add_scan(LaserScan("r0", 0.15, -1.0, 0.01, 0.1, 30.0, scan)) is not None
    assert tr.add_scan(LaserScan("r0", 0.9, -1.0, 0.01, 0.1, 30.0, scan)) is None  # stopped
    assert tr.stale_odometry_scans == 1


@pytest.mark.parametrize("frontend", ["local_slam", "odometry_only"])
def test_both_agent_frontends_drop_odometry_going_back(frontend: str) -> None:
    """The agent's two frontends (`agent.local_slam.enabled` true / false) count what they
    drop, for the agent's statistics."""
    front: LocalTrajectoryBuilder | OdometryTracker
    if frontend == "local_slam":
        front = LocalTrajectoryBuilder(load_config(None).agent.local_slam)
    else:
        front = OdometryTracker()
    front.add_odometry(1.0, np.array([1.0, 0.0, 0.0]))
    front.add_odometry(0.5, np.array([5.0, 0.0, 0.0]))
    front.add_odometry(2.0, np.array([2.0, 0.0, 0.0]))
    assert front.rejected_odometry == 1
    if isinstance(front, OdometryTracker):
        assert front.pose[0] == pytest.approx(1.0)  # 1 -> 2 m, not via 5 m


def test_a_scan_processed_before_its_odometry_still_gets_the_whole_motion() -> None:
    """Odometry and scans of one instant come on two topics: the scan may be handled
    first. Its odometry is then extrapolated at the last velocity, not held (holding
    predicts no motion for one period, and the matcher's prior pulls toward that)."""
    ex = PoseExtrapolator()
    dt = 0.025
    ex.add_odometry(0.0, arc(0.0))
    ex.add_odometry(dt, arc(dt))
    ex.add_pose(dt, arc(dt))
    for k in range(2, 20):
        t = k * dt
        predicted = ex.predict(t)  # the odometry at t is not there yet
        assert np.linalg.norm(predicted[:2] - arc(t)[:2]) < 1e-3  # 25 mm per period moved
        ex.add_pose(t, arc(t))
        ex.add_odometry(t, arc(t))


def test_odometry_stamped_on_arrival_is_extrapolated_at_its_real_speed() -> None:
    """A driver stamping its 50 Hz odometry on arrival: pairs 1 ms apart with 20 ms of
    motion between them. Extrapolated along the last two, the prediction had overshot
    20x (0.475 m a scan at 1 m/s; a 60 m tour ended 322 m off, turned 180 degrees)."""
    ex = PoseExtrapolator()
    for k in range(10):
        t = 0.02 * k
        ex.add_odometry(t if k % 2 == 0 else t - 0.019, np.array([t, 0.0, 0.0]))
    ex.add_pose(0.16, np.array([0.16, 0.0, 0.0]))
    assert ex.predict(0.185)[0] == pytest.approx(0.185, abs=0.03)
