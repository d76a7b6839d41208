"""A drone's sensor clock stepped back (NTP or GPS time setting the host's clock back):
every later scan had been "not after the previous" and dropped for good, and the agent
flew blind on its last command. Now the step is taken up (`BackStepRepair`)."""

from __future__ import annotations

import numpy as np

from agent.node import AgentNode
from agent.sensor_sources import FIX_MAX_APART_S
from agent.vehicle import NullVehicle
from common.bus import Bus
from common.config import Config, ZenohConfig
from common.geometry import pose4_to_pose7
from common.stamps import STEP_CONFIRM, BackStepRepair
from protocol import Altimeter, GnssFix, Imu, Keyframe, LaserScan, Odometry, decode


def test_a_step_back_is_taken_up_and_a_stray_stamp_is_not() -> None:
    c = BackStepRepair()
    assert [c(t) for t in (0.0, 0.1, 0.2)] == [0.0, 0.1, 0.2]
    assert c(0.15) == 0.15  # a reordering between sensors passes
    assert c(-50.0) is None and c(0.3) == 0.3  # a stray stamp is dropped, nothing moves
    for t in (0.4, 0.5, 0.6):  # one sensor stamping by another clock among good ones
        assert c(t - 20.0) is None and c(t) == t
    assert c(500.0) == 500.0  # far ahead: passed on (local SLAM holds it) ...
    assert c(0.7) == 0.7  # ... and not taken as the latest
    assert c.steps == 0 and c.offset == 0.0
    raw = -99.0 + 0.1 * np.arange(STEP_CONFIRM + 3)  # the clock stepped back ~100 s
    out = [c(t) for t in raw]
    assert out[: STEP_CONFIRM - 1] == [None] * (STEP_CONFIRM - 1)
    assert c.steps == 1 and np.all(np.diff(out[STEP_CONFIRM - 1 :]) > 0.0)
    assert 0.7 < out[STEP_CONFIRM - 1] < 0.7 + 0.1 * STEP_CONFIRM  # goes on from 0.7


def test_agent_flies_on_after_its_sensor_clock_steps_back(cfg: Config, endpoint: str) -> None:
    cfg.agent.local_slam.enabled = False  # odometry integration: exact local poses
    n, step = 60, 100.0
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        for k in range(n):  # 0.5 m/s along x; the clock steps back 100 s half way
            t = 0.1 * k - (step if k >= n // 2 else 0.0)
            pose = pose4_to_pose7([0.05 * k, 0.0, 0.0, 0.0])
            node.handle(Altimeter("r0", t, 1.0))
            node.handle(Odometry("r0", t, pose, np.array([0.5, 0.0, 0.0, 0.0])))
            node.handle(LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, np.ones(201, np.float32)))
        sent = [decode(p, Keyframe) for p in node.outbox._pending.values()]
        stats = node.stats()
    # three messages per tick: the step is taken up within the second tick after it
    assert node.scans >= n - 2, node.scans
    assert stats["sensor_clock_steps"] == 1
    assert abs(stats["sensor_clock_offset_s"] - step) < 0.2
    assert node.frontend.pose[0] > 0.05 * (n - 2)  # it followed the odometry to the end
    stamps = node.local_trajectory.rows()[:, 0]
    assert np.all(np.diff(stamps) > 0.0)
    assert np.all(np.diff([kf.stamp for kf in sent]) > 0.0)
    assert sent[-1].pose_odom[0] > 0.05 * (n - 6)  # keyframes to the end


def test_a_sensor_on_another_clock_is_named(caplog) -> None:  # noqa: ANN001
    """A driver's IMU on Unix time, its laser and odometry on time since boot: the IMU
    became the latest stamp and every scan was dropped for good, with only "sensor stamp
    ... dropped" in the log. The IMU is named, with its offset, and counted; an unpaced
    replay's odometry after a gap in its log (one message ahead of the scan before it,
    an Intel replay had 219 false "another clock?" errors) is not."""
    c = BackStepRepair()
    q = np.array([0.0, 0.0, 0.0, 1.0])
    scan = np.ones(201, np.float32)
    for k in range(8):
        t = 100.0 + 0.025 * k + (1.5 if k >= 4 else 0.0)  # a 1.5 s gap in the log
        c.take(Odometry("r0", t, pose4_to_pose7([0.0, 0.0, 0.0, 0.0]), np.zeros(4)))
        c.take(LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, scan))
        c.take(Imu("r0", 1.7e9 + t, np.zeros(3), np.zeros(3), q))
    assert c.stats()["sensor_clock_disagreements"] == 4  # the IMU's from its 5th, no gap's
    assert "Imu stamps are 1700000000.000 s ahead of the laser's" in caplog.text
    assert "Odometry" not in caplog.text


def test_a_late_gnss_fix_agrees_and_one_on_gps_time_does_not() -> None:
    """Relayed fixes are checked with their own tolerance: a fix 1.5 s late (a slow
    serial link) had been taken for another clock by the IMU's 1 s, and dropped."""
    c = BackStepRepair()
    c.take(LaserScan("r0", 100.0, -1.0, 0.01, 0.1, 30.0, np.ones(201, np.float32)))
    lla, sig = np.array([45.8, 16.0, 160.0]), np.array([1.5, 1.5, 3.0])
    assert c.agreement.check(GnssFix("r0", 98.5, lla, sig), FIX_MAX_APART_S)
    assert not c.agreement.check(GnssFix("r0", 98.5, lla, sig))  # (the IMU's tolerance)
    assert not c.agreement.check(GnssFix("r0", 118.0, lla, sig), FIX_MAX_APART_S)  # GPS time
