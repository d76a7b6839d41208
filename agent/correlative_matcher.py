"""Real-time correlative scan matching (Olson 2009; Cartographer's
`FastCorrelativeScanMatcher2D`): branch and bound over max-pooled probability
grids finds the best lattice pose (grid cells x angular steps) in a window around
the prediction, equal to an exhaustive search; the score is the mean cell
probability times Cartographer's real-time penalty exp(-(w_t |dt| + w_r |dyaw|)^2).
`RealTimeCorrelativeMatcher.covariance` is Olson's covariance of the correlative
likelihood over the window (see `agent.scan_matcher` for why it is the one used).

Instances cache the last grid pyramid and are not thread-safe: use one per thread.
"""

from __future__ import annotations

import logging
import math
import weakref
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from agent.branch_and_bound import branch_and_bound
from agent.probability_grid import ProbabilityGrid, cell_probability
from agent.voxel_filter import check_probability, finite_points
from common.errors import ConfigError
from common.geometry import wrap_angle

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@njit(cache=True)
def _discretize(pts, angles, tx, ty, ox, oy, res):
    """Grid cells (cx, cy), (A, N) int32, of the points rotated by each angle and moved
    by (tx, ty), and their bounding box [min x, min y, max x, max y]."""
    n_ang, n = angles.shape[0], pts.shape[0]
    cx = np.empty((n_ang, n), np.int32)
    cy = np.empty((n_ang, n), np.int32)
    inv = 1.0 / res
    u0 = (tx - ox) * inv
    v0 = (ty - oy) * inv
    px = np.empty(n)
    py = np.empty(n)
    for i in range(n):
        px[i] = pts[i, 0] * inv
        py[i] = pts[i, 1] * inv
    lo_x = lo_y = 2**31 - 1
    hi_x = hi_y = -(2**31)
    for a in range(n_ang):
        c = math.cos(angles[a])
        s = math.sin(angles[a])
        rx = cx[a]
        ry = cy[a]
        for i in range(n):
            rx[i] = np.int32(math.floor(c * px[i] - s * py[i] + u0))
            ry[i] = np.int32(math.floor(s * px[i] + c * py[i] + v0))
        for i in range(n):
            lo_x = min(lo_x, rx[i])
            hi_x = max(hi_x, rx[i])
            lo_y = min(lo_y, ry[i])
            hi_y = max(hi_y, ry[i])
    return cx, cy, np.array([lo_x, lo_y, hi_x, hi_y], np.int64)


@njit(cache=True)
def _flatten(cx, cy, x0, y0, w):
    """Row-major indices of the cells in a crop starting at grid cell (x0, y0)."""
    flat = np.empty(cx.shape, np.int32)
    for a in range(cx.shape[0]):
        for i in range(cx.shape[1]):
            flat[a, i] = (cy[a, i] - y0) * w + (cx[a, i] - x0)
    return flat


@njit(cache=True)
def _quantize(prob, gx0, gy0, gx1, gy1, p_unknown, dst, x0, y0, w):
    """dst[(y - y0) * w + x - x0] = round(255 * P(cell (x, y))) for the grid cells
    gx0 <= x < gx1, gy0 <= y < gy1."""
    n = gx1 - gx0
    for y in range(gy0, gy1):
        row = prob[y, gx0:gx1]
        r = (y - y0) * w + gx0 - x0
        out = dst[r : r + n]
        for x in range(n):
            out[x] = np.uint8(
                cell_probability(row[x], p_unknown) * np.float32(255.0) + np.float32(0.5)
            )


def _build_levels(
    grid: ProbabilityGrid, x0: int, y0: int, w: int, h: int, depth: int, p_unknown: float
) -> NDArray[np.uint8]:
    """Flat (depth + 1, h * w) uint8 pyramid: levels[k] at crop cell c is the max of the
    probabilities (x 255) over cells [c, c + 2^k)^2. Crop cell (0, 0) is grid cell
    (x0, y0); cells outside the grid read p_unknown. Pooling runs on the flat array, so
    the last 2^k - 1 columns and rows of level k wrap around: callers keep 2^depth
    cells of crop beyond their last lookup."""
    ny, nx = grid.shape
    levels = np.full((depth + 1, h * w), round(p_unknown * 255.0), dtype=np.uint8)
    gx0, gy0 = max(x0, 0), max(y0, 0)
    gx1, gy1 = min(x0 + w, nx), min(y0 + h, ny)
    if gx0 < gx1 and gy0 < gy1:
        _quantize(grid.data, gx0, gy0, gx1, gy1, np.float32(p_unknown), levels[0], x0, y0, w)
    tmp = np.empty(h * w, dtype=np.uint8)
    for k in range(1, depth + 1):
        s = 1 << (k - 1)
        np.maximum(levels[k - 1, :-s], levels[k - 1, s:], out=tmp[:-s])  # along x
        tmp[-s:] = levels[k - 1, -s:]
        sw = s * w
        np.maximum(tmp[:-sw], tmp[sw:], out=levels[k, :-sw])  # along y
        levels[k, -sw:] = tmp[-sw:]
    return levels


_LOG_LUT = np.log(np.maximum(np.arange(256), 0.5) / 255.0)  # log P of a uint8 cell value


@njit(cache=True)
def _olson_covariance(level0, flat, w, win, a0, dx0, dy0, offsets, res, step, lut):
    """Olson's covariance (see `RealTimeCorrelativeMatcher.covariance`) from the
    likelihoods exp(sum_i log P_i) of all translations of the window at angle index a0
    and of all angles at translation (dx0, dy0) (cells)."""
    n_ang, n = flat.shape
    side = 2 * win + 1
    ll = np.empty(side * side)
    for iy in range(side):
        for ix in range(side):
            off = (iy - win) * w + (ix - win)
            acc = 0.0
            for i in range(n):
                acc += lut[level0[flat[a0, i] + off]]
            ll[iy * side + ix] = acc
    top = ll.max()
    s = sx = sy = sxx = syy = sxy = 0.0
    for iy in range(side):
        for ix in range(side):
            p = math.exp(ll[iy * side + ix] - top)
            x = (ix - win) * res
            y = (iy - win) * res
            s += p
            sx += p * x
            sy += p * y
            sxx += p * x * x
            syy += p * y * y
            sxy += p * x * y
    mx = sx / s
    my = sy / s
    cov = np.zeros((3, 3))
    cov[0, 0] = sxx / s - mx * mx + res * res / 12.0
    cov[1, 1] = syy / s - my * my + res * res / 12.0
    cov[0, 1] = cov[1, 0] = sxy / s - mx * my
    off = dy0 * w + dx0
    la = np.empty(n_ang)
    for a in range(n_ang):
        acc = 0.0
        for i in range(n):
            acc += lut[level0[flat[a, i] + off]]
        la[a] = acc
    top = la.max()
    s = st = stt = 0.0
    for a in range(n_ang):
        p = math.exp(la[a] - top)
        s += p
        st += p * offsets[a]
        stt += p * offsets[a] * offsets[a]
    mt = st / s
    cov[2, 2] = stt / s - mt * mt + step * step / 12.0
    return cov


@dataclass(frozen=True)
class _Lattice:
    """A discretized scan over the search window: `flat[a, i]` indexes point i at angle
    offset `offsets[a]` (rad) in the crop pyramid `levels` (row width `width`)."""

    win: int  # translation half-window, cells
    depth: int  # pyramid levels above full resolution
    step: float  # angular step, rad
    offsets: FloatArray
    width: int
    levels: NDArray[np.uint8]
    flat: NDArray[np.int32]


@dataclass(frozen=True)
class CorrelativeResult:
    """Best lattice pose T_submap_sensor [x, y, yaw], its penalized score in [0, 1],
    and Olson's covariance over the search window (3x3, [x, y, yaw], m and rad)."""

    pose: FloatArray
    score: float
    covariance: FloatArray


class RealTimeCorrelativeMatcher:
    """Correlative search, exact on the lattice, by branch and bound (see module doc).

    `linear_window` (m) and `angular_window` (rad) are half-widths around the
    prediction. `angular_step` (rad) defaults to Cartographer's: the angle that moves
    the farthest point by one cell. `min_score`: no result at or below it.
    `translation_delta_cost_weight` (1/m), `rotation_delta_cost_weight` (1/rad):
    Cartographer's real-time penalty, a tie-breaker toward the prediction.
    `pyramid_margin_m`: the max-pooled pyramid is computed on a crop this much larger
    than needed. It is reused while the grid is unchanged (same `version`) and the
    crop still covers the scan.
    """

    def __init__(
        self,
        linear_window: float = 0.3,
        angular_window: float = math.radians(20.0),
        angular_step: float | None = None,
        min_score: float = 0.0,
        translation_delta_cost_weight: float = 0.1,
        rotation_delta_cost_weight: float = 0.1,
        pyramid_margin_m: float = 0.5,
        unknown_probability: float = 0.5,
    ) -> None:
        if not (linear_window >= 0.0 and angular_window >= 0.0):
            raise ConfigError("search windows must be >= 0")
        if angular_step is not None and not angular_step > 0.0:
            raise ConfigError(f"angular_step must be > 0 rad, got {angular_step}")
        self.linear_window = float(linear_window)
        self.angular_window = float(angular_window)
        self.angular_step = angular_step
        self.min_score = float(min_score)
        self.translation_delta_cost_weight = float(translation_delta_cost_weight)
        self.rotation_delta_cost_weight = float(rotation_delta_cost_weight)
        self.pyramid_margin_m = max(0.0, float(pyramid_margin_m))
        self.unknown_probability = check_probability(unknown_probability)
        # (weakref to grid, grid version, depth, x0, y0, w, h, levels)
        self._cache: tuple | None = None

    def match(
        self, grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
    ) -> CorrelativeResult | None:
        """Best T_submap_sensor near `predicted_pose`; None without points or when no
        candidate scores above `min_score`."""
        found = self._search(grid, points_sensor, predicted_pose)
        if found is None:
            return None
        lat, hits = found
        (pose, score, a, dx, dy) = hits[0]
        covariance = _olson_covariance(
            lat.levels[0],
            lat.flat,
            lat.width,
            lat.win,
            a,
            dx,
            dy,
            lat.offsets,
            grid.resolution,
            lat.step,
            _LOG_LUT,
        )
        return CorrelativeResult(pose=pose, score=score, covariance=covariance)

    def candidates(
        self,
        grid: ProbabilityGrid,
        points_sensor: ArrayLike,
        predicted_pose: ArrayLike,
        k: int,
        separation_m: float,
        separation_rad: float,
    ) -> list[tuple[FloatArray, float]]:
        """Up to k best lattice poses (pose, score), best first, exact like `match`:
        local optima more than `separation_m` or `separation_rad` apart (a better
        pose suppresses those closer to it)."""
        if k < 1:
            raise ConfigError(f"need k >= 1 candidates, got {k}")
        nms = (k, separation_m, separation_rad)
        found = self._search(grid, points_sensor, predicted_pose, nms)
        return [] if found is None else [(h[0], h[1]) for h in found[1]]

    def _search(
        self,
        grid: ProbabilityGrid,
        points_sensor: ArrayLike,
        predicted_pose: ArrayLike,
        nms: tuple[int, float, float] = (1, 0.0, 0.0),
    ) -> tuple[_Lattice, list[tuple[FloatArray, float, int, int, int]]] | None:
        """The lattice and its best poses (pose, score, angle index, dx, dy), for
        nms = (k, separation_m, separation_rad) as in `candidates`."""  # fmt: skip
        k, separation_m, separation_rad = nms
        pts = finite_points(points_sensor, "points_sensor")
        pred = np.asarray(predicted_pose, dtype=np.float64).reshape(3)
        if len(pts) == 0:
            return None
        lat = self._lattice(grid, pts, pred)
        res = grid.resolution
        n, best, best_s = branch_and_bound(
            lat.levels,
            lat.flat,
            lat.width,
            lat.win,
            lat.depth,
            self.rotation_delta_cost_weight * np.abs(lat.offsets),
            self.translation_delta_cost_weight * res,
            self.min_score,
            k,
            int(separation_m / res),
            int(separation_rad / lat.step),
        )
        if n == 0:
            return None
        hits = []
        for (a, dx, dy), score in zip(best[:n].tolist(), best_s[:n].tolist(), strict=True):
            yaw = float(wrap_angle(pred[2] + lat.offsets[a]))
            pose = np.array([pred[0] + dx * res, pred[1] + dy * res, yaw])
            hits.append((pose, float(score), a, dx, dy))
        return lat, hits

    def covariance(
        self, grid: ProbabilityGrid, points_sensor: ArrayLike, pose: ArrayLike
    ) -> FloatArray:
        """Olson's covariance (3x3, [x, y, yaw], m and rad) of a match at `pose`.

        Each pose x of the search lattice gets the likelihood exp(sum_i log P_i(x)),
        with the points taken as independent. The covariance is the second moment of
        those weights around their mean, plus the lattice quantization
        diag(res^2, res^2, step^2) / 12. It is evaluated on two slices of the window:
        all translations at the pose's yaw, and all angles at its translation; the
        cross terms between translation and yaw are 0. Where the scan does not
        constrain a direction (along a corridor), the weight spreads over the whole
        window; where it does, it sits on one cell. `match` computes the same around
        its best lattice pose; without points this is the window's uniform covariance.
        """
        pts = finite_points(points_sensor, "points_sensor")
        T = np.asarray(pose, dtype=np.float64).reshape(3)
        res = grid.resolution
        if len(pts) == 0:
            lw2, aw2 = self.linear_window**2, self.angular_window**2
            return np.diag([lw2 / 3 + res**2 / 12, lw2 / 3 + res**2 / 12, aw2 / 3])
        lat = self._lattice(grid, pts, T)
        a0 = len(lat.offsets) // 2
        return _olson_covariance(
            lat.levels[0],
            lat.flat,
            lat.width,
            lat.win,
            a0,
            0,
            0,
            lat.offsets,
            res,
            lat.step,
            _LOG_LUT,
        )

    def _lattice(self, grid: ProbabilityGrid, pts: FloatArray, pose: FloatArray) -> _Lattice:
        """The search lattice around `pose`: scan cells per angle and the pyramid."""
        res = grid.resolution
        win = int(math.ceil(self.linear_window / res - 1e-9))
        depth = int(math.ceil(math.log2(2 * win + 1)))
        step = self.angular_step
        if step is None:
            d_max = max(float(np.sqrt(np.einsum("ij,ij->i", pts, pts).max())), res)
            step = (1.0 - 1e-3) * math.acos(1.0 - res * res / (2.0 * d_max * d_max))
        n_ang = int(math.ceil(self.angular_window / step - 1e-9))
        offsets = np.arange(-n_ang, n_ang + 1) * step
        ox, oy = (float(v) for v in grid.origin_xy)
        cx, cy, box = _discretize(pts, pose[2] + offsets, pose[0], pose[1], ox, oy, res)
        pad = win + (1 << depth)
        x0, y0, w, levels = self._levels(
            grid,
            int(box[0]) - win,
            int(box[1]) - win,
            int(box[2]) + pad,
            int(box[3]) + pad,
            depth,
        )
        return _Lattice(win, depth, step, offsets, w, levels, _flatten(cx, cy, x0, y0, w))

    def _levels(
        self, grid: ProbabilityGrid, lx: int, ly: int, hx: int, hy: int, depth: int
    ) -> tuple[int, int, int, NDArray[np.uint8]]:
        """The pyramid covering grid cells [lx, hx) x [ly, hy), cached if it still fits."""
        c = self._cache
        if c is not None and c[0]() is grid and c[1] == grid.version and c[2] == depth:
            x0, y0, w, h, levels = c[3:]
            if x0 <= lx and y0 <= ly and hx <= x0 + w and hy <= y0 + h:
                return x0, y0, w, levels
        m = int(math.ceil(self.pyramid_margin_m / grid.resolution))
        x0, y0 = lx - m, ly - m
        w, h = hx + m - x0, hy + m - y0
        levels = _build_levels(grid, x0, y0, w, h, depth, self.unknown_probability)
        self._cache = (weakref.ref(grid), grid.version, depth, x0, y0, w, h, levels)
        return x0, y0, w, levels
