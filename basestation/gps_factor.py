"""GPS position factors on a 2-D pose graph (seed 000 §III, eq. 3-7).

A fix ``p_GPS,k`` (ENU east/north, m, in the ``map`` frame) taken at ``t_k``
between two nodes i, j of one robot's chain (``t_i <= t_k <= t_j``) constrains the
antenna position interpolated between them (eq. 3):

    r = (1 - beta) * a_i + beta * a_j - p_GPS,k,   beta = (t_k - t_i) / (t_j - t_i),
    a_n = t_n + R(theta_n) * l   (antenna of node n, lever arm l in the body frame).

The paper slerps the whole pose and takes its position; in 2-D with the lever arm
that is (1 - beta) t_i + beta t_j + R(theta(beta)) l. We interpolate the two
antenna positions instead: identical without a lever arm, and within
|l| * (1 - cos(dtheta/2)) of it with one (< 1 mm for l = 0.3 m and a 0.1 rad
keyframe turn).

The graph is planar (``Pose2``): only east and north enter the residual. The up
sigma still matters for eq. 6 (the isotropic weight is the worst of all three);
altitude itself is handled by the GNSS model and ENU conversion, not the graph.

Weights (whitening ``W r``, ``W = diag(w)``), per axis from the reported sigmas:
- ``inverse``   (eq. 5): sigma' = sigma (per axis)
- ``isotropic`` (eq. 6): sigma' = max(sigma_east, sigma_north, sigma_up)

and with the user's a, b (eq. 7; a = 1, b = 0 by default) w = a / sigma' + b, for
either (an ``affine`` weighting of its own had been the only one to read a, b).
An optional Huber loss (``gtsam.noiseModel.Robust``) bounds the pull of outliers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError

FloatArray = NDArray[np.float64]
WEIGHTINGS = ("inverse", "isotropic")


@dataclass(frozen=True)
class GpsWeighting:
    """How reported sigmas become factor weights; see the module docstring."""

    mode: str = "inverse"  # inverse | isotropic
    a: float = 1.0  # eq. 7: w = a / sigma' + b
    b: float = 0.0  # eq. 7, 1/m
    huber_k: float | None = 1.345  # whitened units; None: plain least squares
    sigma_min_m: float = 0.05  # m, floor on every reported sigma
    lever_arm: tuple[float, float] = (0.0, 0.0)  # m, antenna in the body frame (x fwd, y left)

    def __post_init__(self) -> None:
        if self.mode not in WEIGHTINGS:
            raise CollabSlamError(f"GPS weighting must be one of {WEIGHTINGS}, got {self.mode!r}")
        if self.a < 0 or self.b < 0 or not (self.a > 0 or self.b > 0):
            raise CollabSlamError(f"GPS weights need a, b >= 0, not both 0: {self.a}, {self.b}")
        if self.huber_k is not None and not self.huber_k > 0:
            raise CollabSlamError(f"huber_k must be > 0, got {self.huber_k}")

    @classmethod
    def from_config(cls, gps: Any) -> GpsWeighting:
        """From a ``common.config.GpsConfig``."""
        return cls(
            mode=gps.weighting,
            a=gps.a,
            b=gps.b,
            huber_k=gps.huber_k if gps.huber else None,
            sigma_min_m=gps.sigma_min_m,
            lever_arm=(gps.antenna_x_m, gps.antenna_y_m),
        )


def gps_weights(sigmas_enu: ArrayLike, weighting: GpsWeighting) -> FloatArray:
    """(3,) per-axis weights [w_east, w_north, w_up] (1/m) for reported sigmas (eq. 5-7)."""
    s = np.asarray(sigmas_enu, dtype=np.float64).reshape(-1)
    if s.shape != (3,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise CollabSlamError(f"GPS sigmas must be 3 finite values > 0, got {sigmas_enu!r}")
    s = np.maximum(s, weighting.sigma_min_m)
    if weighting.mode == "isotropic":
        s = np.full(3, s.max())
    return weighting.a / s + weighting.b


def gps_noise(sigmas_enu: ArrayLike, weighting: GpsWeighting) -> gtsam.noiseModel.Base:
    """The factor's noise model: diagonal with sigma = 1 / w over (east, north), maybe Huber."""
    w = gps_weights(sigmas_enu, weighting)[:2]
    noise = gtsam.noiseModel.Diagonal.Sigmas(1.0 / w)
    if weighting.huber_k is None:
        return noise
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(weighting.huber_k), noise
    )


def interpolation_factor(t_i: float, t_j: float, t_fix: float) -> float:
    """beta of eq. 3 (0 at node i, 1 at node j)."""
    if not t_i <= t_fix <= t_j:
        raise CollabSlamError(f"fix at {t_fix} s is not between the nodes at {t_i} and {t_j} s")
    return 0.0 if t_j <= t_i else (t_fix - t_i) / (t_j - t_i)


def gps_residual(
    pose_i: ArrayLike,
    pose_j: ArrayLike,
    beta: float,
    enu_xy: ArrayLike,
    lever_arm: ArrayLike = (0.0, 0.0),
) -> FloatArray:
    """Unwhitened eq. 3 residual (m) for poses [x, y, yaw] (map = ENU); numpy, no gtsam."""
    pi, pj = np.asarray(pose_i, float), np.asarray(pose_j, float)
    arm = np.asarray(lever_arm, float)

    def antenna(p: FloatArray) -> FloatArray:
        c, s = np.cos(p[2]), np.sin(p[2])
        return p[:2] + np.array([c * arm[0] - s * arm[1], s * arm[0] + c * arm[1]])

    return (1.0 - beta) * antenna(pi) + beta * antenna(pj) - np.asarray(enu_xy, float)


def _error_function(beta: float, enu_xy: FloatArray, arm: FloatArray) -> Any:
    """The CustomFactor callback; Jacobians in gtsam's Pose2 tangent [vx, vy, omega]."""

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: Any) -> FloatArray:
        ki, kj = this.keys()[0], this.keys()[1]
        out = -enu_xy.copy()
        jacobians = []
        for key, w in ((ki, 1.0 - beta), (kj, beta)):
            p = values.atPose2(key)
            c, s = np.cos(p.theta()), np.sin(p.theta())
            R = np.array([[c, -s], [s, c]])
            out += w * (np.array([p.x(), p.y()]) + R @ arm)
            if H is not None:
                # retract(xi): t' = t + R v, theta' = theta + omega (to first order), so
                # d(antenna)/d(v) = R and d(antenna)/d(omega) = R [-l_y, l_x].
                J = np.zeros((2, 3))
                J[:, :2] = w * R
                J[:, 2] = w * (R @ np.array([-arm[1], arm[0]]))
                jacobians.append(J)
        if H is not None:
            H[0], H[1] = jacobians
        return out

    return error


def make_gps_factor(
    key_i: int,
    key_j: int,
    beta: float,
    enu_xy: ArrayLike,
    noise: gtsam.noiseModel.Base,
    lever_arm: ArrayLike = (0.0, 0.0),
) -> gtsam.CustomFactor:
    """A 2-key gtsam factor for one fix between nodes ``key_i`` and ``key_j`` (eq. 3)."""
    if key_i == key_j:
        raise CollabSlamError("a GPS factor needs two different nodes")
    if not 0.0 <= beta <= 1.0:
        raise CollabSlamError(f"beta must be in [0, 1], got {beta}")
    xy = np.asarray(enu_xy, dtype=np.float64).reshape(-1)
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        raise CollabSlamError(f"GPS fix must be a finite [east, north], got {enu_xy!r}")
    arm = np.asarray(lever_arm, dtype=np.float64).reshape(2)
    return gtsam.CustomFactor(noise, [key_i, key_j], _error_function(float(beta), xy, arm))
