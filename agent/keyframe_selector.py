"""Cuts base-station keyframes every `distance` metres or `angle` radians (seed 002).

Computes each keyframe's relative motion since the previous keyframe and its
covariance from a simple odometry error model (std grows with distance and
rotation), in the 6x6 [x, y, z, roll, pitch, yaw] order of the protocol.
"""

from __future__ import annotations

import numpy as np

from common.config import AgentConfig
from common.geometry import pose4_compose, pose4_inverse, se2_rotate_covariance, wrap_angle


class KeyframeSelector:
    def __init__(self, cfg: AgentConfig) -> None:
        self.cfg = cfg
        self.last_pose: np.ndarray | None = None  # T_odom_base [x, y, z, yaw] of last keyframe

    def is_due(self, T_odom_base: np.ndarray) -> bool:
        if self.last_pose is None:
            return True
        d = pose4_compose(pose4_inverse(self.last_pose), T_odom_base)
        return bool(
            np.hypot(d[0], d[1]) >= self.cfg.keyframe_distance_m
            or abs(wrap_angle(d[3])) >= self.cfg.keyframe_angle_rad
        )

    def cut(
        self, T_odom_base: np.ndarray, match_cov: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Accept a keyframe at T_odom_base: (delta [x, y, z, yaw], 6x6 covariance).
        `match_cov`: the scan match's 3x3 [x, y, yaw] covariance (odom frame), added
        turned into the keyframe's own frame, the delta's (it carries a corridor's
        degenerate direction to the graph; added unturned, a corridor along y in odom
        had swapped its sigmas along and across)."""
        if self.last_pose is None:
            delta = np.zeros(4)
        else:
            delta = pose4_compose(pose4_inverse(self.last_pose), T_odom_base)
        self.last_pose = np.asarray(T_odom_base, dtype=np.float64).copy()
        cov = self.covariance(delta)
        if match_cov is not None:
            turned = se2_rotate_covariance(match_cov, -float(T_odom_base[3]))
            cov[np.ix_([0, 1, 5], [0, 1, 5])] += turned
        return delta, cov

    def covariance(self, delta: np.ndarray) -> np.ndarray:
        c = self.cfg
        dist = float(np.hypot(delta[0], delta[1]))
        sxy = max(c.odom_sigma_min, c.odom_sigma_per_m * dist)
        sz = max(c.odom_sigma_min, c.odom_sigma_per_m * abs(float(delta[2])))
        syaw = max(
            c.odom_sigma_min,
            c.odom_sigma_yaw_per_rad * abs(float(delta[3])) + c.odom_sigma_yaw_per_m * dist,
        )
        srp = c.odom_sigma_min
        return np.diag([sxy, sxy, sz, srp, srp, syaw]) ** 2
