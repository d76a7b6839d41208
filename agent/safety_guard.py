"""Keeps the drone's velocity command clear of what its laser sees right now.

The base station plans on a global map that lags the robot (and treats unknown
space as free), so the agent must never rely on the path alone: before each
command goes out, `SafetyGuard.limit` caps the speed along the commanded
direction so that the drone can stop (at `max_accel`) before any scan point
within its `radius_m + margin_m` corridor, and removes the velocity component
toward a point already closer than that. A drone held still for longer than
`blocked_after_s` is reported `blocked` so the base station replans.

All in the body frame of the latest scan (x forward, y left; the laser at the
origin), metres and seconds; the vehicle's own limits still apply after this.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class SafetyGuard:
    def __init__(
        self,
        radius_m: float,
        margin_m: float,
        max_accel: float,
        reaction_s: float,
        blocked_after_s: float,
        horizon_m: float = 4.0,
    ) -> None:
        self.corridor = radius_m + margin_m  # half-width swept by the drone, m
        self.stop_margin = margin_m  # m left between the disc and a point when stopped
        self.max_accel = max_accel
        self.reaction_s = reaction_s
        self.blocked_after_s = blocked_after_s
        self.horizon = horizon_m
        self.points: NDArray[np.float64] = np.zeros((0, 2))
        self._held_since: float | None = None
        self.blocked = False
        self.limited_ticks = 0

    def update(self, angles: NDArray[np.float64], ranges: NDArray[np.float64]) -> None:
        """Take the latest scan (beam angles, rad; ranges, m; NaN/inf = no return)."""
        r = np.asarray(ranges, dtype=np.float64)
        keep = np.isfinite(r) & (r < self.horizon)
        a = np.asarray(angles, dtype=np.float64)[keep]
        self.points = np.column_stack([r[keep] * np.cos(a), r[keep] * np.sin(a)])

    def limit(self, stamp: float, vx: float, vy: float) -> tuple[float, float]:
        """The body-frame horizontal command (vx, vy), m/s, made safe for the last scan."""
        v = np.array([vx, vy], dtype=np.float64)
        wanted = float(np.hypot(vx, vy))
        p = self.points
        if len(p) and wanted > 1e-6:
            dist = np.hypot(p[:, 0], p[:, 1])
            k = int(np.argmin(dist))
            if dist[k] < self.corridor:  # too close already: no motion toward it
                n = p[k] / max(dist[k], 1e-9)
                v -= max(float(v @ n), 0.0) * n
            speed = float(np.hypot(*v))
            if speed > 1e-6:
                u = v / speed
                along = p @ u
                lateral = np.abs(p @ np.array([-u[1], u[0]]))
                ahead = (along > 0.0) & (lateral < self.corridor)
                if ahead.any():
                    # distance the disc can travel before touching the nearest point ahead
                    travel = along[ahead] - np.sqrt(self.corridor**2 - lateral[ahead] ** 2)
                    room = max(float(travel.min()) - self.stop_margin, 0.0)
                    # fly at most the speed from which it still stops in `room`, one
                    # reaction time of travel included
                    a, t = self.max_accel, self.reaction_s
                    allowed = -a * t + np.sqrt((a * t) ** 2 + 2.0 * a * room)
                    if allowed < speed:
                        v *= allowed / speed
        limited = float(np.hypot(*v)) < wanted - 1e-6
        self.limited_ticks += int(limited)
        held = wanted > 0.05 and float(np.hypot(*v)) < 0.05
        if not held:
            self._held_since = None
        elif self._held_since is None:
            self._held_since = stamp
        self.blocked = held and stamp - self._held_since >= self.blocked_after_s
        return float(v[0]), float(v[1])

    def clear(self) -> None:
        """A new path: forget being blocked."""
        self._held_since = None
        self.blocked = False
