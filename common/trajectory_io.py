"""Trajectories in the TUM format (one pose per line, readable by `evo`).

Line format: `timestamp tx ty tz qx qy qz qw` (s, m, Hamilton quaternion with the
scalar last), separated by spaces (commas are accepted on read); lines starting
with '#' are comments. A georeferenced trajectory (``map`` = ENU, seed 000 §III)
carries its frame's WGS84 origin in a comment line that evo ignores:
``# wgs84_origin: LAT_DEG LON_DEG ALT_M``; files without it read as before.
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError, FileFormatError
from common.geodesy import GeoOrigin
from common.geometry import MAX_POSITION_M, quat_to_yaw, yaw_to_quat

logger = logging.getLogger(__name__)

_HEADER = "# timestamp tx ty tz qx qy qz qw"
_ORIGIN_TAG = "wgs84_origin:"


@dataclass(eq=False)
class Trajectory:
    """Timestamped 3-D poses of one body in one frame (e.g. `map` or `odom`)."""

    stamps: NDArray[np.float64]  # (N,) s, non-decreasing
    positions: NDArray[np.float64]  # (N, 3) m
    quats_xyzw: NDArray[np.float64]  # (N, 4) [qx, qy, qz, qw]
    wgs84_origin: GeoOrigin | None = None  # the frame's ENU origin if georeferenced

    def __post_init__(self) -> None:
        self.stamps = np.asarray(self.stamps, dtype=np.float64).reshape(-1)
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        self.quats_xyzw = np.asarray(self.quats_xyzw, dtype=np.float64).reshape(-1, 4)
        n = len(self.stamps)
        if len(self.positions) != n or len(self.quats_xyzw) != n:
            raise CollabSlamError(
                f"Trajectory: expected {n} positions and quaternions, got "
                f"{len(self.positions)} and {len(self.quats_xyzw)}"
            )
        if np.any(np.diff(self.stamps) < 0.0):
            raise CollabSlamError("Trajectory: stamps must be non-decreasing")

    @classmethod
    def from_pose4(cls, stamps: ArrayLike, poses: ArrayLike) -> Trajectory:
        """From (N,) stamps and (N, 4) [x, y, z, yaw] poses (m, rad)."""
        p = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
        return cls(stamps=np.asarray(stamps), positions=p[:, :3], quats_xyzw=yaw_to_quat(p[:, 3]))

    @classmethod
    def in_time_order(cls, stamps: ArrayLike, poses: ArrayLike, name: str = "") -> Trajectory:
        """`from_pose4` of the longest run of poses whose stamps do not go back (a
        subsequence): a pose stamped out of order (a sender's clock that jumped back, or
        far ahead once) is left out, the fewest possible, with a warning; the others
        stay (the base station had kept one such keyframe in its graph, and then failed
        to write every output at the end)."""
        t = np.asarray(stamps, dtype=np.float64).reshape(-1)
        p = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
        if np.all(np.diff(t) >= 0.0):
            return cls.from_pose4(t, p)
        keep = longest_non_decreasing(t)
        logger.warning("trajectory %s: %d poses stamped out of time order left out",
                    name, len(t) - len(keep))  # fmt: skip
        return cls.from_pose4(t[keep], p[keep])

    def poses_se2(self) -> NDArray[np.float64]:
        """(N, 3) [x, y, yaw] (z, roll and pitch dropped)."""
        return np.column_stack([self.positions[:, :2], quat_to_yaw(self.quats_xyzw)])

    def __len__(self) -> int:
        return len(self.stamps)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; an empty file (or only comments) is an empty trajectory."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{path}: cannot read trajectory: {exc}") from exc
    rows: list[list[float]] = []
    linenos: list[int] = []
    origin: GeoOrigin | None = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line.startswith("#") and line[1:].strip().startswith(_ORIGIN_TAG):
            origin = _parse_origin(line[1:].strip()[len(_ORIGIN_TAG) :], f"{path}:{lineno}")
            continue
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise FileFormatError(
                f"{path}:{lineno}: expected 8 values 'timestamp tx ty tz qx qy qz qw', "
                f"got {len(fields)}: {raw!r}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise FileFormatError(f"{path}:{lineno}: expected 8 numbers, got {raw!r}") from None
        rows.append(values)
        linenos.append(lineno)
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)
    bad = ~np.all(np.isfinite(data), axis=1)
    if bad.any():
        raise FileFormatError(f"{path}:{linenos[int(np.argmax(bad))]}: non-finite value")
    far = np.any(np.abs(data[:, 1:4]) > MAX_POSITION_M, axis=1)  # errors of inf had followed
    if far.any():
        raise FileFormatError(
            f"{path}:{linenos[int(np.argmax(far))]}: a position beyond {MAX_POSITION_M:g} m"
        )
    back = np.flatnonzero(np.diff(data[:, 0]) < 0.0)
    if back.size:
        raise FileFormatError(
            f"{path}:{linenos[int(back[0]) + 1]}: timestamp goes backwards "
            f"({data[back[0] + 1, 0]!r} after {data[back[0], 0]!r})"
        )
    norms = np.linalg.norm(data[:, 4:8], axis=1)
    off = np.abs(norms - 1.0) > 1e-3
    if off.any():
        raise FileFormatError(
            f"{path}:{linenos[int(np.argmax(off))]}: quaternion is not unit length "
            f"(norm {norms[int(np.argmax(off))]:.6f})"
        )
    logger.debug("read %d poses from %s", len(data), path)
    return Trajectory(
        stamps=data[:, 0], positions=data[:, 1:4], quats_xyzw=data[:, 4:8], wgs84_origin=origin
    )


def _parse_origin(text: str, where: str) -> GeoOrigin:
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
        return GeoOrigin.from_sequence(values)
    except (ValueError, CollabSlamError) as exc:
        raise FileFormatError(
            f"{where}: expected '# {_ORIGIN_TAG} LAT_DEG LON_DEG ALT_M', got {text!r} ({exc})"
        ) from None


def write_tum(path: str | Path, traj: Trajectory, wgs84_origin: GeoOrigin | None = None) -> None:
    """Write `traj` as TUM (stamps '%.9f', values '%.9f'), creating parent directories.

    ``wgs84_origin`` (default: ``traj.wgs84_origin``) goes into a header comment.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    table = np.column_stack([traj.stamps, traj.positions, traj.quats_xyzw])
    header = _HEADER[2:]
    origin = wgs84_origin or traj.wgs84_origin
    if origin is not None:
        lat, lon, alt = origin.as_list()
        header += f"\n{_ORIGIN_TAG} {lat!r} {lon!r} {alt!r}"
    with path.open("w", encoding="utf-8") as f:
        np.savetxt(f, table, fmt="%.9f", delimiter=" ", header=header, comments="# ")
    logger.debug("wrote %d poses to %s", len(traj), path)


def longest_non_decreasing(values: NDArray[np.float64]) -> NDArray[np.intp]:
    """Indices of a longest non-decreasing subsequence of `values` (patience sorting,
    O(n log n))."""
    tails: list[float] = []  # smallest last value of a run of each length
    tail_at: list[int] = []  # ... and its index
    parent = np.full(len(values), -1, dtype=np.intp)
    for i, v in enumerate(values.tolist()):
        k = bisect.bisect_right(tails, v)
        if k:
            parent[i] = tail_at[k - 1]
        if k == len(tails):
            tails.append(v)
            tail_at.append(i)
        else:
            tails[k], tail_at[k] = v, i
    out = []
    i = tail_at[-1] if tail_at else -1
    while i >= 0:
        out.append(i)
        i = int(parent[i])
    return np.array(out[::-1], dtype=np.intp)
