"""Follows a list of waypoints with body-frame velocity commands.

Waypoints are [x, y] (or [x, y, z, yaw]) in the robot's `odom` frame. The
follower flies straight at each waypoint at cruise speed, turning to face the
direction of travel, slows down for the last one, and holds `altitude_m`. A
multirotor need not face where it flies, but its laser must see there (270 deg, a
blind sector behind): up to `full_speed_off_nose_deg` off the nose it flies at
full speed while it turns, slower the further off, not at all beyond
`max_off_nose_deg` (it turns first). It only computes commands; the vehicle
limits itself.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from common.geometry import wrap_angle

if TYPE_CHECKING:
    from common.config import AgentConfig


class PathFollower:
    def __init__(
        self,
        cruise_speed: float,
        tolerance: float,
        yaw_gain: float,
        max_accel: float,
        altitude_m: float,
        full_speed_off_nose_deg: float = 60.0,
        max_off_nose_deg: float = 105.0,
    ) -> None:
        if not 0.0 <= full_speed_off_nose_deg < max_off_nose_deg <= 180.0:
            raise ValueError(
                "need 0 <= full_speed_off_nose_deg < max_off_nose_deg <= 180, got "
                f"{full_speed_off_nose_deg} and {max_off_nose_deg}"
            )
        self.cruise_speed = cruise_speed
        self.tolerance = tolerance
        self.yaw_gain = yaw_gain
        self.max_accel = max_accel
        self.altitude_m = altitude_m
        self.full_speed_off_nose = np.radians(full_speed_off_nose_deg)
        self.max_off_nose = np.radians(max_off_nose_deg)
        self.waypoints = np.zeros((0, 2))
        self.index = 0

    @classmethod
    def from_config(cls, a: AgentConfig) -> PathFollower:
        """The follower the agent flies with (`agent.*` of the configuration)."""
        return cls(
            a.cruise_speed_mps,
            a.waypoint_tolerance_m,
            a.yaw_gain,
            a.max_accel_mps2,
            a.cruise_altitude_m,
            a.full_speed_off_nose_deg,
            a.max_off_nose_deg,
        )

    def set_path(
        self,
        waypoints_odom: np.ndarray,
        keep_progress: bool = False,
        here: np.ndarray | None = None,
        catch_up_m: float = 1.5,
    ) -> None:
        """`here`: the drone flies on from the path's waypoint nearest `here`, never one
        behind it: for a new path (planned from where the drone was at its last state) from
        its start, for the same path re-placed by a correction (`keep_progress`) from the
        waypoint it flew to; within `catch_up_m` along it, or as far as `here` is from
        that waypoint and half a metre. It had flown back for waypoints passed meanwhile:
        0.3-0.8 m of a path planned 0.3-0.8 s before; 1.2-3.8 m of one from a step of 2-5 s
        (4 drones on a loaded laptop); 0.7-1.7 m after a correction moved the path 1-2 m
        along its way, turning round twice."""
        self.waypoints = np.asarray(waypoints_odom, dtype=np.float64)[:, :2]
        start = min(self.index, len(self.waypoints)) if keep_progress else 0
        self.index = start
        if here is not None and len(self.waypoints) - start > 1:
            wp = self.waypoints[start:]
            along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(wp, axis=0).T))])
            reach = max(catch_up_m, float(np.hypot(*(wp[0] - here[:2]))) + 0.5)
            dist = np.where(along <= reach, np.hypot(*(wp - here[:2]).T), np.inf)
            self.index = start + int(np.argmin(dist))
        self.index = min(self.index, len(self.waypoints))

    @property
    def done(self) -> bool:
        return self.index >= len(self.waypoints)

    def command(
        self, T_odom_base: np.ndarray, z_known: bool = True
    ) -> tuple[float, float, float, float]:
        """(vx, vy, vz, yaw_rate) body-frame command for the pose [x, y, z, yaw];
        `z_known` False (no altimeter): no vertical speed (it had climbed for good)."""
        x, y, z, yaw = (float(v) for v in T_odom_base)
        vz = float(np.clip(1.0 * (self.altitude_m - z), -0.5, 0.5)) if z_known else 0.0
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
        # Sideways while turning as far as the laser sees; turn first beyond that.
        taper = self.max_off_nose - self.full_speed_off_nose
        speed *= float(np.clip((self.max_off_nose - abs(heading_err)) / taper, 0.0, 1.0))
        c, s = np.cos(yaw), np.sin(yaw)
        v_odom = speed * d / max(dist, 1e-9)
        vx = c * v_odom[0] + s * v_odom[1]
        vy = -s * v_odom[0] + c * v_odom[1]
        # (close in the bearing swings: no turn, but one behind is turned to, else it stays)
        turn = dist > 0.2 or abs(heading_err) >= self.max_off_nose
        yaw_rate = self.yaw_gain * heading_err if turn else 0.0
        return float(vx), float(vy), vz, float(yaw_rate)
