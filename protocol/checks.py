"""The checks messages make of their fields (`Message.validate`, protocol/messages.py):
what a process takes from the wire is refused here, not deep inside the one using it."""

from __future__ import annotations

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


def check_covariance(name: str, cov: np.ndarray) -> None:
    """Symmetric to 1e-9 of its largest entry (as the pose graph takes it: a looser
    test, relative 1e-5, let through one that stopped the base station) with a positive
    diagonal, and positive definite."""
    if np.abs(cov - cov.T).max() > 1e-9 * np.abs(cov).max() or np.any(np.diag(cov) <= 0.0):
        raise ProtocolError(f"{name} must be symmetric with a positive diagonal")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise ProtocolError(f"{name} is not positive definite") from None


def check_frame(frame: str, allowed: tuple[str, ...] = ("odom", "map")) -> None:
    if frame not in allowed:
        raise ProtocolError(f"frame must be one of {allowed}, got {frame!r}")
