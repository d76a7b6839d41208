"""Predicts the pose at the next scan from odometry (or constant velocity).

With odometry, the prediction is the last matched pose composed with the
odometry motion since that scan; without it, the last velocity is held.
"""

from __future__ import annotations

import numpy as np

from common.geometry import se2_compose, se2_inverse


class PoseExtrapolator:
    def __init__(self, use_odometry: bool = True) -> None:
        self.use_odometry = use_odometry
        self._odom: np.ndarray | None = None  # latest odometry pose [x, y, yaw], its own frame
        self._odom_at_pose: np.ndarray | None = None
        self._poses: list[tuple[float, np.ndarray]] = []  # last two (stamp, T_local_base)

    def add_odometry(self, pose_xyyaw: np.ndarray) -> None:
        self._odom = np.asarray(pose_xyyaw, dtype=np.float64)

    def add_pose(self, stamp: float, pose: np.ndarray) -> None:
        self._poses = [*self._poses[-1:], (stamp, np.asarray(pose, dtype=np.float64).copy())]
        self._odom_at_pose = None if self._odom is None else self._odom.copy()

    @property
    def has_pose(self) -> bool:
        return bool(self._poses)

    def predict(self, stamp: float) -> np.ndarray:
        if not self._poses:
            return np.zeros(3)
        t1, p1 = self._poses[-1]
        if self.use_odometry and self._odom is not None and self._odom_at_pose is not None:
            return se2_compose(p1, se2_compose(se2_inverse(self._odom_at_pose), self._odom))
        if len(self._poses) == 2:
            t0, p0 = self._poses[0]
            if t1 > t0:
                step = se2_compose(se2_inverse(p0), p1)
                return se2_compose(p1, step * ((stamp - t1) / (t1 - t0)))
        return p1.copy()
