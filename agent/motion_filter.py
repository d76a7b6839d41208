"""Decides which scans become local keyframes (inserted into the submaps).

Seed 002 inserts a local keyframe every 0.25 s; like Cartographer's motion
filter, a scan is only inserted when the vehicle moved a little since the last
one (so hovering does not saturate the submaps), or after `max_time_s` anyway.
"""

from __future__ import annotations

import numpy as np

from common.geometry import wrap_angle
from common.stamps import due


class MotionFilter:
    def __init__(
        self, period_s: float, min_distance_m: float, min_angle_rad: float, max_time_s: float
    ) -> None:
        self.period_s = period_s
        self.min_distance_m = min_distance_m
        self.min_angle_rad = min_angle_rad
        self.max_time_s = max_time_s
        self._last: tuple[float, np.ndarray] | None = None
        self.accepted = 0
        self.rejected = 0

    def accept(self, stamp: float, pose: np.ndarray) -> bool:
        """True if the scan at `pose` [x, y, yaw] should become a local keyframe."""
        ok = self._last is None
        if not ok:
            t0, p0 = self._last
            moved = (
                np.hypot(pose[0] - p0[0], pose[1] - p0[1]) >= self.min_distance_m
                or abs(float(wrap_angle(pose[2] - p0[2]))) >= self.min_angle_rad
            )
            ok = due(stamp, t0, self.period_s) and (moved or due(stamp, t0, self.max_time_s))
        if ok:
            self._last = (stamp, np.asarray(pose, dtype=np.float64).copy())
            self.accepted += 1
        else:
            self.rejected += 1
        return ok
