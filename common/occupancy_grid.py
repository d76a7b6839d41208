"""Log-odds occupancy grid with laser-ray insertion (numba kernel).

Cell (ix, iy) covers [ox + ix * res, ox + (ix + 1) * res) x [oy + iy * res, ...) in
the frame the grid lives in (usually `map` or a robot's `odom`); arrays are
indexed [iy, ix] like `GridMap.data`.

Update rule per scan (as cartographer's `CastRays` and octomap do): every cell is
updated at most once per scan, and hits win over misses, so a wall cell hit by one
beam is not cleared by a neighbouring grazing beam of the same scan. With the default
probabilities a cell therefore needs one hit to read as occupied (0.70 > 0.65) but four
scans that see through it to read as free at map_server's 0.196 (0.4 -> 0.31 -> 0.23 ->
0.17), two at the base station's published map's `map.free_thresh` 0.35.

Free space is traced with an 8-connected (Bresenham-like) walk: one cell per column
(or row), the one the beam crosses at that column's centre line.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit, uint64
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError, ConfigError
from common.map_io import FREE, OCCUPIED, UNKNOWN, GridMap

logger = logging.getLogger(__name__)


def logodds(p: float) -> float:
    """log(p / (1 - p))."""
    return math.log(p / (1.0 - p))


@njit(cache=True)
def _clip_segment(
    u0: float, v0: float, du: float, dv: float, w: float, h: float
) -> tuple[float, float]:
    """Liang-Barsky: parameter interval [t0, t1] of u0 + t du inside [0, w] x [0, h]."""
    t0 = 0.0
    t1 = 1.0
    for p, q in ((-du, u0), (du, w - u0), (-dv, v0), (dv, h - v0)):
        if p == 0.0:
            if q < 0.0:
                return 1.0, 0.0
        else:
            r = q / p
            if p < 0.0:
                if r > t0:
                    t0 = r
            elif r < t1:
                t1 = r
    return t0, t1


# Bits of the per-cell `flags` array (uint8). MISS/HIT only live during one scan.
_MISS = 1
_HIT = 2
_OBSERVED = 4
_FIX_SHIFT = 32  # fixed-point fraction bits of the ray walker


@njit(cache=True)
def _mark_ray(
    flags: np.ndarray, w: int, h: int, su: float, sv: float, eu: float, ev: float, skip_last: bool
) -> None:
    """Flag as MISS the cells of the segment (su, sv) -> (eu, ev) (cell units, inside the
    grid box): one cell per column (x-major) or row (y-major), taken where the segment
    crosses that column's/row's centre line (8-connected, like Bresenham). The end cell
    is left out if `skip_last`. Fixed-point stepping keeps the loop free of branches.
    """
    ix = min(max(int(math.floor(su)), 0), w - 1)
    iy = min(max(int(math.floor(sv)), 0), h - 1)
    ex = min(max(int(math.floor(eu)), 0), w - 1)
    ey = min(max(int(math.floor(ev)), 0), h - 1)
    nx = abs(ex - ix)
    ny = abs(ey - iy)
    steps = max(nx, ny)
    if steps > 0 or not skip_last:
        flags[uint64(iy * w + ix)] |= _MISS
    if steps == 0:
        return
    if not skip_last:
        flags[uint64(ey * w + ex)] |= _MISS
    one = 1 << _FIX_SHIFT
    if nx >= ny:
        step = 1 if ex > ix else -1
        slope = (ev - sv) / (eu - su)
        cx = ix + step
        yf = np.int64((sv + (cx + 0.5 - su) * slope) * one)
        dyf = np.int64(slope * step * one)
        for _ in range(steps - 1):
            cy = min(max(yf >> _FIX_SHIFT, 0), h - 1)
            flags[uint64(cy * w + cx)] |= _MISS
            yf += dyf
            cx += step
    else:
        step = 1 if ey > iy else -1
        slope = (eu - su) / (ev - sv)
        cy = iy + step
        xf = np.int64((su + (cy + 0.5 - sv) * slope) * one)
        dxf = np.int64(slope * step * one)
        for _ in range(steps - 1):
            cx = min(max(xf >> _FIX_SHIFT, 0), w - 1)
            flags[uint64(cy * w + cx)] |= _MISS
            xf += dxf
            cy += step


@njit(cache=True)
def _cast_scan(
    log_odds: np.ndarray,
    flags: np.ndarray,
    u0: float,
    v0: float,
    yaw: float,
    inv_res: float,
    ranges: np.ndarray,
    angles: np.ndarray,
    range_min: float,
    range_max: float,
    free_range: float,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
) -> None:
    """Apply one scan; sensor at (u0, v0) in cell units, ranges in metres.

    Flags HIT and MISS cells first, then updates every flagged cell once (HIT wins),
    sweeping only the bounding box of the scan.
    """
    h, w = log_odds.shape
    lo = log_odds.ravel()
    fl = flags.ravel()
    bx0, by0, bx1, by1 = w, h, -1, -1
    n = ranges.shape[0]
    for i in range(n):
        r = ranges[i]
        if not np.isfinite(r) or r < range_min:
            continue
        is_hit = r < range_max
        length = r if is_hit else free_range
        if length <= 0.0:
            continue
        a = yaw + angles[i]
        du = length * inv_res * math.cos(a)
        dv = length * inv_res * math.sin(a)
        hu = u0 + du
        hv = v0 + dv
        hit_inside = is_hit and 0.0 <= hu < w and 0.0 <= hv < h
        if hit_inside:
            fl[uint64(int(math.floor(hv)) * w + int(math.floor(hu)))] |= _HIT
        t0, t1 = _clip_segment(u0, v0, du, dv, float(w), float(h))
        if t0 > t1:
            continue
        su = u0 + t0 * du
        sv = v0 + t0 * dv
        eu = u0 + t1 * du
        ev = v0 + t1 * dv
        _mark_ray(fl, w, h, su, sv, eu, ev, hit_inside)
        for cu, cv in ((su, sv), (eu, ev)):
            cx = min(max(int(math.floor(cu)), 0), w - 1)
            cy = min(max(int(math.floor(cv)), 0), h - 1)
            bx0 = min(bx0, cx)
            bx1 = max(bx1, cx)
            by0 = min(by0, cy)
            by1 = max(by1, cy)
    # Unsigned indices: numba skips the negative-index wraparound, LLVM vectorizes.
    span = bx1 + 1 - bx0
    for cy in range(by0, by1 + 1):
        row = uint64(cy * w + bx0)
        for j in range(span):
            k = row + uint64(j)
            f = fl[k]
            old = lo[k]
            if f & _HIT:
                lo[k] = min(old + l_hit, l_max)
            elif f & _MISS:
                lo[k] = max(old + l_miss, l_min)
            fl[k] = _OBSERVED if f != 0 else 0


@njit(cache=True)
def _cast_scans(
    log_odds: np.ndarray,
    flags: np.ndarray,
    poses_cells: np.ndarray,
    inv_res: float,
    ranges: np.ndarray,
    angles: np.ndarray,
    range_min: float,
    range_max: float,
    free_range: float,
    l_hit: float,
    l_miss: float,
    l_min: float,
    l_max: float,
) -> None:
    """`_cast_scan` for each row of `ranges` (k, N), in order; poses_cells (k, 3):
    sensor [u0, v0] in cell units and yaw."""
    for k in range(ranges.shape[0]):
        _cast_scan(
            log_odds, flags, poses_cells[k, 0], poses_cells[k, 1], poses_cells[k, 2], inv_res,
            ranges[k], angles, range_min, range_max, free_range, l_hit, l_miss, l_min, l_max,
        )  # fmt: skip


class OccupancyGrid:
    """A growable log-odds occupancy grid (probabilities clamped to [p_min, p_max])."""

    def __init__(
        self,
        resolution: float,
        origin_xy: tuple[float, float],
        shape: tuple[int, int],
        p_hit: float = 0.7,
        p_miss: float = 0.4,
        p_min: float = 0.12,
        p_max: float = 0.97,
    ) -> None:
        """`origin_xy`: lower-left corner of cell (0, 0) (m); `shape`: (H, W) cells."""
        if not (math.isfinite(resolution) and resolution > 0.0):
            raise ConfigError(f"resolution must be > 0 m, got {resolution}")
        if not 0.0 < p_min < p_miss < 0.5 < p_hit < p_max < 1.0:
            raise ConfigError(
                "expected 0 < p_min < p_miss < 0.5 < p_hit < p_max < 1, got "
                f"p_min={p_min}, p_miss={p_miss}, p_hit={p_hit}, p_max={p_max}"
            )
        h, w = (int(v) for v in shape)
        if h <= 0 or w <= 0:
            raise ConfigError(f"shape must be positive (H, W), got {shape}")
        self._resolution = float(resolution)
        self._origin = (float(origin_xy[0]), float(origin_xy[1]))
        self._l_hit = logodds(p_hit)
        self._l_miss = logodds(p_miss)
        self._l_min = logodds(p_min)
        self._l_max = logodds(p_max)
        self._log_odds = np.zeros((h, w), dtype=np.float32)
        self._flags = np.zeros((h, w), dtype=np.uint8)  # _OBSERVED between scans

    @classmethod
    def from_bounds(
        cls,
        min_xy: ArrayLike,
        max_xy: ArrayLike,
        resolution: float,
        **kwargs: float,
    ) -> OccupancyGrid:
        """A grid whose origin is `min_xy` and that covers at least up to `max_xy` (m)."""
        lo = np.asarray(min_xy, dtype=np.float64)
        hi = np.asarray(max_xy, dtype=np.float64)
        if lo.shape != (2,) or hi.shape != (2,) or not np.all(hi > lo):
            raise ConfigError(f"expected min_xy < max_xy (2 values each), got {lo}, {hi}")
        w, h = np.maximum(np.ceil((hi - lo) / resolution - 1e-9), 1).astype(int)
        return cls(resolution, (float(lo[0]), float(lo[1])), (int(h), int(w)), **kwargs)

    @property
    def resolution(self) -> float:
        """Cell size in metres."""
        return self._resolution

    @property
    def origin_xy(self) -> tuple[float, float]:
        """Lower-left corner of cell (0, 0) in metres."""
        return self._origin

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) in cells."""
        h, w = self._log_odds.shape
        return int(h), int(w)

    @property
    def log_odds(self) -> NDArray[np.float32]:
        """Read-only (H, W) view of the log-odds."""
        view = self._log_odds.view()
        view.flags.writeable = False
        return view

    @property
    def observed(self) -> NDArray[np.bool_]:
        """(H, W) mask (a copy) of the cells any scan has updated since the last clear."""
        return self._flags != 0

    def insert_scan(
        self,
        T_map_sensor: ArrayLike,
        ranges: ArrayLike,
        angles: ArrayLike,
        range_min: float,
        range_max: float,
        max_free_range: float | None = None,
    ) -> None:
        """Insert one planar scan taken at sensor pose `T_map_sensor` = [x, y, yaw].

        `ranges` (m) and `angles` (rad, sensor frame) are (N,) arrays. Non-finite
        ranges and ranges < range_min are ignored. Ranges >= range_max are "no
        return": they clear free space up to min(range_max, max_free_range) and mark
        no hit. Parts of rays outside the grid are dropped (see `grow_to_include`).
        """
        pose = np.asarray(T_map_sensor, dtype=np.float64)
        r = np.ascontiguousarray(ranges, dtype=np.float32)
        a = np.ascontiguousarray(angles, dtype=np.float32)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise CollabSlamError(f"T_map_sensor must be a finite [x, y, yaw], got {pose}")
        if r.ndim != 1 or r.shape != a.shape or not np.all(np.isfinite(a)):
            raise CollabSlamError(
                f"ranges and angles must be (N,) arrays of one length, the angles finite "
                f"(a NaN had marked cell (0, 0) free), got {r.shape}, {a.shape}"
            )
        if not 0.0 <= range_min < range_max:
            raise CollabSlamError(
                f"expected 0 <= range_min < range_max, got {range_min}, {range_max}"
            )
        # Infinite only if range_max is, and then no finite range counts as "no return".
        free_range = range_max if max_free_range is None else min(range_max, max_free_range)
        inv_res = 1.0 / self._resolution
        _cast_scan(
            self._log_odds,
            self._flags,
            (pose[0] - self._origin[0]) * inv_res,
            (pose[1] - self._origin[1]) * inv_res,
            float(pose[2]),
            inv_res,
            r,
            a,
            float(range_min),
            float(range_max),
            float(free_range),
            np.float32(self._l_hit),
            np.float32(self._l_miss),
            np.float32(self._l_min),
            np.float32(self._l_max),
        )

    def insert_scans(
        self,
        T_map_sensor: ArrayLike,
        ranges: ArrayLike,
        angles: ArrayLike,
        range_min: float,
        range_max: float,
        max_free_range: float | None = None,
    ) -> None:
        """`insert_scan` for k scans of one geometry at once, in order (one call into
        the kernel): poses (k, 3) [x, y, yaw], ranges (k, N) in m, angles (N,)."""
        poses = np.asarray(T_map_sensor, dtype=np.float64).reshape(-1, 3)
        r = np.ascontiguousarray(ranges, dtype=np.float32)
        a = np.ascontiguousarray(angles, dtype=np.float32)
        if not np.all(np.isfinite(poses)) or not np.all(np.isfinite(a)):
            raise CollabSlamError("T_map_sensor rows [x, y, yaw] and angles must be finite")
        if r.ndim != 2 or r.shape != (len(poses), a.size) or a.ndim != 1:
            raise CollabSlamError(
                f"expected ranges ({len(poses)}, N) and angles (N,), got {r.shape}, {a.shape}"
            )
        if not 0.0 <= range_min < range_max:
            raise CollabSlamError(
                f"expected 0 <= range_min < range_max, got {range_min}, {range_max}"
            )
        free_range = range_max if max_free_range is None else min(range_max, max_free_range)
        inv_res = 1.0 / self._resolution
        cells = np.column_stack(
            [(poses[:, 0] - self._origin[0]) * inv_res, (poses[:, 1] - self._origin[1]) * inv_res,
             poses[:, 2]]
        )  # fmt: skip
        _cast_scans(
            self._log_odds, self._flags, cells, inv_res, r, a,
            float(range_min), float(range_max), float(free_range),
            np.float32(self._l_hit), np.float32(self._l_miss),
            np.float32(self._l_min), np.float32(self._l_max),
        )  # fmt: skip

    def grow_to_include(self, min_xy: ArrayLike, max_xy: ArrayLike, margin: float) -> None:
        """Make the grid cover the box [min_xy, max_xy] (m), keeping its content.

        No-op if the box is already covered. Otherwise each side that is too short is
        extended to the box plus `margin` (m), so a robot driving towards the edge
        triggers a reallocation only every `margin` metres. The cell lattice is kept.
        """
        lo = np.asarray(min_xy, dtype=np.float64)
        hi = np.asarray(max_xy, dtype=np.float64)
        if (
            lo.shape != (2,)
            or hi.shape != (2,)
            or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)))
        ):
            raise CollabSlamError(f"expected finite 2-D bounds, got {lo}, {hi}")
        if not margin >= 0.0:
            raise CollabSlamError(f"margin must be >= 0 m, got {margin}")
        res = self._resolution
        h, w = self.shape
        ox, oy = self._origin
        cur_lo = np.array([ox, oy])
        cur_hi = cur_lo + res * np.array([w, h])
        add_lo = np.where(lo < cur_lo, np.ceil((cur_lo - (lo - margin)) / res - 1e-9), 0)
        add_hi = np.where(hi > cur_hi, np.ceil(((hi + margin) - cur_hi) / res - 1e-9), 0)
        add_lo = np.maximum(add_lo, 0).astype(int)
        add_hi = np.maximum(add_hi, 0).astype(int)
        if not (add_lo.any() or add_hi.any()):
            return
        new_w = w + int(add_lo[0] + add_hi[0])
        new_h = h + int(add_lo[1] + add_hi[1])
        sx, sy = int(add_lo[0]), int(add_lo[1])
        for name in ("_log_odds", "_flags"):
            old = getattr(self, name)
            new = np.zeros((new_h, new_w), dtype=old.dtype)
            new[sy : sy + h, sx : sx + w] = old
            setattr(self, name, new)
        self._origin = (ox - sx * res, oy - sy * res)
        logger.debug("grid grown from %d x %d to %d x %d cells", w, h, new_w, new_h)

    def region(self, min_xy: ArrayLike, max_xy: ArrayLike) -> tuple[slice, slice]:
        """(rows, cols) slices of the cells covering the box [min_xy, max_xy] (m), clipped
        to the grid (possibly empty)."""
        lo = np.asarray(min_xy, dtype=np.float64)
        hi = np.asarray(max_xy, dtype=np.float64)
        h, w = self.shape
        c0, r0 = np.floor((lo - self._origin) / self._resolution).astype(int)
        c1, r1 = np.ceil((hi - self._origin) / self._resolution).astype(int)
        return slice(max(r0, 0), min(max(r1, 0), h)), slice(max(c0, 0), min(max(c1, 0), w))

    def empty_like_region(self, rows: slice, cols: slice) -> OccupancyGrid:
        """An empty grid on the same lattice and sensor model covering cells [rows, cols]."""
        res = self._resolution
        g = OccupancyGrid.__new__(OccupancyGrid)
        g.__dict__.update(self.__dict__)
        g._origin = (self._origin[0] + cols.start * res, self._origin[1] + rows.start * res)
        shape = (rows.stop - rows.start, cols.stop - cols.start)
        g._log_odds = np.zeros(shape, dtype=np.float32)
        g._flags = np.zeros(shape, dtype=np.uint8)
        return g

    def paste(self, rows: slice, cols: slice, other: OccupancyGrid) -> None:
        """Replace cells [rows, cols] by `other` (made by `empty_like_region` for the same
        cells or a larger box), leaving its border out: rays entering
        a grid from outside are clipped there, so its edge cells are not exact."""
        r0, c0 = rows.start - other._origin_cell(self)[0], cols.start - other._origin_cell(self)[1]
        h, w = rows.stop - rows.start, cols.stop - cols.start
        self._log_odds[rows, cols] = other._log_odds[r0 : r0 + h, c0 : c0 + w]
        self._flags[rows, cols] = other._flags[r0 : r0 + h, c0 : c0 + w]

    def _origin_cell(self, parent: OccupancyGrid) -> tuple[int, int]:
        """(row, col) of this grid's cell (0, 0) in `parent`'s lattice."""
        d = (np.array(self._origin) - parent._origin) / self._resolution
        return int(round(d[1])), int(round(d[0]))

    def clear(self) -> None:
        """Forget everything (all cells back to unknown); the extent is kept."""
        self._log_odds.fill(0.0)
        self._flags.fill(0)

    def probability(self) -> NDArray[np.float32]:
        """(H, W) occupancy probabilities (0.5 where nothing is known)."""
        return (1.0 / (1.0 + np.exp(-self._log_odds))).astype(np.float32)

    def to_gridmap(self, occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> GridMap:
        """Trinary map: p > occupied_thresh -> 100, p < free_thresh -> 0, else -1.

        Cells never updated are -1 whatever the thresholds.
        """
        if not 0.0 < free_thresh < occupied_thresh < 1.0:
            raise ConfigError(
                "expected 0 < free_thresh < occupied_thresh < 1, "
                f"got {free_thresh}, {occupied_thresh}"
            )
        seen = self._flags != 0
        data = np.full(self._log_odds.shape, UNKNOWN, dtype=np.int8)
        data[seen & (self._log_odds > logodds(occupied_thresh))] = OCCUPIED
        data[seen & (self._log_odds < logodds(free_thresh))] = FREE
        return GridMap(data=data, resolution=self._resolution, origin=(*self._origin, 0.0))
