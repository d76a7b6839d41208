"""The agent's local pose by odometry integration alone (`agent.local_slam.enabled =
false`): the same interface as `LocalTrajectoryBuilder`, without scan matching.

Each Odometry message carries the vehicle's dead-reckoned pose in the odometry
source's own frame; the tracker composes the motion between consecutive
messages onto its own estimate and takes the height from the altimeter.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from agent.local_trajectory_builder import MAX_SPEED_MPS, LocalSlamResult
from agent.pose_extrapolator import MAX_EXTRAPOLATION_S
from common.geometry import se2_compose, se2_inverse
from common.logging_setup import worth_logging
from common.stamps import JumpGate
from protocol import LaserScan

log = logging.getLogger(__name__)

RESET_SLACK_M = 0.5  # m: a step past MAX_SPEED_MPS times its time and this is a reset


class OdometryTracker:
    def __init__(self) -> None:
        self.pose = np.zeros(4)  # T_odom_base [x, y, z, yaw]; odom starts at the first pose
        self.altitude: float | None = None  # the altimeter's latest (None: none yet)
        self.last_stamp: float | None = None
        self.distance_m = 0.0
        self.scans = 0
        self.rejected_scans = 0
        self.few_point_scans = 0  # (local SLAM's: no scan is matched here)
        self.rejected_odometry = 0
        self.gated_matches = 0  # no scan matching here: always 0
        self.odometry_resets = 0  # steps faster than a drone flies: the source's resets
        self.stale_odometry_scans = 0  # scans not used: no odometry for a while
        self._last_odom: np.ndarray | None = None
        self._last_odom_stamp = -math.inf
        # a stamp far ahead of the last (`common.stamps`; without, one glitch of 1e9 s had
        # every later scan and odometry refused as older: the pose froze for good)
        self._scan_jump, self._odom_jump = JumpGate(), JumpGate()

    def resume(self, stamp: float, pose: np.ndarray, odometry: np.ndarray | None) -> None:
        """Go on from an agent before this one (`LocalTrajectoryBuilder.resume`)."""
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self.last_stamp = stamp
        if odometry is not None:
            self._last_odom = np.asarray(odometry, dtype=np.float64)
            self._last_odom_stamp = stamp

    def odometry_at(self, stamp: float) -> np.ndarray | None:
        """The latest odometry pose [x, y, yaw] (None: none yet)."""
        return None if self._last_odom is None else self._last_odom.copy()

    def add_odometry(self, stamp: float, pose_xyyaw: np.ndarray) -> None:
        last = self._last_odom_stamp if self._last_odom is not None else None
        if self._odom_jump.holds(stamp, last):
            log.error("odometry stamp %.3f is far past the previous %.3f: dropped unless "
                      "the next follows it", stamp, self._last_odom_stamp)  # fmt: skip
            self.rejected_odometry += 1
            return
        if stamp < self._last_odom_stamp:
            if worth_logging(self.rejected_odometry):
                log.error("odometry stamp %.3f is before the previous %.3f: dropped (%d so "
                          "far)", stamp, self._last_odom_stamp,
                          self.rejected_odometry + 1)  # fmt: skip
            self.rejected_odometry += 1
            return
        dt, self._last_odom_stamp = stamp - self._last_odom_stamp, stamp
        pose = np.asarray(pose_xyyaw, dtype=np.float64)
        if self._last_odom is not None:
            step = se2_compose(se2_inverse(self._last_odom), pose)
            moved = float(np.hypot(step[0], step[1]))
            if moved > RESET_SLACK_M + MAX_SPEED_MPS * dt:  # a reset of the source's frame:
                # not flown (taken as motion, a 3 m reset had flown the drone 3 m off its
                # path, and its keyframes carried the step)
                if worth_logging(self.odometry_resets):
                    log.error("odometry moved %.3g m in %.3f s: taken as a reset of its "
                              "frame, not as motion (%d so far)", moved, dt,
                              self.odometry_resets + 1)  # fmt: skip
                self.odometry_resets += 1
            else:
                self.pose[[0, 1, 3]] = se2_compose(self.pose[[0, 1, 3]], step)
                self.distance_m += moved
        self._last_odom = pose

    def keyframe_ranges(self, scan: LaserScan) -> np.ndarray:
        """The scan's readings for a keyframe, as they are (no attitude here)."""
        return scan.ranges

    def add_imu(self, stamp: float, orientation_xyzw: np.ndarray) -> None:
        """Attitude is not needed without scan matching."""

    def add_altitude(self, stamp: float, altitude_m: float) -> None:
        self.altitude = self.pose[2] = float(altitude_m)

    def add_scan(self, scan: LaserScan) -> LocalSlamResult | None:
        if self._scan_jump.holds(scan.stamp, self.last_stamp):
            log.error("scan stamp %.3f is far past the previous %.3f: dropped unless the "
                      "next scan follows it", scan.stamp, self.last_stamp)  # fmt: skip
            self.rejected_scans += 1
            return None
        if self.last_stamp is not None and scan.stamp <= self.last_stamp:
            if worth_logging(self.rejected_scans):
                log.error("scan stamp %.3f is not after the previous %.3f: dropped (%d so "
                          "far)", scan.stamp, self.last_stamp, self.rejected_scans + 1)  # fmt: skip
            self.rejected_scans += 1
            return None
        if self._last_odom is not None and scan.stamp - self._last_odom_stamp > MAX_EXTRAPOLATION_S:
            # odometry stopped: no pose (the scan is not used, the drone hovers); its last
            # pose had stood while the drone flew on at its command, 6 m off in 6 s
            if worth_logging(self.stale_odometry_scans):
                log.error("no odometry for %.1f s: scan not used, the drone hovers (%d so far)",
                          scan.stamp - self._last_odom_stamp,
                          self.stale_odometry_scans + 1)  # fmt: skip
            self.stale_odometry_scans += 1
            self.rejected_scans += 1
            return None
        self.last_stamp = scan.stamp
        self.scans += 1
        return LocalSlamResult(
            scan.stamp, self.pose.copy(), np.zeros((3, 3)), math.nan, False, False, 0
        )
