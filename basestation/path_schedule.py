"""Robots flying their paths over time: where they are, and whether two come too close.

Exploration judges paths in time, not only in space: a robot may follow another through
a door it is leaving, but must not meet it head-on, catch it up, or pass within the
clearance of where it hovers. Every robot is flown along its path at cruise speed from
where it is now (one at the end of its path stays there).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from basestation.path_planner import densify, path_length

# m over the clearance that robots close at their starts keep from each other: what a
# drone may overshoot its path by (random:1, seed 11: two drones leaving their starts
# 1.5 m apart came within 1.003 m when 1.0 m was allowed)
START_MARGIN_M = 0.2


def points_along(path: NDArray[np.float64], s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points at arc lengths `s` (m) along a polyline; its end beyond its length."""
    seg = np.hypot(*np.diff(path, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    if cum[-1] <= 0.0:
        return np.repeat(path[:1], len(s), axis=0)
    return np.column_stack([np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])])


def nearest_leg(path: NDArray[np.float64], xy: NDArray[np.float64]) -> int:
    """The leg i (from waypoint i to i + 1) of a polyline nearest `xy` (0 for one point)."""
    if len(path) < 2:
        return 0
    a, d = path[:-1], np.diff(path, axis=0)
    u = np.clip(np.einsum("ij,ij->i", xy - a, d) / np.maximum(np.einsum("ij,ij->i", d, d),
                                                              1e-12), 0.0, 1.0)  # fmt: skip
    return int(np.argmin(np.hypot(*(a + u[:, None] * d - xy).T)))


def schedule_conflict(
    path: NDArray[np.float64],
    start: NDArray[np.float64],
    others: list[NDArray[np.float64]],
    speed_mps: float,
    horizon_s: float,
    clearance_m: float,
    keep_m: float | list[float],
    lag_s: float,
    delays_s: list[float] | None = None,
    delay_s: float = 0.0,
) -> bool:
    """Whether a robot at `start` flying `path` would come within `keep_m` of another
    over the next `horizon_s`: each of `others` is a hovering robot ((2,) point) or the
    rest of a flying robot's path ((N, 2), from where it is); `keep_m` one distance for
    all or one per other. Points within `clearance_m` of the robot's own start are
    held to less (robots already close must be able to move apart): not closer than
    the clearance (+ `START_MARGIN_M`), or than the other is now if it is closer
    already; its end, where
    it will hover, is judged in full. Flying others are also checked `lag_s` behind
    their schedule (one slowed by a turn or still speeding up must not be caught up)
    and `lag_s` ahead of it (this robot itself late: one that got to the end of its
    path early must not be passed within the clearance). `delay_s` (this robot) and
    `delays_s` (one per other) hold a robot where it is before it sets off: the turn to
    face its way (`turn_delay_s`)."""
    t = np.arange(0.0, horizon_s, 0.1)
    mine = points_along(path, speed_mps * np.maximum(t - delay_s, 0.0))
    near_start = np.hypot(*(mine - start[:2]).T) <= clearance_m
    # its end, where it will hover, is judged in full (turning first, it is near its
    # start for longer, and the allowance lasts as long: it had been cut at the turn's)
    near_start &= speed_mps * np.maximum(t - delay_s, 0.0) < path_length(path)
    keeps = [keep_m] * len(others) if np.isscalar(keep_m) else keep_m
    waits = [0.0] * len(others) if delays_s is None else delays_s
    for other, keep, wait in zip(others, keeps, waits, strict=True):
        now = other[:2] if other.ndim == 1 else other[0]
        # near the start: two drones starting 1.5 m apart came within 0.91 m, both
        # still within the clearance of their starts, and then held each other forever
        near_keep = min(clearance_m + START_MARGIN_M, float(np.hypot(*(start[:2] - now))) - 0.05)
        limit = np.where(near_start, min(near_keep, keep), keep)
        if other.ndim == 1:
            positions = [other[:2]]
        else:
            positions = [
                points_along(other, speed_mps * np.maximum(t - wait - lag, 0.0))
                for lag in (0.0, lag_s, -lag_s)
            ]
        for theirs in positions:
            if np.any(np.hypot(*(mine - theirs).T) < limit):
                return True
    return False


def turn_delay_s(
    pose: NDArray[np.float64], path: NDArray[np.float64], free_rad: float, rate_rps: float
) -> float:
    """Seconds a robot at `pose` (x, y, yaw) stays where it is before it flies `path`
    (from where it is): the turn until its way is within `free_rad` of its nose, at
    `rate_rps` (the follower flies while it turns only that far off the nose; 0: the
    turn is not modelled)."""
    ahead = points_along(path, np.array([0.5]))[0] - pose[:2]
    if rate_rps <= 0.0 or len(pose) < 3 or np.hypot(*ahead) < 1e-6:
        return 0.0
    err = abs((np.arctan2(ahead[1], ahead[0]) - pose[2] + np.pi) % (2.0 * np.pi) - np.pi)
    return max(0.0, err - free_rad) / rate_rps


def comes_near(
    path: NDArray[np.float64], routes: list[NDArray[np.float64]], within_m: float, skip_m: float
) -> bool:
    """Whether `path` (from a robot on) comes within `within_m` of any of `routes` (points
    or polylines), past its first `skip_m` (the robot's start allowance). Sampled every
    0.1 m."""
    if not routes:
        return False
    p = densify(path, 0.1)
    p = p[np.hypot(*(p - path[0]).T) > skip_m]
    q = np.vstack([densify(w, 0.1) if len(w) > 1 else w for w in routes])
    if not len(p):
        return False
    return bool((((p[:, None, :] - q[None, :, :]) ** 2).sum(axis=2) < within_m**2).any())
