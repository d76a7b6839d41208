"""Per-robot keyframe sequences: in-order admission, duplicates and gaps.

Agents deliver at least once and may resend, so the store admits each robot's
keyframes strictly in `seq` order: a seq already admitted is a harmless
duplicate (counted, re-acknowledged, never added twice); a seq beyond a gap is
held (up to `reorder_window` per robot) until the gap fills.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from common.geometry import pose7_to_pose4
from protocol.messages import Keyframe

log = logging.getLogger(__name__)


@dataclass
class RobotKeyframes:
    robot_id: str
    stamps: list[float] = field(default_factory=list)
    poses_odom: list[np.ndarray] = field(default_factory=list)  # T_odom_base [x, y, z, yaw]
    keyframes: list[Keyframe] = field(default_factory=list)
    points: list[np.ndarray] = field(default_factory=list)  # (N, 2) body-frame scan points
    var_cumsum: list[np.ndarray] = field(default_factory=list)  # running [var_xy, var_yaw]
    held: dict[int, Keyframe] = field(default_factory=dict)
    duplicates: int = 0

    def chain_covariance(self, i: ArrayLike, j: ArrayLike) -> np.ndarray:
        """Approximate (n, 3, 3) covariances of nodes j relative to nodes i (index arrays)
        along the chain: summed per-keyframe variances, plus the heading uncertainty
        swept over the (odometry) distance between them. Zero where i == j."""
        i, j = np.atleast_1d(i), np.atleast_1d(j)
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        cum = np.asarray(self.var_cumsum)
        v = cum[hi] - cum[lo]
        P = np.asarray(self.poses_odom)
        d2 = np.sum((P[hi, :2] - P[lo, :2]) ** 2, axis=1)
        same = lo == hi
        var_xy = np.where(same, 0.0, v[:, 0] + 0.5 * v[:, 1] * d2 + 1e-6)
        var_yaw = np.where(same, 0.0, v[:, 1] + 1e-8)
        out = np.zeros((len(i), 3, 3))
        out[:, 0, 0] = out[:, 1, 1] = var_xy
        out[:, 2, 2] = var_yaw
        return out

    @property
    def next_seq(self) -> int:
        return len(self.keyframes)


def scan_points(kf: Keyframe, voxel_m: float = 0.05) -> np.ndarray:
    """A keyframe's returns as (N, 2) points in its body frame, one per voxel."""
    if kf.scan2d is None:
        return np.zeros((0, 2))
    r = kf.scan2d.ranges()
    a = kf.scan2d.angles()
    ok = np.isfinite(r)
    pts = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])]).astype(np.float64)
    if len(pts) == 0:
        return pts
    keys = np.floor(pts / voxel_m).astype(np.int64)
    _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
    return pts[np.sort(first)]


class KeyframeStore:
    def __init__(self, reorder_window: int = 1000) -> None:
        self.reorder_window = reorder_window
        self.robots: dict[str, RobotKeyframes] = {}

    def robot(self, robot_id: str) -> RobotKeyframes:
        if robot_id not in self.robots:
            self.robots[robot_id] = RobotKeyframes(robot_id)
        return self.robots[robot_id]

    def admit(self, kf: Keyframe) -> list[Keyframe]:
        """Offer one keyframe; returns the keyframes now admitted, in order (maybe none)."""
        r = self.robot(kf.robot_id)
        if kf.seq < r.next_seq or kf.seq in r.held:
            r.duplicates += 1
            return []
        if kf.seq > r.next_seq:
            if len(r.held) >= self.reorder_window:
                log.error(
                    "robot %s: reorder window full (%d held, waiting for seq %d); "
                    "dropped seq %d (it will be resent)",
                    kf.robot_id,
                    len(r.held),
                    r.next_seq,
                    kf.seq,
                )
                return []
            r.held[kf.seq] = kf
            return []
        ready = [kf]
        while r.next_seq + len(ready) in r.held:
            ready.append(r.held.pop(r.next_seq + len(ready)))
        for k in ready:
            if r.stamps and k.stamp < r.stamps[-1]:
                log.warning(
                    "robot %s: keyframe %d stamp %.3f is before the previous one",
                    k.robot_id,
                    k.seq,
                    k.stamp,
                )
            r.stamps.append(k.stamp)
            r.poses_odom.append(pose7_to_pose4(k.pose_odom))
            r.points.append(scan_points(k))
            c = k.delta_cov
            prev = r.var_cumsum[-1] if r.var_cumsum else np.zeros(2)
            r.var_cumsum.append(
                prev
                + (np.zeros(2) if k.seq == 0 else np.array([0.5 * (c[0, 0] + c[1, 1]), c[5, 5]]))
            )
            r.keyframes.append(k)
        return ready

    def acked_seq(self, robot_id: str) -> int:
        """Highest seq such that every keyframe up to it is admitted (-1 if none)."""
        return self.robot(robot_id).next_seq - 1
