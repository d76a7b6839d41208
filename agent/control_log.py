"""The control-pose stream an agent records (one row per control tick), as CSV.

Each row: sensor stamp (s), then three pose7 `[x, y, z, qx, qy, qz, qw]`:
`T_odom_base` (local SLAM, never filtered), the latest raw correction
`T_map_odom` and the correction actually applied by the pose smoother. The
raw and smoothed control poses are `T_map_odom · T_odom_base` with either.
`bench smoothing` reads these files to measure the pose steps a controller saw.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from common.errors import FileFormatError
from common.row_spool import RowSpool

_POSES = ("odom_base", "map_odom_raw", "map_odom_applied")
_AXES = ("x", "y", "z", "qx", "qy", "qz", "qw")
HEADER = ",".join(["stamp"] + [f"{p}_{a}" for p in _POSES for a in _AXES])
COLUMNS = 1 + 7 * len(_POSES)


@dataclass
class ControlLog:
    """stamps (N,) s; T_odom_base, T_map_odom_raw, T_map_odom_applied (N, 7) pose7."""

    stamps: np.ndarray
    T_odom_base: np.ndarray
    T_map_odom_raw: np.ndarray
    T_map_odom_applied: np.ndarray

    def __len__(self) -> int:
        return len(self.stamps)

    @classmethod
    def from_rows(cls, rows: np.ndarray) -> ControlLog:
        rows = np.asarray(rows, dtype=np.float64).reshape(-1, COLUMNS)
        return cls(rows[:, 0], rows[:, 1:8], rows[:, 8:15], rows[:, 15:22])

    def rows(self) -> np.ndarray:
        return np.column_stack(
            [self.stamps, self.T_odom_base, self.T_map_odom_raw, self.T_map_odom_applied]
        )


def control_positions(T_map_odom: np.ndarray, T_odom_base: np.ndarray) -> np.ndarray:
    """(N, 3) map-frame positions (m) of T_map_odom · T_odom_base, both (N, 7) pose7."""
    return T_map_odom[:, :3] + Rotation.from_quat(T_map_odom[:, 3:7]).apply(T_odom_base[:, :3])


def correction_steps(
    T_map_odom: np.ndarray, T_odom_base: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-tick steps of the control pose beyond the robot's own (local) motion.

    Translation step k (m) = |C(k)·L(k) − C(k−1)·L(k)| with C = T_map_odom and
    L = T_odom_base: the jump the change of correction put into the position.
    Rotation step k (deg) = angle of C(k−1)⁻¹·C(k). Inputs (N, 7); outputs (N−1,).
    """
    r = Rotation.from_quat(T_map_odom[:, 3:7])
    p_prev = T_map_odom[:-1, :3] + r[:-1].apply(T_odom_base[1:, :3])
    trans = np.linalg.norm(control_positions(T_map_odom, T_odom_base)[1:] - p_prev, axis=1)
    rot = np.degrees((r[:-1].inv() * r[1:]).magnitude())
    return trans, rot


class ControlRecorder:
    """Collects one row per tick in a `RowSpool` (on disk: 176 bytes a tick, 40 Hz for
    1 h is 25 MB of file and nothing in memory)."""

    def __init__(self) -> None:
        self._rows = RowSpool(COLUMNS)

    def add(
        self,
        stamp: float,
        T_odom_base: np.ndarray,
        T_map_odom_raw: np.ndarray,
        T_map_odom_applied: np.ndarray,
    ) -> None:
        self._rows.append(
            np.concatenate([[stamp], T_odom_base, T_map_odom_raw, T_map_odom_applied])
        )

    def __len__(self) -> int:
        return len(self._rows)

    def log(self) -> ControlLog:
        return ControlLog.from_rows(self._rows.rows())


def write_control_log(path: str | Path, log: ControlLog) -> None:
    """Write a ControlLog as CSV with a header line."""
    rows = log.rows()
    if rows.ndim != 2 or rows.shape[1] != COLUMNS:
        raise FileFormatError(f"control log: expected (N, {COLUMNS}) rows, got {rows.shape}")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, rows, delimiter=",", header=HEADER, comments="", fmt="%.9f")


def read_control_log(path: str | Path) -> ControlLog:
    """Read a file written by `write_control_log`; checks the header and the shape."""
    p = Path(path)
    if not p.is_file():
        raise FileFormatError(f"control log not found: {p}")
    with p.open() as f:
        header = f.readline().strip()
    if header != HEADER:
        raise FileFormatError(f"{p}: expected the header {HEADER!r}, got {header[:80]!r}")
    rows = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
    if rows.size == 0:
        rows = np.zeros((0, COLUMNS))
    if rows.shape[1] != COLUMNS:
        raise FileFormatError(f"{p}: expected {COLUMNS} columns, got {rows.shape[1]}")
    return ControlLog.from_rows(rows)
