"""2-D scan-to-submap matching: correlative search, then least-squares refinement.

The agent's local SLAM front end, as Cartographer's
`LocalTrajectoryBuilder2D::ScanMatch` does it. All poses are T_submap_sensor
[x, y, yaw] (m, rad); points are (N, 2) in the sensor frame (m).

1. `adaptive_voxel_filter` thins a scan to a few hundred points.
2. `RealTimeCorrelativeMatcher` finds the best pose on the lattice (grid cells x
   angular steps) inside a window around the prediction. The result equals an
   exhaustive search, found by branch and bound over max-pooled grids (Olson 2009;
   Cartographer's `FastCorrelativeScanMatcher2D`). Score = mean cell probability of
   the points times Cartographer's real-time penalty exp(-(w_t |dt| + w_r |dyaw|)^2),
   so ties (a corridor) go to the candidate nearest the prediction.
3. `CeresLikeRefiner` moves the pose off the lattice: Levenberg-Marquardt with
   analytic Jacobians (numba) on the Catmull-Rom bicubic interpolation of the grid,
   cost = sum_i (w_occ / sqrt(N) * (1 - P(T p_i)))^2 + |w_t (t - t_prior)|^2
   + (w_r wrap(yaw - yaw_prior))^2 (Cartographer's `CeresScanMatcher2D`). As in
   Cartographer, `match` uses the predicted translation and the correlative yaw as
   the prior.

Unknown cells read as `unknown_probability`, 0.5 by default (Hector SLAM's choice).
Cartographer reads them as the grid's min probability (0.1). In a young submap that
makes free cells (0.49 after one scan) almost as good as walls (0.55) and much
better than the unknown space behind walls: in tests with a one-scan submap the
correlative result was off by up to 16 cm, against 3.5 cm with 0.5.

Covariance of a match (3x3, [x, y, yaw], submap frame): Olson's, from the
correlative likelihood exp(sum_i log P_i) over the search window, through the best
lattice pose (`RealTimeCorrelativeMatcher.covariance`). It is not taken from the
Gauss-Newton Hessian. The rasterized walls of a grid are stair-stepped, which gives
the cost strong local curvature along a featureless corridor: there the Hessian
covariance came out nearly isotropic (ratio 1-3), while the actual errors were
15-45 cm along the corridor and under 5 mm across it. The lattice likelihood is flat
along the corridor, so the covariance spreads over the window there.
`RefineResult.information` still carries J^T J for callers who want it.

`ScanMatcher` uses that covariance to keep the prediction in directions the scan
does not constrain (solution remapping, see its doc). Without remapping, the stair
texture would move the pose along a corridor by up to the window on every scan.

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

from agent.probability_grid import ProbabilityGrid
from common.errors import CollabSlamError, ConfigError
from common.geometry import wrap_angle

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


def _finite_points(points: ArrayLike, name: str = "points") -> FloatArray:
    p = np.asarray(points, dtype=np.float64)
    if p.size == 0:
        return np.zeros((0, 2))
    if p.ndim != 2 or p.shape[1] != 2:
        raise CollabSlamError(f"{name} must have shape (N, 2), got {p.shape}")
    finite = np.isfinite(p[:, 0] + p[:, 1])  # NaN and +-inf propagate through the sum
    return p if finite.all() else p[finite]


def _check_probability(p: float, name: str = "unknown_probability") -> float:
    if not 0.0 < p < 1.0:
        raise ConfigError(f"{name} must be in (0, 1), got {p}")
    return float(p)


# ----------------------------------------------------------------------------- filters


@njit(cache=True)
def _first_in_voxel(points, inv_size):
    """Mask of the first point (in input order) of each occupied voxel: an
    open-addressing hash set of the packed voxel keys."""
    n = points.shape[0]
    cap = 16
    while cap < 2 * n:
        cap *= 2
    keys = np.empty(cap, np.int64)
    used = np.zeros(cap, np.bool_)
    keep = np.zeros(n, np.bool_)
    for i in range(n):
        kx = np.int64(math.floor(points[i, 0] * inv_size))
        ky = np.int64(math.floor(points[i, 1] * inv_size))
        key = (kx << 32) ^ (ky & 0xFFFFFFFF)
        h = ((key * 0x9E3779B97F4A7C15) >> 17) & (cap - 1)
        while used[h] and keys[h] != key:
            h = (h + 1) & (cap - 1)
        if not used[h]:
            used[h] = True
            keys[h] = key
            keep[i] = True
    return keep


def voxel_filter(points: ArrayLike, voxel_size: float) -> FloatArray:
    """Keep the first point (in input order) of every occupied square voxel (m);
    non-finite points are dropped."""
    p = _finite_points(points)
    return p[_first_in_voxel(p, 1.0 / voxel_size)] if len(p) else p


def adaptive_voxel_filter(
    points: ArrayLike,
    max_length: float = 0.5,
    min_num_points: int = 200,
    max_range: float = 50.0,
) -> FloatArray:
    """Cartographer's `AdaptiveVoxelFilter` on (N, 2) sensor-frame points (m).

    Drops non-finite points and points beyond `max_range`. Then it uses the largest
    voxel size <= `max_length` that keeps at least `min_num_points`: it halves the
    size, then binary-searches to within 10 %. If even max_length / 100 keeps too
    few, all points are returned.
    """
    p = _finite_points(points)
    p = p[np.einsum("ij,ij->i", p, p) <= max_range * max_range]
    if len(p) <= min_num_points:
        return p
    return p[_adaptive_voxel_mask(p, max_length, min_num_points)]


@njit(cache=True)
def _adaptive_voxel_mask(p, max_length, min_num_points):
    """Cartographer's search, as one loop so that _first_in_voxel has one call site
    (every inlined copy adds compile time): halve the voxel size until enough points
    remain, then bisect between the dense (low) and sparse (high) sizes to 10 %."""
    size = high = max_length
    low = 0.0  # largest size known to keep enough points (0: none yet)
    best = np.ones(p.shape[0], np.bool_)  # if no size is dense enough: every point
    while True:
        keep = _first_in_voxel(p, 1.0 / size)
        if keep.sum() >= min_num_points:
            if size == max_length:
                return keep
            low, best = size, keep
        else:
            high = size
        if low == 0.0:
            if high <= 1e-2 * max_length:
                return best
            size = 0.5 * high
        elif high / low <= 1.1:
            return best
        else:
            size = 0.5 * (low + high)


# ------------------------------------------------------------ correlative (numba kernels)


@njit(cache=True, inline="always")
def _p(v, p_unknown):
    """A stored cell value as a probability: 0 (never observed) reads `p_unknown`."""
    return v if v > 0.0 else p_unknown


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
            out[x] = np.uint8(_p(row[x], p_unknown) * np.float32(255.0) + np.float32(0.5))


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


@njit(cache=True)
def _node_score(level, flat, a, off, n):
    acc = 0
    for i in range(n):
        acc += level[flat[a, i] + off]
    return acc / (255.0 * n)


@njit(cache=True)
def _bound(levels, flat, a, dx, dy, k, w, win, ang_cost, lin_coef):
    """Upper bound of the penalized score over the node: angle a, offsets
    [dx, dx + 2^k) x [dy, dy + 2^k) clipped to the window (exact when k == 0)."""
    near = 0.0
    for d in (dx, dy):
        hi = min(d + (1 << k) - 1, win)
        if not d <= 0 <= hi:
            m = min(abs(d), abs(hi))
            near += m * m
    f = ang_cost[a] + lin_coef * math.sqrt(near)
    return math.exp(-f * f) * _node_score(levels[k], flat, a, dy * w + dx, flat.shape[1])


@njit(cache=True)
def _argsort(x):
    """Indices sorting x ascending (Shell sort: np.argsort costs seconds of compile)."""
    n = x.shape[0]
    idx = np.arange(n)
    gap = n // 2
    while gap > 0:
        for i in range(gap, n):
            j, k = i, idx[i]
            while j >= gap and x[idx[j - gap]] > x[k]:
                idx[j] = idx[j - gap]
                j -= gap
            idx[j] = k
        gap //= 2
    return idx


@njit(cache=True)
def _branch_and_bound(levels, flat, w, win, depth, ang_cost, lin_coef, min_score):
    """Best (angle index, dx, dy, score) with score > min_score (angle index -1: none).
    Depth-first, best child first, pruning nodes whose bound <= the best leaf so far."""
    n_ang = flat.shape[0]
    step = 1 << depth
    per_axis = (2 * win) // step + 1
    n_root = n_ang * per_axis * per_axis
    root = np.empty((n_root, 3), np.int64)
    root_s = np.empty(n_root)
    r = 0
    for a in range(n_ang):
        for ix in range(per_axis):
            for iy in range(per_axis):
                dx, dy = -win + ix * step, -win + iy * step
                root[r, 0], root[r, 1], root[r, 2] = a, dx, dy
                root_s[r] = _bound(levels, flat, a, dx, dy, depth, w, win, ang_cost, lin_coef)
                r += 1
    cap = n_root + 4 * (depth + 1)
    st = np.empty((cap, 4), np.int64)  # angle, dx, dy, depth
    st_s = np.empty(cap)
    order = _argsort(root_s)  # ascending: the best root is popped first
    for j in range(n_root):
        q = order[j]
        st[j, 0], st[j, 1], st[j, 2], st[j, 3] = root[q, 0], root[q, 1], root[q, 2], depth
        st_s[j] = root_s[q]
    sp = n_root
    best_a, best_x, best_y, best_s = -1, 0, 0, min_score
    ch = np.empty((4, 2), np.int64)
    ch_s = np.empty(4)
    while sp > 0:
        sp -= 1
        a, dx, dy, k = st[sp, 0], st[sp, 1], st[sp, 2], st[sp, 3]
        if st_s[sp] <= best_s:
            continue
        if k == 0:
            best_a, best_x, best_y, best_s = a, dx, dy, st_s[sp]
            continue
        half = 1 << (k - 1)
        m = 0
        for cx in (dx, dx + half):
            for cy in (dy, dy + half):
                if cx > win or cy > win:
                    continue
                s = _bound(levels, flat, a, cx, cy, k - 1, w, win, ang_cost, lin_coef)
                j = m  # insertion sort, ascending
                while j > 0 and ch_s[j - 1] > s:
                    ch[j, 0], ch[j, 1], ch_s[j] = ch[j - 1, 0], ch[j - 1, 1], ch_s[j - 1]
                    j -= 1
                ch[j, 0], ch[j, 1], ch_s[j] = cx, cy, s
                m += 1
        for j in range(m):
            if ch_s[j] > best_s:
                st[sp, 0], st[sp, 1], st[sp, 2], st[sp, 3] = a, ch[j, 0], ch[j, 1], k - 1
                st_s[sp] = ch_s[j]
                sp += 1
    return best_a, best_x, best_y, best_s


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
        self.unknown_probability = _check_probability(unknown_probability)
        # (weakref to grid, grid version, depth, x0, y0, w, h, levels)
        self._cache: tuple | None = None

    def match(
        self, grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
    ) -> CorrelativeResult | None:
        """Best T_submap_sensor near `predicted_pose`; None without points or when no
        candidate scores above `min_score`."""
        pts = _finite_points(points_sensor, "points_sensor")
        pred = np.asarray(predicted_pose, dtype=np.float64).reshape(3)
        if len(pts) == 0:
            return None
        lat = self._lattice(grid, pts, pred)
        a, dx, dy, score = _branch_and_bound(
            lat.levels,
            lat.flat,
            lat.width,
            lat.win,
            lat.depth,
            self.rotation_delta_cost_weight * np.abs(lat.offsets),
            self.translation_delta_cost_weight * grid.resolution,
            self.min_score,
        )
        if a < 0:
            return None
        res = grid.resolution
        yaw = float(wrap_angle(pred[2] + lat.offsets[a]))
        pose = np.array([pred[0] + dx * res, pred[1] + dy * res, yaw])
        covariance = _olson_covariance(
            lat.levels[0],
            lat.flat,
            lat.width,
            lat.win,
            a,
            dx,
            dy,
            lat.offsets,
            res,
            lat.step,
            _LOG_LUT,
        )
        return CorrelativeResult(pose=pose, score=float(score), covariance=covariance)

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
        pts = _finite_points(points_sensor, "points_sensor")
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


# ---------------------------------------------------------------- refinement (numba kernels)


@njit(cache=True)
def _bicubic(g, p_unknown, u, v):
    """Catmull-Rom interpolation of the probabilities g (unknown or outside: p_unknown)
    at (u, v) in cell-centre units (u = 0: centre of column 0). Value, d/du, d/dv."""
    ny, nx = g.shape
    fu = math.floor(u)
    fv = math.floor(v)
    x = int(fu) - 1
    y = int(fv) - 1
    t = u - fu
    t2 = t * t
    t3 = t2 * t
    wu0 = 0.5 * (-t3 + 2.0 * t2 - t)
    wu1 = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0)
    wu2 = 0.5 * (-3.0 * t3 + 4.0 * t2 + t)
    wu3 = 0.5 * (t3 - t2)
    du0 = 0.5 * (-3.0 * t2 + 4.0 * t - 1.0)
    du1 = 0.5 * (9.0 * t2 - 10.0 * t)
    du2 = 0.5 * (-9.0 * t2 + 8.0 * t + 1.0)
    du3 = 0.5 * (3.0 * t2 - 2.0 * t)
    t = v - fv
    t2 = t * t
    t3 = t2 * t
    inside = x >= 0 and y >= 0 and x + 3 < nx and y + 3 < ny
    val = 0.0
    gu = 0.0
    gv = 0.0
    for j in range(4):
        if j == 0:
            wv, dv = 0.5 * (-t3 + 2.0 * t2 - t), 0.5 * (-3.0 * t2 + 4.0 * t - 1.0)
        elif j == 1:
            wv, dv = 0.5 * (3.0 * t3 - 5.0 * t2 + 2.0), 0.5 * (9.0 * t2 - 10.0 * t)
        elif j == 2:
            wv, dv = 0.5 * (-3.0 * t3 + 4.0 * t2 + t), 0.5 * (-9.0 * t2 + 8.0 * t + 1.0)
        else:
            wv, dv = 0.5 * (t3 - t2), 0.5 * (3.0 * t2 - 2.0 * t)
        yy = y + j
        if inside:
            c0 = _p(g[yy, x], p_unknown)
            c1 = _p(g[yy, x + 1], p_unknown)
            c2 = _p(g[yy, x + 2], p_unknown)
            c3 = _p(g[yy, x + 3], p_unknown)
        elif 0 <= yy < ny:
            c0 = _p(g[yy, x], p_unknown) if 0 <= x < nx else p_unknown
            c1 = _p(g[yy, x + 1], p_unknown) if 0 <= x + 1 < nx else p_unknown
            c2 = _p(g[yy, x + 2], p_unknown) if 0 <= x + 2 < nx else p_unknown
            c3 = _p(g[yy, x + 3], p_unknown) if 0 <= x + 3 < nx else p_unknown
        else:
            c0 = c1 = c2 = c3 = p_unknown
        r = wu0 * c0 + wu1 * c1 + wu2 * c2 + wu3 * c3
        e = du0 * c0 + du1 * c1 + du2 * c2 + du3 * c3
        val += wv * r
        gu += wv * e
        gv += dv * r
    return val, gu, gv


@njit(cache=True)
def _normal_equations(g, p_unknown, ox, oy, res, pts, pose, prior, s_occ, w_t, w_r, H, b):
    """Cost 0.5 * sum r^2 at `pose`; fills H = J^T J and b = J^T r (3x3 and 3).
    With s_occ = 1 and w_t = w_r = 0 these are the bare occupancy terms."""
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    h00 = h01 = h02 = h11 = h12 = h22 = b0 = b1 = b2 = cost = 0.0
    for i in range(pts.shape[0]):
        rx = c * pts[i, 0] - s * pts[i, 1]
        ry = s * pts[i, 0] + c * pts[i, 1]
        u = (pose[0] + rx - ox) / res - 0.5
        v = (pose[1] + ry - oy) / res - 0.5
        p, pu, pv = _bicubic(g, p_unknown, u, v)
        r = s_occ * (1.0 - p)
        j0 = -s_occ * pu / res
        j1 = -s_occ * pv / res
        j2 = -j0 * ry + j1 * rx
        cost += r * r
        b0 += j0 * r
        b1 += j1 * r
        b2 += j2 * r
        h00 += j0 * j0
        h01 += j0 * j1
        h02 += j0 * j2
        h11 += j1 * j1
        h12 += j1 * j2
        h22 += j2 * j2
    r0 = w_t * (pose[0] - prior[0])
    r1 = w_t * (pose[1] - prior[1])
    d = pose[2] - prior[2]
    r2 = w_r * (d - 2.0 * math.pi * math.floor((d + math.pi) / (2.0 * math.pi)))
    cost += r0 * r0 + r1 * r1 + r2 * r2
    b[0], b[1], b[2] = b0 + w_t * r0, b1 + w_t * r1, b2 + w_r * r2
    H[0, 0], H[1, 1], H[2, 2] = h00 + w_t * w_t, h11 + w_t * w_t, h22 + w_r * w_r
    H[0, 1] = H[1, 0] = h01
    H[0, 2] = H[2, 0] = h02
    H[1, 2] = H[2, 1] = h12
    return 0.5 * cost


@njit(cache=True)
def _solve3(A, y):
    """x with A x = y, A symmetric positive definite 3x3 (Cholesky)."""
    l00 = math.sqrt(max(A[0, 0], 1e-300))
    l10 = A[1, 0] / l00
    l20 = A[2, 0] / l00
    l11 = math.sqrt(max(A[1, 1] - l10 * l10, 1e-300))
    l21 = (A[2, 1] - l20 * l10) / l11
    l22 = math.sqrt(max(A[2, 2] - l20 * l20 - l21 * l21, 1e-300))
    z0 = y[0] / l00
    z1 = (y[1] - l10 * z0) / l11
    z2 = (y[2] - l20 * z0 - l21 * z1) / l22
    x = np.empty(3)
    x[2] = z2 / l22
    x[1] = (z1 - l21 * x[2]) / l11
    x[0] = (z0 - l10 * x[1] - l20 * x[2]) / l00
    return x


@njit(cache=True)
def _levenberg_marquardt(
    g,
    p_unknown,
    ox,
    oy,
    res,
    pts,
    pose0,
    prior,
    s_occ,
    w_t,
    w_r,
    max_iterations,
    step_tol_m,
    step_tol_rad,
    cost_tol,
    damping0,
):
    """Minimize the refinement cost from pose0: (pose, cost, iterations, converged).
    Converged: a step below the tolerances, or a relative cost decrease below cost_tol.
    (Explicit loops, not slice assignments or array expressions, and one call site
    of _normal_equations: both cut numba's compile time several-fold.)"""
    H = np.empty((3, 3))
    b = np.empty(3)
    Hn = np.empty((3, 3))
    bn = np.empty(3)
    A = np.empty((3, 3))
    minus_b = np.empty(3)
    pose = pose0.copy()
    cand = pose0.copy()
    cost = math.inf  # not evaluated yet
    lam = damping0  # relative to diag(H); updated by Nielsen's gain-ratio rule
    nu = 2.0
    converged = False
    small = False
    predicted = 0.0
    it = 0
    while True:
        new_cost = _normal_equations(
            g, p_unknown, ox, oy, res, pts, cand, prior, s_occ, w_t, w_r, Hn, bn
        )
        decrease = cost - new_cost
        if cost == math.inf or (decrease >= 0.0 and predicted > 0.0):
            if cost != math.inf:
                rho = decrease / predicted
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                if small or decrease <= cost_tol * new_cost:
                    converged = True
            for i in range(3):
                pose[i] = cand[i]
                b[i] = bn[i]
                for j in range(3):
                    H[i, j] = Hn[i, j]
            cost = new_cost
        elif small:
            converged = True
        else:
            lam *= nu
            nu *= 2.0
        if converged or it >= max_iterations or lam > 1e8:
            break
        it += 1
        for i in range(3):
            for j in range(3):
                A[i, j] = H[i, j]
            A[i, i] += lam * H[i, i] + 1e-12
            minus_b[i] = -b[i]
        delta = _solve3(A, minus_b)
        small = (
            abs(delta[0]) < step_tol_m
            and abs(delta[1]) < step_tol_m
            and abs(delta[2]) < step_tol_rad
        )
        # decrease predicted by the damped model: -(delta.b + 0.5 delta.H.delta)
        predicted = 0.0
        for i in range(3):
            predicted -= delta[i] * b[i]
            for j in range(3):
                predicted -= 0.5 * delta[i] * H[i, j] * delta[j]
        for i in range(3):
            cand[i] = pose[i] + delta[i]
    return pose, cost, it, converged


@njit(cache=True)
def _mean_cell_probability(g, p_unknown, ox, oy, res, pts, pose):
    """Mean probability of the cells the points fall in (unknown or outside: p_unknown)."""
    ny, nx = g.shape
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    acc = 0.0
    for i in range(pts.shape[0]):
        x = int(math.floor((pose[0] + c * pts[i, 0] - s * pts[i, 1] - ox) / res))
        y = int(math.floor((pose[1] + s * pts[i, 0] + c * pts[i, 1] - oy) / res))
        acc += _p(g[y, x], p_unknown) if 0 <= x < nx and 0 <= y < ny else p_unknown
    return acc / max(pts.shape[0], 1)


@dataclass(frozen=True)
class RefineResult:
    """Refined T_submap_sensor, with the Gauss-Newton statistics at the solution.

    `information`: J^T J of the bare occupancy residuals 1 - P(T p_i) (3x3,
    [x, y, yaw]); `residual_variance`: sum (1 - P_i)^2 / max(N - 3, 1). Their
    sigma^2 (J^T J)^-1 is the textbook covariance; `MatchResult` does not use it (see
    the module doc).
    `cost`: the weighted cost (0.5 sum r^2) at the solution.
    """

    pose: FloatArray
    cost: float
    iterations: int
    converged: bool
    information: FloatArray
    residual_variance: float


class CeresLikeRefiner:
    """Levenberg-Marquardt refinement on the bicubic grid (cost in the module doc).

    The weights are Cartographer's `occupied_space_weight` (residuals scaled by
    1/sqrt(N)), `translation_weight` (1/m) and `rotation_weight` (1/rad). The
    defaults keep the prior a weak regularizer, so that an offset prediction does not
    bias the result. Cartographer's local defaults (10, 40) trust a good IMU
    prediction: with them a 0.3 m prediction error pulls the result by centimetres.

    LM stops after `max_iterations` or when a step is below `step_tolerance_m` and
    `step_tolerance_rad`, or the relative cost decrease is below `cost_tolerance`.
    `initial_damping` is relative to diag(J^T J). Gauss-Newton underestimates the
    curvature of this cost, because its residuals are not small, so LM starts damped:
    it then needs 5-11 iterations, against 9-20 from 1e-4.
    """

    def __init__(
        self,
        occupied_space_weight: float = 1.0,
        translation_weight: float = 0.1,
        rotation_weight: float = 0.1,
        max_iterations: int = 20,
        step_tolerance_m: float = 1e-4,
        step_tolerance_rad: float = 1e-4,
        cost_tolerance: float = 1e-6,
        initial_damping: float = 10.0,
        unknown_probability: float = 0.5,
    ) -> None:
        if occupied_space_weight <= 0.0 or translation_weight < 0.0 or rotation_weight < 0.0:
            raise ConfigError("refiner weights must be >= 0 (occupied_space_weight > 0)")
        if max_iterations < 1:
            raise ConfigError(f"max_iterations must be >= 1, got {max_iterations}")
        self.occupied_space_weight = float(occupied_space_weight)
        self.translation_weight = float(translation_weight)
        self.rotation_weight = float(rotation_weight)
        self.max_iterations = int(max_iterations)
        self.step_tolerance_m = float(step_tolerance_m)
        self.step_tolerance_rad = float(step_tolerance_rad)
        self.cost_tolerance = float(cost_tolerance)
        self.initial_damping = float(initial_damping)
        self.unknown_probability = _check_probability(unknown_probability)

    def refine(
        self,
        grid: ProbabilityGrid,
        points_sensor: ArrayLike,
        initial_pose: ArrayLike,
        prior_pose: ArrayLike | None = None,
    ) -> RefineResult:
        """Refine T_submap_sensor from `initial_pose`, regularized toward `prior_pose`
        (default: `initial_pose`). Raises CollabSlamError with < 3 finite points."""
        pts = _finite_points(points_sensor, "points_sensor")
        if len(pts) < 3:
            raise CollabSlamError(f"refinement needs >= 3 finite points, got {len(pts)}")
        pose0 = np.asarray(initial_pose, dtype=np.float64).reshape(3).copy()
        prior = pose0 if prior_pose is None else np.asarray(prior_pose, np.float64).reshape(3)
        g, p_unknown = grid.data, self.unknown_probability
        ox, oy = (float(v) for v in grid.origin_xy)
        res, n = grid.resolution, len(pts)
        pose, cost, iterations, converged = _levenberg_marquardt(
            g,
            p_unknown,
            ox,
            oy,
            res,
            pts,
            pose0,
            prior,
            self.occupied_space_weight / math.sqrt(n),
            self.translation_weight,
            self.rotation_weight,
            self.max_iterations,
            self.step_tolerance_m,
            self.step_tolerance_rad,
            self.cost_tolerance,
            self.initial_damping,
        )
        info = np.empty((3, 3))
        half_ss = _normal_equations(
            g, p_unknown, ox, oy, res, pts, pose, pose, 1.0, 0.0, 0.0, info, np.empty(3)
        )
        pose[2] = float(wrap_angle(pose[2]))
        return RefineResult(
            pose=pose,
            cost=float(cost),
            iterations=int(iterations),
            converged=bool(converged),
            information=info,
            residual_variance=2.0 * half_ss / max(n - 3, 1),
        )


def refine(
    grid: ProbabilityGrid,
    points_sensor: ArrayLike,
    initial_pose: ArrayLike,
    prior_pose: ArrayLike | None = None,
    refiner: CeresLikeRefiner | None = None,
) -> RefineResult:
    """`CeresLikeRefiner.refine`, with the default weights unless `refiner` is given."""
    return (refiner or CeresLikeRefiner()).refine(grid, points_sensor, initial_pose, prior_pose)


# ------------------------------------------------------------------------------- matching


@dataclass(frozen=True)
class MatchResult:
    """The outcome of `ScanMatcher.match`.

    `pose`: T_submap_sensor [x, y, yaw] (m, rad). `score`: mean probability of the
    cells the points fall in, unknown cells counted as the grid's min_probability.
    `covariance`: 3x3 over [x, y, yaw] (see module doc). `iterations`: LM iterations.
    `converged` is False when the scan had too few finite points (pose = prediction,
    covariance = the prior's), when the correlative search found no candidate above
    its min_score, or when LM did not converge; `pose` is then the best estimate
    available. `correlative_score`: NaN when the search was off or found nothing.
    """

    pose: FloatArray
    score: float
    covariance: FloatArray
    iterations: int
    converged: bool
    correlative_score: float = math.nan


class ScanMatcher:
    """Correlative search (optional), then refinement, with Olson's covariance.

    Degenerate directions are handled by solution remapping (Zhang, Kaess and Singh,
    ICRA 2016). A translation eigen-direction of the covariance whose standard
    deviation exceeds `unconstrained_sigma_xy` (m; default a third of the linear
    window) is taken from the prediction, not the match. The same holds for yaw
    against `unconstrained_sigma_yaw` (rad; default a third of the angular window).
    Otherwise the lattice's texture (stair-stepped walls, sparse far hits) would move
    the pose along a featureless corridor by up to the window on every scan. Pass
    math.inf to turn remapping off. The covariance comes from the correlative matcher
    even when `use_correlative` is off. A scan with fewer than `min_num_points`
    finite points is not matched.
    """

    def __init__(
        self,
        correlative: RealTimeCorrelativeMatcher | None = None,
        refiner: CeresLikeRefiner | None = None,
        use_correlative: bool = True,
        min_num_points: int = 3,
        unconstrained_sigma_xy: float | None = None,
        unconstrained_sigma_yaw: float | None = None,
    ) -> None:
        self.correlative = correlative or RealTimeCorrelativeMatcher()
        self.refiner = refiner or CeresLikeRefiner()
        self.use_correlative = bool(use_correlative)
        self.min_num_points = max(3, int(min_num_points))
        self.unconstrained_sigma_xy = (
            self.correlative.linear_window / 3.0
            if unconstrained_sigma_xy is None
            else float(unconstrained_sigma_xy)
        )
        self.unconstrained_sigma_yaw = (
            self.correlative.angular_window / 3.0
            if unconstrained_sigma_yaw is None
            else float(unconstrained_sigma_yaw)
        )

    def match(
        self, grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
    ) -> MatchResult:
        """Match (N, 2) sensor-frame points against `grid` near `predicted_pose`
        (T_submap_sensor). Raises CollabSlamError for a grid without scans, a bad
        shape or a non-finite prediction. An empty or all-NaN scan does not raise: it
        gives `converged=False` at the prediction."""
        if grid.num_scans == 0:
            raise CollabSlamError("cannot match against an empty probability grid")
        pred = np.asarray(predicted_pose, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(pred)):
            raise CollabSlamError(f"predicted pose must be finite, got {pred}")
        pts = _finite_points(points_sensor, "points_sensor")
        if len(pts) < self.min_num_points:
            logger.warning(
                "scan has %d finite points (< %d): not matched", len(pts), self.min_num_points
            )
            covariance = self.correlative.covariance(grid, pts[:0], pred)
            return MatchResult(pred.copy(), 0.0, covariance, 0, False)
        initial, corr_score, found, covariance = pred, math.nan, True, None
        if self.use_correlative:
            corr = self.correlative.match(grid, pts, pred)
            if corr is None:
                found = False
                logger.debug("correlative search found no candidate above min_score")
            else:
                covariance, corr_score = corr.covariance, corr.score
                initial = self._remap(corr.pose, pred, covariance)
        # Cartographer's prior: the predicted translation and the initial yaw.
        prior = np.array([pred[0], pred[1], initial[2]])
        ref = self.refiner.refine(grid, pts, initial, prior)
        if covariance is None:
            covariance = self.correlative.covariance(grid, pts, ref.pose)
        pose = self._remap(ref.pose, pred, covariance)
        ox, oy = (float(v) for v in grid.origin_xy)
        score = _mean_cell_probability(
            grid.data, grid.min_probability, ox, oy, grid.resolution, pts, pose
        )
        return MatchResult(
            pose, float(score), covariance, ref.iterations, ref.converged and found, corr_score
        )

    def _remap(self, pose: FloatArray, pred: FloatArray, covariance: FloatArray) -> FloatArray:
        """`pose` in the constrained directions of `covariance`, `pred` in the others."""
        out = pose.copy()
        limit = self.unconstrained_sigma_xy**2
        a, b, c = covariance[0, 0], covariance[0, 1], covariance[1, 1]
        half_gap = math.hypot(0.5 * (a - c), b)
        big, small = 0.5 * (a + c) + half_gap, 0.5 * (a + c) - half_gap  # eigenvalues
        if small > limit:  # nothing constrains the translation
            out[:2] = pred[:2]
        elif big > limit:  # one loose direction: the eigenvector of `big`
            v = np.array([big - c, b]) if abs(big - c) >= abs(big - a) else np.array([b, big - a])
            v /= np.linalg.norm(v)
            out[:2] -= v * (v @ (pose[:2] - pred[:2]))
        if covariance[2, 2] > self.unconstrained_sigma_yaw**2:
            out[2] = pred[2]
        return out


_default_matcher: ScanMatcher | None = None


def match(
    grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
) -> MatchResult:
    """`ScanMatcher.match` with the default parameters (one shared, cached instance)."""
    global _default_matcher
    if _default_matcher is None:
        _default_matcher = ScanMatcher()
    return _default_matcher.match(grid, points_sensor, predicted_pose)
