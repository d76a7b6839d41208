"""SE(2) / SE(3) helpers on plain numpy arrays.

Conventions (REP-105 names): a pose `T_a_b` maps points from frame b into frame a.
- SE(2) poses are arrays `[x, y, yaw]` (m, m, rad), yaw wrapped to (-pi, pi].
- 2.5-D poses are `[x, y, z, yaw]`.
- "pose7" is `[x, y, z, qx, qy, qz, qw]` (Hamilton quaternion, scalar last),
  the wire format of every pose in `protocol/`.
All functions accept a single pose (shape (3,)) or a stack (shape (N, 3)).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

# m: no pose, waypoint or trajectory point is farther out (10,000 km; a correction of
# 1e308 m had made every command NaN, a waypoint of 1e9 m sent a drone off toward it)
MAX_POSITION_M = 1e7


def wrap_angle(a: ArrayLike) -> FloatArray:
    """Wrap angles (rad) to (-pi, pi]."""
    a = np.asarray(a, dtype=np.float64)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def se2_compose(T_a_b: ArrayLike, T_b_c: ArrayLike) -> FloatArray:
    """T_a_c = T_a_b * T_b_c for [x, y, yaw] poses (broadcasts over stacks)."""
    a = np.asarray(T_a_b, dtype=np.float64)
    b = np.asarray(T_b_c, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def se2_inverse(T_a_b: ArrayLike) -> FloatArray:
    """T_b_a from T_a_b."""
    a = np.asarray(T_a_b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def se2_between(T_w_a: ArrayLike, T_w_b: ArrayLike) -> FloatArray:
    """T_a_b = inverse(T_w_a) * T_w_b: the motion from pose a to pose b."""
    return se2_compose(se2_inverse(T_w_a), T_w_b)


def se2_transform_points(T_a_b: ArrayLike, points_b: ArrayLike) -> FloatArray:
    """Map (N, 2) points from frame b to frame a."""
    T = np.asarray(T_a_b, dtype=np.float64)
    p = np.asarray(points_b, dtype=np.float64)
    c, s = np.cos(T[2]), np.sin(T[2])
    R = np.array([[c, -s], [s, c]])
    return p @ R.T + T[:2]


def se2_rotate_covariance(cov: ArrayLike, yaw: float) -> FloatArray:
    """A 3x3 [x, y, yaw] covariance in a frame turned by `yaw`: R cov R^T (from a
    frame b to a, with T_a_b's rotation `yaw`)."""
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R @ np.asarray(cov, dtype=np.float64) @ R.T


def se2_to_matrix(T: ArrayLike) -> FloatArray:
    """3x3 homogeneous matrix of an [x, y, yaw] pose."""
    x, y, yaw = np.asarray(T, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def yaw_to_quat(yaw: ArrayLike) -> FloatArray:
    """Quaternion [qx, qy, qz, qw] of a rotation by yaw (rad) about +z."""
    h = 0.5 * np.asarray(yaw, dtype=np.float64)
    z = np.zeros_like(h)
    return np.stack([z, z, np.sin(h), np.cos(h)], axis=-1)


def quat_to_yaw(q: ArrayLike) -> FloatArray:
    """Yaw (rad) of quaternions [qx, qy, qz, qw] (ZYX Euler convention)."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def rpy_to_quat(roll: float, pitch: float, yaw: float) -> FloatArray:
    """Quaternion [qx, qy, qz, qw] from ZYX Euler angles (rad)."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.array(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ]
    )


def quat_to_rpy(q: ArrayLike) -> tuple[float, float, float]:
    """ZYX Euler angles (roll, pitch, yaw) in rad of a quaternion [qx, qy, qz, qw]."""
    x, y, z, w = (float(v) for v in np.asarray(q, dtype=np.float64))
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return float(roll), float(pitch), float(yaw)


def pose4_to_pose7(p: ArrayLike) -> FloatArray:
    """[x, y, z, yaw] -> [x, y, z, qx, qy, qz, qw]."""
    p = np.asarray(p, dtype=np.float64)
    return np.concatenate([p[..., :3], yaw_to_quat(p[..., 3])], axis=-1)


def pose7_to_pose4(p: ArrayLike) -> FloatArray:
    """[x, y, z, qx, qy, qz, qw] -> [x, y, z, yaw] (roll and pitch dropped)."""
    p = np.asarray(p, dtype=np.float64)
    return np.concatenate([p[..., :3], quat_to_yaw(p[..., 3:7])[..., None]], axis=-1)


def pose4_compose(T_a_b: ArrayLike, T_b_c: ArrayLike) -> FloatArray:
    """2.5-D composition: SE(2) in the plane, heights add."""
    a = np.asarray(T_a_b, dtype=np.float64)
    b = np.asarray(T_b_c, dtype=np.float64)
    xy = se2_compose(a[..., [0, 1, 3]], b[..., [0, 1, 3]])
    z = a[..., 2] + b[..., 2]
    return np.stack([xy[..., 0], xy[..., 1], z, xy[..., 2]], axis=-1)


def pose4_inverse(T_a_b: ArrayLike) -> FloatArray:
    """2.5-D inverse."""
    a = np.asarray(T_a_b, dtype=np.float64)
    xy = se2_inverse(a[..., [0, 1, 3]])
    return np.stack([xy[..., 0], xy[..., 1], -a[..., 2], xy[..., 2]], axis=-1)


def map_to_odom(T_map_odom: ArrayLike, poses_map: ArrayLike) -> FloatArray:
    """Goals / waypoints [x, y, z, yaw] (..., 4) from `map` into a robot's `odom` frame
    with its correction T_map_odom [x, y, z, yaw] (seed 002 eq. 4)."""
    return pose4_compose(pose4_inverse(T_map_odom), poses_map)


def odom_to_map(T_map_odom: ArrayLike, poses_odom: ArrayLike) -> FloatArray:
    """The inverse of `map_to_odom`: poses in `odom` into `map`."""
    return pose4_compose(T_map_odom, poses_odom)
