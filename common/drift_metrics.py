"""Per-pose drift metrics of seed 003 (Tazir & Seube 2020, "Comparison of UAV LiDAR odometry
of rotating and fixed Velodyne platforms", ISPRS Archives XLIII-B1):

- eq. 8, RTE = ||t_GT - t_E||_2 (m), evaluated at every estimated pose;
- eq. 9, RRE = ||logm(R_E^T R_GT)||_F (rad), evaluated at every estimated pose. For a
  rotation by angle a, the Frobenius norm of the skew matrix logm(R) is sqrt(2) * |a|, so
  RRE = sqrt(2) * (angle of R_E^T R_GT); `RRE / sqrt(2)` is the usual angular error.

Despite their names both are errors of the poses themselves (the paper plots them over the
flight and quotes their average "along the full trajectory"), so `est` and `gt` must be in
the same frame; `align_first=True` optionally moves `est` onto `gt` at the first associated
pose (for estimates in an agent's own local frame). Association: `gt` is interpolated
(linear position, slerp rotation) at each `est` stamp inside gt's time span; other `est`
poses are dropped.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from common.errors import CollabSlamError
from common.trajectory_io import Trajectory

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class ErrorSeries:
    """One error value per associated estimated pose."""

    stamps: FloatArray  # (M,) s, the est stamps inside gt's span
    values: FloatArray  # (M,) m for RTE, rad (Frobenius norm) for RRE

    @property
    def mean(self) -> float:
        return float(self.values.mean()) if len(self.values) else float("nan")

    @property
    def rmse(self) -> float:
        return float(np.sqrt(np.mean(self.values**2))) if len(self.values) else float("nan")

    @property
    def max(self) -> float:
        return float(self.values.max()) if len(self.values) else float("nan")


@dataclass(frozen=True, eq=False)
class _Associated:
    stamps: FloatArray
    est_pos: FloatArray
    est_rot: Rotation
    gt_pos: FloatArray
    gt_rot: Rotation


def _associate(est: Trajectory, gt: Trajectory, align_first: bool) -> _Associated:
    if len(gt) < 2:
        raise CollabSlamError(f"drift metrics: ground truth needs >= 2 poses, got {len(gt)}")
    inside = (est.stamps >= gt.stamps[0]) & (est.stamps <= gt.stamps[-1])
    if not inside.any():
        raise CollabSlamError(
            f"drift metrics: no estimated pose inside the ground truth's time span "
            f"[{gt.stamps[0]:.6f}, {gt.stamps[-1]:.6f}]"
        )
    t = est.stamps[inside]
    # Slerp needs strictly increasing times: keep the last of repeated gt stamps.
    keep = np.append(np.diff(gt.stamps) > 0.0, True)
    gs, gp, gq = gt.stamps[keep], gt.positions[keep], gt.quats_xyzw[keep]
    if len(gs) < 2:
        raise CollabSlamError("drift metrics: ground truth spans no time")
    gt_rot = Slerp(gs, Rotation.from_quat(gq))(t)
    gt_pos = np.column_stack([np.interp(t, gs, gp[:, k]) for k in range(3)])
    est_pos = est.positions[inside]
    est_rot = Rotation.from_quat(est.quats_xyzw[inside])
    if align_first:
        # T_gt_est = T_gt(t0) * T_est(t0)^-1, applied to every estimated pose.
        r_align = gt_rot[0] * est_rot[0].inv()
        est_pos = r_align.apply(est_pos - est_pos[0]) + gt_pos[0]
        est_rot = r_align * est_rot
    return _Associated(t, est_pos, est_rot, gt_pos, gt_rot)


def relative_translation_error(
    est: Trajectory, gt: Trajectory, align_first: bool = False
) -> ErrorSeries:
    """Seed 003 eq. 8: ||t_GT - t_E||_2 (m) at every estimated pose inside gt's span."""
    a = _associate(est, gt, align_first)
    return ErrorSeries(a.stamps, np.linalg.norm(a.gt_pos - a.est_pos, axis=1))


def relative_rotation_error(
    est: Trajectory, gt: Trajectory, align_first: bool = False
) -> ErrorSeries:
    """Seed 003 eq. 9: ||logm(R_E^T R_GT)||_F (rad) = sqrt(2) * angle(R_E^T R_GT)."""
    a = _associate(est, gt, align_first)
    angle = (a.est_rot.inv() * a.gt_rot).magnitude()
    return ErrorSeries(a.stamps, math.sqrt(2.0) * np.asarray(angle, dtype=np.float64))


def drift_percent(est: Trajectory, gt: Trajectory, align_first: bool = False) -> float:
    """Final position error / distance flown * 100 (%).

    Final error: RTE at the last estimated pose inside gt's span. Distance flown: 3-D path
    length of gt between the first and last associated stamps (gt's own samples in between).
    """
    a = _associate(est, gt, align_first)
    t0, t1 = a.stamps[0], a.stamps[-1]
    mid = (gt.stamps > t0) & (gt.stamps < t1)
    path = np.vstack([a.gt_pos[:1], gt.positions[mid], a.gt_pos[-1:]])
    distance = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    if distance <= 0.0:
        raise CollabSlamError("drift_percent: the ground truth does not move")
    final_error = float(np.linalg.norm(a.gt_pos[-1] - a.est_pos[-1]))
    return 100.0 * final_error / distance
