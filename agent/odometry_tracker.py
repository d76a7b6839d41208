"""The agent's local pose T_odom_base, by odometry integration.

Each Odometry message carries the vehicle's dead-reckoned pose in the
odometry source's own frame; the tracker composes the motion between
consecutive messages onto its own estimate, and takes the height from the
altimeter when one is present. (The scan-matching local trajectory builder
replaces this as the agent's front end.)
"""

from __future__ import annotations

import logging

import numpy as np

from common.geometry import pose4_compose, pose4_inverse, pose7_to_pose4

log = logging.getLogger(__name__)


class OdometryTracker:
    def __init__(self) -> None:
        self.T_odom_base = np.zeros(4)  # [x, y, z, yaw]; the odom frame starts at the first pose
        self.stamp: float | None = None
        self.distance_m = 0.0
        self._last_odom: np.ndarray | None = None

    def on_odometry(self, stamp: float, pose7: np.ndarray) -> bool:
        """Integrate one odometry sample; returns False (and logs) if time went backwards."""
        if self.stamp is not None and stamp < self.stamp:
            log.error("odometry stamp %.3f is before the previous %.3f: dropped", stamp, self.stamp)
            return False
        pose = pose7_to_pose4(pose7)
        if self._last_odom is not None:
            step = pose4_compose(pose4_inverse(self._last_odom), pose)
            self.T_odom_base = pose4_compose(self.T_odom_base, step)
            self.distance_m += float(np.hypot(step[0], step[1]))
        self._last_odom = pose
        self.stamp = stamp
        return True

    def on_altitude(self, altitude_m: float) -> None:
        self.T_odom_base[2] = altitude_m
