"""Follows a list of waypoints with body-frame velocity commands.

Waypoints are [x, y] (or [x, y, z, yaw]) in the robot's `odom` frame. The
follower flies straight at each waypoint at cruise speed, turning to face the
direction of travel (the laser looks forward), slows down for the last one,
and holds `altitude_m`. A multirotor need not face where it flies: it flies while
it turns, at full speed while the way lies within `full_speed_heading_deg` of the
nose, slower up to `max_heading_deg` (kept inside the laser's field of view, so the
safety guard sees what is ahead), and turns on the spot beyond. It only computes
commands; the vehicle limits itself.
"""

from __future__ import annotations

import numpy as np

from common.config import AgentConfig
from common.geometry import wrap_angle


class PathFollower:
    def __init__(
        self,
        cruise_speed: float,
        tolerance: float,
        yaw_gain: float,
        max_accel: float,
        altitude_m: float,
        full_speed_heading_deg: float = 45.0,
        max_heading_deg: float = 100.0,
    ) -> None:
        self.cruise_speed = cruise_speed
        self.tolerance = tolerance
        self.yaw_gain = yaw_gain
        self.max_accel = max_accel
        self.altitude_m = altitude_m
        self.full_speed_heading = np.radians(full_speed_heading_deg)
        self.max_heading = np.radians(max_heading_deg)
        self.waypoints = np.zeros((0, 2))
        self.index = 0

    @classmethod
    def from_config(cls, a: AgentConfig) -> PathFollower:
        return cls(
            a.cruise_speed_mps,
            a.waypoint_tolerance_m,
            a.yaw_gain,
            a.max_accel_mps2,
            a.cruise_altitude_m,
            a.full_speed_heading_deg,
            a.max_heading_deg,
        )

    def set_path(self, waypoints_odom: np.ndarray, keep_progress: bool = False) -> None:
        self.waypoints = np.asarray(waypoints_odom, dtype=np.float64)[:, :2]
        if not keep_progress:
            self.index = 0
        self.index = min(self.index, len(self.waypoints))

    @property
    def done(self) -> bool:
        return self.index >= len(self.waypoints)

    def command(self, T_odom_base: np.ndarray) -> tuple[float, float, float, float]:
        """(vx, vy, vz, yaw_rate) body-frame command for the pose [x, y, z, yaw]."""
        x, y, z, yaw = (float(v) for v in T_odom_base)
        vz = float(np.clip(1.0 * (self.altitude_m - z), -0.5, 0.5))
        while not self.done:
            d = self.waypoints[self.index] - (x, y)
            last = self.index == len(self.waypoints) - 1
            if np.hypot(*d) > self.tolerance or (last and np.hypot(*d) > 0.5 * self.tolerance):
                break
            self.index += 1
        if self.done:
            return 0.0, 0.0, vz, 0.0
        d = self.waypoints[self.index] - (x, y)
        dist = float(np.hypot(*d))
        remaining = dist + float(
            np.sum(np.linalg.norm(np.diff(self.waypoints[self.index :], axis=0), axis=1))
        )
        heading_err = float(wrap_angle(np.arctan2(d[1], d[0]) - yaw))
        speed = min(self.cruise_speed, np.sqrt(2.0 * self.max_accel * 0.5 * remaining))
        # Fly while turning (full speed near the nose, none beyond max_heading).
        off = (self.max_heading - abs(heading_err)) / (self.max_heading - self.full_speed_heading)
        speed *= min(max(off, 0.0), 1.0)
        c, s = np.cos(yaw), np.sin(yaw)
        v_odom = speed * d / max(dist, 1e-9)
        vx = c * v_odom[0] + s * v_odom[1]
        vy = -s * v_odom[0] + c * v_odom[1]
        yaw_rate = self.yaw_gain * heading_err if dist > 0.2 else 0.0
        return float(vx), float(vy), vz, float(yaw_rate)
