"""The checks messages make of their fields (`Message.validate`, protocol/messages.py):
what a process takes from the wire is refused here, not deep inside the one using it."""

from __future__ import annotations

import math
import re

import numpy as np

from common.errors import ProtocolError
from common.geometry import MAX_POSITION_M

ROBOT_ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")


def check_robot_id(robot_id: str) -> None:
    if not ROBOT_ID_RE.match(robot_id):
        raise ProtocolError(
            f"robot_id {robot_id!r} is invalid: expected 1-32 letters, digits, '_' or '-'"
        )


def check_position(name: str, xyz: np.ndarray) -> None:
    if xyz.size and float(np.abs(xyz).max()) > MAX_POSITION_M:
        raise ProtocolError(f"{name}: a position beyond {MAX_POSITION_M:g} m")


def check_pose7(name: str, pose: np.ndarray) -> None:
    check_position(name, pose[:3])
    norm = float(np.linalg.norm(pose[3:7]))
    if abs(norm - 1.0) > 1e-3:
        raise ProtocolError(f"{name}: quaternion norm is {norm:.6f}, expected 1")


MAX_TILT_DEG = 60.0  # a drone's attitude from level; past it, not a flying drone's


def check_upright(name: str, q_xyzw: np.ndarray) -> None:
    """A drone's attitude within `MAX_TILT_DEG` of level. A quaternion in w, x, y, z order
    (PX4's) read as x, y, z, w makes a level drone yawed 0.3 rad look rolled 163 degrees:
    its scans were levelled onto the other side, its odometry read as never turning."""
    x, y = float(q_xyzw[0]), float(q_xyzw[1])
    up = 1.0 - 2.0 * (x * x + y * y)  # the body z axis's vertical part
    if up < math.cos(math.radians(MAX_TILT_DEG)):
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, up))))
        raise ProtocolError(f"{name}: the body tilted {tilt:.0f} degrees from level (beyond "
                            f"{MAX_TILT_DEG:.0f}): a quaternion in w, x, y, z order? expected "
                            "x, y, z, w")  # fmt: skip


def check_covariance(name: str, cov: np.ndarray) -> None:
    """Symmetric to 1e-9 of its largest entry (as the pose graph takes it: a looser
    test, relative 1e-5, let through one that stopped the base station) with a positive
    diagonal, and positive definite."""
    if np.abs(cov - cov.T).max() > 1e-9 * np.abs(cov).max() or np.any(np.diag(cov) <= 0.0):
        raise ProtocolError(f"{name} must be symmetric with a positive diagonal")
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise ProtocolError(f"{name} is not positive definite") from None
    # each variance given the ones before it (the pivots): a correlation within 1e-9 of
    # +-1 had passed here, been refused by the pose graph's own test, and stopped the
    # base station at every restart (its agent sent it again)
    if np.any(np.diag(chol) ** 2 < 1e-9 * np.diag(cov)):
        raise ProtocolError(f"{name} is nearly singular (a correlation within 1e-9 of 1)")


MAX_SCAN_SPAN_RAD = 2.0 * math.pi * (1.0 + 1e-3)  # first to last beam: one turn at most


def check_scan_angles(name: str, angle_min: float, angle_increment: float, beams: int) -> None:
    """A scan's beams within one turn from an angle_min within two turns of 0: angles far
    beyond (an increment of 1e37) had become inf in the map's float32 angles and stopped
    the base station, at every restart too (the keyframe was stored)."""
    if angle_increment == 0.0:
        raise ProtocolError(f"{name}.angle_increment is 0")
    span = abs(angle_increment) * max(beams - 1, 0)
    if abs(angle_min) > 4.0 * math.pi or span > MAX_SCAN_SPAN_RAD:
        raise ProtocolError(
            f"{name}: angle_min {angle_min:.6g} rad and {beams} beams of "
            f"{angle_increment:.6g} rad: expected |angle_min| <= 4 pi and one turn at most"
        )


def check_frame(frame: str, allowed: tuple[str, ...] = ("odom", "map")) -> None:
    if frame not in allowed:
        raise ProtocolError(f"frame must be one of {allowed}, got {frame!r}")
