"""Streaming reader for CARMEN log files (`.clf`, plain or bzip2-compressed).

Every message line is `NAME [contents] ipc_timestamp ipc_hostname logger_timestamp`.
Understood messages (the shipped Intel / ACES / MIT-CSAIL logs use only the first three):

- `PARAM name value ...`: updates `CarmenParams`; not yielded.
- `ODOM x y theta tv rv accel ...` -> `CarmenOdometry`.
- `FLASER n r1..rn x y theta odom_x odom_y odom_theta ...` -> `CarmenLaser`.
- `ROBOTLASER1 type start fov res maxrange accuracy remission_mode n r1..rn m e1..em
  laser_x laser_y laser_theta robot_x robot_y robot_theta tv rv fwd_safety side_safety
  turn_axis ...` -> `CarmenLaser` (beam geometry from the message itself).

Other message types (RLASER, TRUEPOS, RAWLASER*, SYNC, ...) are skipped (logged once per
type at debug level). Poses are `[x, y, theta]` (m, m, rad) in the log's odometry frame.

Beam geometry of FLASER when the log has no `laser_front_laser_*` PARAM lines follows
CARMEN's own reader (`carmen_string_to_robot_laser_message_orig`): first beam at -90 deg,
1 deg steps for 180/181 beams, 0.5 deg for 360/361, 0.25 deg for 400/401, otherwise
180 deg spread over n-1 steps; maximum range 80 m. Note that the shipped logs contain
range readings above 80 m (e.g. 81.91 m "no return" in MIT-CSAIL): consumers should treat
`r >= range_max` as no return. ACES's laser writes 50.00 m for no return, below that
guess: `saturation_range_m` finds such a value (the replay takes it as the range_max).
Ranges may be inf or nan (a driver's no return); poses and stamps must be finite. The
laser's mounting offset (ROBOTLASER1's laser pose, `robot_frontlaser_offset`) is read
but not applied: the shipped logs' is zero.

Timestamps: the `ipc_timestamp` (s). They are NOT monotonic in file order in every log
(intel.clf: 631 FLASER records are up to 0.9 s older than the previous FLASER); records are
yielded in file order and consumers that need time order must sort.
"""

from __future__ import annotations

import bz2
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

from common.errors import FileFormatError
from common.trajectory_io import Trajectory

logger = logging.getLogger(__name__)

DEFAULT_RANGE_MAX_M = 80.0  # CARMEN's guess for a SICK LMS when the log does not say

_BZ2_MAGIC = b"BZh"
_FLASER_TAIL = 9  # laser pose (3), odom pose (3), ipc_timestamp, hostname, logger_timestamp
_ODOM_FIELDS = 9  # x y theta tv rv accel ipc_timestamp hostname logger_timestamp


@dataclass(frozen=True, eq=False)
class CarmenLaser:
    """One front-laser scan (FLASER or ROBOTLASER1); beam i is at angle_min + i * angle_increment
    (rad, counter-clockwise, 0 = the laser's +x axis)."""

    stamp: float  # ipc_timestamp (s)
    ranges: NDArray[np.float32]  # (n,) m
    angle_min: float  # rad
    angle_increment: float  # rad
    range_max: float  # m
    odom_pose: NDArray[np.float64]  # [x, y, theta] odometry pose of the robot at the scan
    laser_pose: NDArray[np.float64]  # [x, y, theta] logged laser pose (front laser offset applied)


@dataclass(frozen=True, eq=False)
class CarmenOdometry:
    """One ODOM record."""

    stamp: float  # ipc_timestamp (s)
    pose: NDArray[np.float64]  # [x, y, theta] (m, m, rad)
    tv: float  # translational velocity (m/s)
    rv: float  # rotational velocity (rad/s)


# PARAM name -> (CarmenParams field, scale to m / rad, must be > 0)
_PARAM_FIELDS = {
    "robot_frontlaser_offset": ("frontlaser_offset_m", 1.0, False),
    "robot_frontlaser_side_offset": ("frontlaser_side_offset_m", 1.0, False),
    "robot_frontlaser_angular_offset": ("frontlaser_angular_offset_rad", 1.0, False),
    "laser_front_laser_fov": ("laser_fov_rad", math.pi / 180.0, True),
    "laser_front_laser_resolution": ("laser_resolution_rad", math.pi / 180.0, True),
    "robot_front_laser_max": ("laser_range_max_m", 1.0, True),
    "laser_front_laser_maxrange": ("laser_range_max_m", 1.0, True),
}


@dataclass
class CarmenParams:
    """Robot / laser parameters from PARAM lines. `None` means "not in the log": the
    CARMEN guesses from the beam count apply (see the module docstring).

    PARAM names read (CARMEN units in the log; stored here in m / rad):
    robot_frontlaser_offset (m, forward), robot_frontlaser_side_offset (m, left),
    robot_frontlaser_angular_offset (rad), laser_front_laser_fov (deg),
    laser_front_laser_resolution (deg), robot_front_laser_max or
    laser_front_laser_maxrange (m). Every PARAM line is also kept verbatim in `raw`.
    """

    frontlaser_offset_m: float = 0.0
    frontlaser_side_offset_m: float = 0.0
    frontlaser_angular_offset_rad: float = 0.0
    laser_fov_rad: float | None = None
    laser_resolution_rad: float | None = None
    laser_range_max_m: float | None = None
    raw: dict[str, str] = field(default_factory=dict)

    def update(self, name: str, value: str) -> None:
        """Apply one PARAM line (raises ValueError naming the rule if a known numeric
        parameter is not a finite number, or a laser's field of view, resolution or
        range not > 0: a maximum range of nan had every keyframe refused)."""
        if name not in _PARAM_FIELDS:
            self.raw[name] = value
            return
        number = float(value)
        if not math.isfinite(number):
            raise ValueError(f"expected a finite number, got {value!r}")
        attr, scale, positive = _PARAM_FIELDS[name]
        if positive and not number > 0.0:
            raise ValueError(f"expected a value > 0, got {value!r}")
        if name == "laser_front_laser_fov" and number > 360.0:
            raise ValueError(f"expected at most 360 deg, got {value!r}")
        self.raw[name] = value
        setattr(self, attr, scale * number)

    def beam_geometry(self, n: int) -> tuple[float, float, float]:
        """(angle_min, angle_increment, range_max) for an FLASER scan with n beams."""
        inc = self.laser_resolution_rad
        if inc is None:
            inc = guess_angle_increment(n)
        angle_min = -0.5 * self.laser_fov_rad if self.laser_fov_rad is not None else -0.5 * math.pi
        range_max = self.laser_range_max_m
        return angle_min, inc, DEFAULT_RANGE_MAX_M if range_max is None else range_max


def guess_angle_increment(n: int) -> float:
    """CARMEN's `carmen_laser_guess_angle_increment` for a SICK LMS with n beams (rad)."""
    if n in (180, 181):
        return math.pi / 180.0
    if n in (360, 361):
        return math.pi / 360.0
    if n in (400, 401):
        return math.pi / 720.0
    return math.pi / max(n - 1, 1)


def _open_text(path: Path) -> IO[str]:
    """Open a log as text, decompressing bzip2 on the fly (by suffix or magic bytes)."""
    try:
        with path.open("rb") as f:
            magic = f.read(3)
        if path.suffix == ".bz2" or magic == _BZ2_MAGIC:
            return bz2.open(path, "rt", encoding="ascii", errors="replace")
        return path.open("r", encoding="ascii", errors="replace")
    except OSError as exc:
        raise FileFormatError(f"{path}: cannot open CARMEN log: {exc}") from exc


def _lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number from 1, line) of a log; one that breaks off or is not the bzip2
    its name or first bytes say raises FileFormatError."""
    with _open_text(path) as stream:
        try:
            yield from enumerate(stream, start=1)
        except (OSError, EOFError) as exc:
            raise FileFormatError(f"{path}: cannot read CARMEN log: {exc}") from exc


def _numbers(
    path: Path, lineno: int, what: str, tokens: list[str], finite: bool = True
) -> NDArray[np.float64]:
    """Parse tokens as floats (`finite`: and finite) or raise a FileFormatError naming the
    first bad one. Ranges may be inf or nan: a driver's "no return" (a ROS LaserScan
    written to CARMEN), which the agent's preprocessing drops beam by beam."""
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise FileFormatError(f"{path}:{lineno}: {what}: expected a number, got {bad!r}") from None
    if finite and not math.isfinite(values.sum()):  # a NaN or inf anywhere propagates
        raise FileFormatError(f"{path}:{lineno}: {what}: non-finite value")
    return values


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _beam_count(path: Path, lineno: int, name: str, token: str) -> int:
    try:
        n = int(token)
    except ValueError:
        raise FileFormatError(
            f"{path}:{lineno}: {name}: expected an integer beam count, got {token!r}"
        ) from None
    if n < 0:
        raise FileFormatError(f"{path}:{lineno}: {name}: negative beam count {n}")
    return n


def _parse_flaser(path: Path, lineno: int, f: list[str], params: CarmenParams) -> CarmenLaser:
    if len(f) < 2:
        raise FileFormatError(f"{path}:{lineno}: FLASER: expected a beam count")
    n = _beam_count(path, lineno, "FLASER", f[1])
    if len(f) != 2 + n + _FLASER_TAIL:
        raise FileFormatError(
            f"{path}:{lineno}: FLASER: expected {n} ranges + 9 fields (laser x y theta, "
            f"odom x y theta, ipc_timestamp, hostname, logger_timestamp) = {n + 9} fields "
            f"after the beam count, got {len(f) - 2}"
        )
    v = np.concatenate([
        _numbers(path, lineno, "FLASER ranges", f[2 : 2 + n], finite=False),
        _numbers(path, lineno, "FLASER", f[2 + n : 2 + n + 7]),
    ])  # fmt: skip
    angle_min, inc, range_max = params.beam_geometry(n)
    return CarmenLaser(
        stamp=float(v[n + 6]),
        ranges=v[:n].astype(np.float32),
        angle_min=angle_min,
        angle_increment=inc,
        range_max=range_max,
        odom_pose=v[n + 3 : n + 6].copy(),
        laser_pose=v[n : n + 3].copy(),
    )


def _parse_robotlaser(path: Path, lineno: int, f: list[str]) -> CarmenLaser:
    name = f[0]
    if len(f) < 9:
        raise FileFormatError(f"{path}:{lineno}: {name}: expected 7 config fields and a beam count")
    cfg = _numbers(path, lineno, name, f[1:8])
    n = _beam_count(path, lineno, name, f[8])
    if len(f) < 10 + n:
        raise FileFormatError(f"{path}:{lineno}: {name}: expected {n} ranges and a remission count")
    m = _beam_count(path, lineno, name, f[9 + n])
    expected = 10 + n + m + 14  # poses (6), tv rv safety (2) turn_axis, ipc, host, logger
    if len(f) != expected:
        raise FileFormatError(
            f"{path}:{lineno}: {name}: expected {expected} fields for {n} ranges and "
            f"{m} remissions, got {len(f)}"
        )
    if not (cfg[3] > 0.0 and cfg[4] > 0.0):
        raise FileFormatError(
            f"{path}:{lineno}: {name}: expected an angular resolution and a maximum range "
            f"> 0, got {cfg[3]} and {cfg[4]}"
        )
    ranges = _numbers(path, lineno, f"{name} ranges", f[9 : 9 + n], finite=False)
    tail = _numbers(path, lineno, name, f[10 + n + m : expected - 2])
    return CarmenLaser(
        stamp=float(tail[11]),
        ranges=ranges.astype(np.float32),
        angle_min=float(cfg[1]),
        angle_increment=float(cfg[3]),
        range_max=float(cfg[4]),
        odom_pose=tail[3:6].copy(),
        laser_pose=tail[0:3].copy(),
    )


def _parse_odom(path: Path, lineno: int, f: list[str]) -> CarmenOdometry:
    if len(f) != 1 + _ODOM_FIELDS:
        raise FileFormatError(
            f"{path}:{lineno}: ODOM: expected 9 fields (x y theta tv rv accel ipc_timestamp "
            f"hostname logger_timestamp), got {len(f) - 1}"
        )
    try:
        x, y, theta, tv, rv, accel, stamp = (float(t) for t in f[1:8])
    except ValueError:
        _numbers(path, lineno, "ODOM", f[1:8])  # raises, naming the bad token
        raise
    if not math.isfinite(x + y + theta + tv + rv + accel + stamp):
        raise FileFormatError(f"{path}:{lineno}: ODOM: non-finite value")
    return CarmenOdometry(stamp=stamp, pose=np.array([x, y, theta]), tv=tv, rv=rv)


def _apply_param(path: Path, lineno: int, f: list[str], params: CarmenParams) -> None:
    if len(f) < 3:
        raise FileFormatError(f"{path}:{lineno}: PARAM: expected 'PARAM name value ...'")
    try:
        params.update(f[1], f[2])
    except ValueError as exc:
        why = str(exc) if str(exc).startswith("expected") else f"expected a number, got {f[2]!r}"
        raise FileFormatError(f"{path}:{lineno}: PARAM {f[1]}: {why}") from None


MALFORMED_LOGGED = 10  # malformed lines logged one by one (drop_malformed); then a count


def read_carmen(
    path: str | Path,
    start: float | None = None,
    end: float | None = None,
    drop_malformed: bool = False,
    quiet: bool = False,
) -> Iterator[CarmenLaser | CarmenOdometry]:
    """Yield the laser and odometry records of a CARMEN log in file order.

    `start` / `end` (s, inclusive) keep only records whose ipc_timestamp is in range.
    PARAM lines update the beam geometry of the FLASER records that follow them.
    Raises FileFormatError("path:LINE: ...") on the first malformed known message, or
    with `drop_malformed` logs it as an error and goes on with the next line (a replay
    an hour long is not stopped by one bad line; the first `MALFORMED_LOGGED` are
    logged, then how many in all at the end; none `quiet`: a pre-pass over the log).
    """
    path = Path(path)
    params = CarmenParams()
    skipped: set[str] = set()
    lo = -math.inf if start is None else start
    hi = math.inf if end is None else end
    dropped = 0
    for lineno, line in _lines(path):
        f = line.split()
        if not f or f[0].startswith("#"):
            continue
        kind = f[0]
        record: CarmenLaser | CarmenOdometry
        try:
            if kind == "FLASER":
                record = _parse_flaser(path, lineno, f, params)
            elif kind == "ODOM":
                record = _parse_odom(path, lineno, f)
            elif kind == "ROBOTLASER1":
                record = _parse_robotlaser(path, lineno, f)
            elif kind == "PARAM":
                _apply_param(path, lineno, f, params)
                continue
            else:
                if kind not in skipped:
                    skipped.add(kind)
                    logger.debug("%s:%d: skipping %s messages", path, lineno, kind)
                continue
        except FileFormatError as exc:
            if not drop_malformed:
                raise
            dropped += 1
            if dropped <= MALFORMED_LOGGED and not quiet:
                logger.error("%s (line dropped)", exc)
            continue
        if lo <= record.stamp <= hi:
            yield record
    if dropped > MALFORMED_LOGGED and not quiet:
        logger.error("%s: %d malformed lines dropped in all", path, dropped)


def read_carmen_params(path: str | Path) -> CarmenParams:
    """All PARAM lines of a log (a later line overrides an earlier one)."""
    path = Path(path)
    params = CarmenParams()
    for lineno, line in _lines(path):
        if line.startswith("PARAM"):
            _apply_param(path, lineno, line.split(), params)
    return params


def carmen_time_span(path: str | Path) -> tuple[float, float]:
    """(earliest, latest) FLASER / ROBOTLASER1 ipc_timestamp (s) of a log's well-formed
    scans (a malformed one is left out, as a replay drops it: its stamp may be a range).

    Min / max rather than first / last line, because stamps can go backwards in file order.
    """
    path = Path(path)
    lo, hi = math.inf, -math.inf
    params = CarmenParams()  # beam geometry does not change which lines are well formed
    for lineno, line in _lines(path):
        f = line.split()
        try:
            if line.startswith("FLASER"):
                stamp = _parse_flaser(path, lineno, f, params).stamp
            elif line.startswith("ROBOTLASER1"):
                stamp = _parse_robotlaser(path, lineno, f).stamp
            else:
                continue
        except FileFormatError:
            continue
        lo, hi = min(lo, stamp), max(hi, stamp)
    if lo > hi:
        raise FileFormatError(f"{path}: no well-formed FLASER or ROBOTLASER1 record")
    return lo, hi


def saturation_range_m(path: str | Path, min_fraction: float = 1e-3) -> float | None:
    """The range a log's laser writes for "no return" below its range_max, if any: the
    largest reading, when at least `min_fraction` of all readings are exactly that (ACES:
    50.00 m, 0.84 % of them, the next largest 49.91 m, under CARMEN's guessed 80 m; taken
    as returns, they drew arcs of wall 50 m around the building). None if there is none."""
    top, at_top, total = -math.inf, 0, 0
    for rec in read_carmen(path, drop_malformed=True, quiet=True):
        if not isinstance(rec, CarmenLaser) or not rec.ranges.size:
            continue
        r = rec.ranges[np.isfinite(rec.ranges) & (rec.ranges < rec.range_max)]
        total += rec.ranges.size
        if r.size and (m := float(r.max())) >= top:
            at_top = (at_top if m == top else 0) + int((r == m).sum())
            top = m
    return top if total and at_top >= min_fraction * total else None


def odometry_stamps_regular(
    path: str | Path,
    records: int = 200,
    burst_gap_s: float = 0.005,
    max_burst_fraction: float = 0.05,
) -> bool:
    """Whether the ODOM records' ipc timestamps say when the odometry was measured.

    Some logs stamp messages on arrival over a network link, so they come in bursts
    (Intel: 61 % of consecutive ODOM stamps less than 5 ms apart, some going back in
    time) and say little about when each pose was measured; others are regular (ACES:
    none under 5 ms, median 0.18 s). Looks at the first ``records`` ODOM stamps:
    regular if none goes back and at most ``max_burst_fraction`` of the gaps are under
    ``burst_gap_s``. False without ODOM records.
    """
    path = Path(path)
    stamps: list[float] = []
    for lineno, line in _lines(path):
        if not line.startswith("ODOM"):
            continue
        try:
            stamps.append(_parse_odom(path, lineno, line.split()).stamp)
        except FileFormatError:  # (a torn line: the replay drops it, with a warning)
            continue
        if len(stamps) > records:
            break
    if len(stamps) < 2:
        return False
    gaps = np.diff(stamps)
    return bool(gaps.min() >= 0.0 and np.mean(gaps < burst_gap_s) <= max_burst_fraction)


def laser_odometry_trajectory(
    path: str | Path, start: float | None = None, end: float | None = None
) -> Trajectory:
    """The odometry poses logged with each laser scan, sorted by stamp (z = 0): the
    "no SLAM at all" baseline for the relation metric, at exactly the relations' stamps."""
    stamps: list[float] = []
    poses: list[NDArray[np.float64]] = []
    for record in read_carmen(path, start, end):
        if isinstance(record, CarmenLaser):
            stamps.append(record.stamp)
            poses.append(record.odom_pose)
    t = np.array(stamps, dtype=np.float64)
    p = np.array(poses, dtype=np.float64).reshape(-1, 3)
    order = np.argsort(t, kind="stable")
    pose4 = np.column_stack([p[order, :2], np.zeros(len(t)), p[order, 2]])
    return Trajectory.from_pose4(t[order], pose4)
