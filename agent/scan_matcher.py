"""2-D scan-to-submap matching: correlative search, then least-squares refinement.

The local SLAM front end of the agent, as Cartographer's
`LocalTrajectoryBuilder2D::ScanMatch` does it:

1. `adaptive_voxel_filter` thins a scan to a few hundred points.
2. `RealTimeCorrelativeMatcher` finds the best pose on the lattice (grid cells x
   angular steps) inside a window around the prediction, exactly, by branch and
   bound over max-pooled grids (Olson 2009; Cartographer's
   `FastCorrelativeScanMatcher2D`). Score = mean cell probability of the points,
   times Cartographer's real-time penalty exp(-(w_t |dt| + w_r |dyaw|)^2) so that
   ties (a corridor) go to the candidate nearest the prediction.
3. `CeresLikeRefiner` polishes the pose off the lattice: Levenberg-Marquardt with
   analytic Jacobians (numba) on the bicubic (Catmull-Rom) interpolation of the
   grid, cost = sum_i (w_occ / sqrt(N) * (1 - P(T p_i)))^2
   + |w_t (t - t_prior)|^2 + (w_r wrap(yaw - yaw_prior))^2
   (Cartographer's `CeresScanMatcher2D`; its prior is the predicted translation and
   the correlative yaw, as here).

Covariance of a match (3x3, [x, y, yaw], m and rad, submap frame): Gauss-Newton
information of the occupancy residuals at the solution, J^T J / sigma^2 with
sigma^2 = sum_i (1 - P_i)^2 / (N - 3) the residual variance, plus a prior
information diag(1/s_xy^2, 1/s_xy^2, 1/s_yaw^2) with s_xy, s_yaw the search window:
cov = (J^T J / sigma^2 + prior)^-1. A direction the scan does not constrain (along
a corridor) thus reads as window-sized uncertainty, a constrained one as the
least-squares uncertainty. Like every grid-matching covariance it treats points as
independent and is optimistic in the constrained directions.

Grids are `ProbabilityGrid`s; unknown cells read as their `min_probability`.
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


# ----------------------------------------------------------------------------- filters


def _finite_points(points: ArrayLike, name: str = "points") -> FloatArray:
    p = np.asarray(points, dtype=np.float64)
    if p.size == 0:
        return np.zeros((0, 2))
    if p.ndim != 2 or p.shape[1] != 2:
        raise CollabSlamError(f"{name} must have shape (N, 2), got {p.shape}")
    return p[np.isfinite(p).all(axis=1)]


def voxel_filter(points: ArrayLike, voxel_size: float) -> FloatArray:
    """Keep the first point (in input order) of every occupied square voxel (m)."""
    p = _finite_points(points)
    if len(p) == 0:
        return p
    keys = np.floor(p / voxel_size).astype(np.int64)
    packed = (keys[:, 0] << 32) ^ (keys[:, 1] & 0xFFFFFFFF)
    _, first = np.unique(packed, return_index=True)
    return p[np.sort(first)]


def adaptive_voxel_filter(
    points: ArrayLike,
    max_length: float = 0.5,
    min_num_points: int = 200,
    max_range: float = 50.0,
) -> FloatArray:
    """Cartographer's `AdaptiveVoxelFilter` on (N, 2) sensor-frame points (m).

    Drops non-finite points and points beyond `max_range`, then uses the largest
    voxel size <= `max_length` that keeps at least `min_num_points` (halving, then a
    binary search to within 10 %); returns all points when even max_length / 100
    is not enough.
    """
    p = _finite_points(points)
    p = p[np.einsum("ij,ij->i", p, p) <= max_range * max_range]
    if len(p) <= min_num_points:
        return p
    result = voxel_filter(p, max_length)
    if len(result) >= min_num_points:
        return result
    high = max_length
    while high > 1e-2 * max_length:
        low = 0.5 * high
        result = voxel_filter(p, low)
        if len(result) >= min_num_points:
            while high / low > 1.1:
                mid = 0.5 * (low + high)
                candidate = voxel_filter(p, mid)
                if len(candidate) >= min_num_points:
                    low, result = mid, candidate
                else:
                    high = mid
            return result
        high = low
    return p


# ------------------------------------------------------------ correlative (numba kernels)


@njit(cache=True)
def _discretize(pts, angles, tx, ty, ox, oy, res, cx, cy):  # type: ignore[no-untyped-def]
    """Cells (cx, cy) (A, N) of the points rotated by each angle and moved by (tx, ty)."""
    for a in range(angles.shape[0]):
        c = math.cos(angles[a])
        s = math.sin(angles[a])
        for i in range(pts.shape[0]):
            x = c * pts[i, 0] - s * pts[i, 1] + tx
            y = s * pts[i, 0] + c * pts[i, 1] + ty
            cx[a, i] = int(math.floor((x - ox) / res))
            cy[a, i] = int(math.floor((y - oy) / res))


@njit(cache=True, inline="always")
def _p(v, p_unknown):  # type: ignore[no-untyped-def]
    """A stored cell value as a probability: 0 (never observed) reads `p_unknown`."""
    return v if v > 0.0 else p_unknown


@njit(cache=True)
def _quantize(prob, gx0, gy0, gx1, gy1, p_unknown, dst, x0, y0, w):  # type: ignore[no-untyped-def]
    """dst[(y - y0) * w + x - x0] = round(max(prob[y, x], p_unknown) * 255) as uint8 for the
    grid cells gx0 <= x < gx1, gy0 <= y < gy1."""
    for y in range(gy0, gy1):
        row = prob[y]
        r = (y - y0) * w - x0
        for x in range(gx0, gx1):
            dst[r + x] = np.uint8(_p(row[x], p_unknown) * np.float32(255.0) + np.float32(0.5))


def _build_levels(
    grid: ProbabilityGrid, x0: int, y0: int, w: int, h: int, depth: int, p_unknown: float
) -> NDArray[np.uint8]:
    """Flat (depth + 1, h * w) uint8 pyramid: levels[k] at crop cell c is the max of the
    probabilities (* 255) over cells [c, c + 2^k)^2. Crop cell (0, 0) is grid cell
    (x0, y0); cells outside the grid read p_unknown. Rows are max-pooled on the flat array,
    so the last 2^k - 1 columns and rows of level k wrap around: callers keep 2^depth
    cells of crop beyond their last lookup."""
    ny, nx = grid.shape
    levels = np.full((depth + 1, h * w), round(p_unknown * 255.0), dtype=np.uint8)
    gx0, gy0 = max(x0, 0), max(y0, 0)
    gx1, gy1 = min(x0 + w, nx), min(y0 + h, ny)
    if gx0 < gx1 and gy0 < gy1:
        p_unk = np.float32(p_unknown)
        _quantize(grid.data, gx0, gy0, gx1, gy1, p_unk, levels[0], x0, y0, w)
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
def _node_score(level, flat, a, off, n):  # type: ignore[no-untyped-def]
    acc = 0
    for i in range(n):
        acc += level[flat[a, i] + off]
    return acc / (255.0 * n)


@njit(cache=True)
def _penalty(d, k, win):  # type: ignore[no-untyped-def]
    """Smallest |offset| (cells) over the node [d, min(d + 2^k - 1, win)]."""
    hi = min(d + (1 << k) - 1, win)
    if d <= 0 <= hi:
        return 0.0
    return float(min(abs(d), abs(hi)))


@njit(cache=True)
def _branch_and_bound(levels, flat, w, win, depth, ang_cost, lin_coef, min_score):  # type: ignore[no-untyped-def]
    """Best (angle index, dx, dy, score) with score > min_score, or angle index -1."""
    n_ang, n = flat.shape
    step = 1 << depth
    per_axis = (2 * win) // step + 1
    n_root = n_ang * per_axis * per_axis
    cap = n_root + 4 * (depth + 2)
    st_a = np.empty(cap, np.int64)
    st_x = np.empty(cap, np.int64)
    st_y = np.empty(cap, np.int64)
    st_k = np.full(cap, depth, np.int64)
    st_s = np.empty(cap, np.float64)
    root_a = np.empty(n_root, np.int64)
    root_x = np.empty(n_root, np.int64)
    root_y = np.empty(n_root, np.int64)
    root_s = np.empty(n_root, np.float64)
    r = 0
    for a in range(n_ang):
        for ix in range(per_axis):
            for iy in range(per_axis):
                dx = -win + ix * step
                dy = -win + iy * step
                px = _penalty(dx, depth, win)
                py = _penalty(dy, depth, win)
                f = ang_cost[a] + lin_coef * math.sqrt(px * px + py * py)
                f = math.exp(-f * f)
                root_s[r] = f * _node_score(levels[depth], flat, a, dy * w + dx, n)
                root_a[r] = a
                root_x[r] = dx
                root_y[r] = dy
                r += 1
    order = np.argsort(root_s)  # ascending: the best root is popped first
    for j in range(n_root):
        q = order[j]
        st_a[j] = root_a[q]
        st_x[j] = root_x[q]
        st_y[j] = root_y[q]
        st_s[j] = root_s[q]
    sp = n_root
    best_a, best_x, best_y, best_s = -1, 0, 0, min_score
    ch_x = np.empty(4, np.int64)
    ch_y = np.empty(4, np.int64)
    ch_s = np.empty(4, np.float64)
    while sp > 0:
        sp -= 1
        a, dx, dy, k, sc = st_a[sp], st_x[sp], st_y[sp], st_k[sp], st_s[sp]
        if sc <= best_s:
            continue
        if k == 0:
            best_a, best_x, best_y, best_s = a, dx, dy, sc
            continue
        kk = k - 1
        half = 1 << kk
        m = 0
        for ox in range(2):
            cx = dx + ox * half
            if cx > win:
                break
            for oy in range(2):
                cy = dy + oy * half
                if cy > win:
                    break
                px = _penalty(cx, kk, win)
                py = _penalty(cy, kk, win)
                f = ang_cost[a] + lin_coef * math.sqrt(px * px + py * py)
                f = math.exp(-f * f)
                s = f * _node_score(levels[kk], flat, a, cy * w + cx, n)
                # insertion sort, ascending
                j = m
                while j > 0 and ch_s[j - 1] > s:
                    ch_x[j] = ch_x[j - 1]
                    ch_y[j] = ch_y[j - 1]
                    ch_s[j] = ch_s[j - 1]
                    j -= 1
                ch_x[j] = cx
                ch_y[j] = cy
                ch_s[j] = s
                m += 1
        for j in range(m):
            if ch_s[j] > best_s:
                st_a[sp] = a
                st_x[sp] = ch_x[j]
                st_y[sp] = ch_y[j]
                st_k[sp] = kk
                st_s[sp] = ch_s[j]
                sp += 1
    return best_a, best_x, best_y, best_s


@dataclass(frozen=True)
class CorrelativeResult:
    """Best lattice pose T_submap_sensor [x, y, yaw] and its (penalized) score in [0, 1]."""

    pose: FloatArray
    score: float


class RealTimeCorrelativeMatcher:
    """Exhaustive-equivalent correlative search by branch and bound (see module doc).

    `linear_window` (m) and `angular_window` (rad) are half-widths around the
    prediction. `angular_step` (rad) defaults to Cartographer's: the angle that moves
    the farthest point by one cell. `min_score`: no result at or below it.
    `translation_delta_cost_weight` (1/m), `rotation_delta_cost_weight` (1/rad):
    Cartographer's real-time penalty, a tie-breaker toward the prediction.
    `pyramid_margin_m`: the max-pooled pyramid is computed on a crop this much larger
    than needed and reused while the grid is unchanged and the crop still covers.
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
        self.pyramid_margin_m = float(pyramid_margin_m)
        self.unknown_probability = _check_probability(unknown_probability)
        self._cache: tuple | None = None  # (grid ref, version, x0, y0, w, h, depth, levels)

    def match(
        self, grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
    ) -> CorrelativeResult | None:
        """Best pose T_submap_sensor near `predicted_pose`, or None (no points / score)."""
        pts = _finite_points(points_sensor, "points_sensor")
        pred = np.asarray(predicted_pose, dtype=np.float64).reshape(3)
        if len(pts) == 0:
            return None
        res = grid.resolution
        win = int(math.ceil(self.linear_window / res - 1e-9))
        depth = max(0, int(math.ceil(math.log2(2 * win + 1))))
        step = self.angular_step
        if step is None:
            d_max = float(np.sqrt(np.einsum("ij,ij->i", pts, pts).max()))
            step = (1.0 - 1e-3) * math.acos(max(-1.0, 1.0 - res * res / (2.0 * d_max * d_max)))
        n_ang = int(math.ceil(self.angular_window / step - 1e-9))
        offsets = np.arange(-n_ang, n_ang + 1) * step
        angles = pred[2] + offsets
        n = len(pts)
        cx = np.empty((len(angles), n), np.int64)
        cy = np.empty((len(angles), n), np.int64)
        ox, oy = grid.origin_xy
        _discretize(pts, angles, pred[0], pred[1], ox, oy, res, cx, cy)
        x0, y0, w, levels = self._levels(
            grid,
            cx.min() - win,
            cy.min() - win,
            cx.max() + win + (1 << depth),
            cy.max() + win + (1 << depth),
            depth,
        )
        flat = (cy - y0) * w + (cx - x0)
        ang_cost = self.rotation_delta_cost_weight * np.abs(offsets)
        lin_coef = self.translation_delta_cost_weight * res
        a, dx, dy, score = _branch_and_bound(
            levels, flat, w, win, depth, ang_cost, lin_coef, self.min_score
        )
        if a < 0:
            return None
        pose = np.array([pred[0] + dx * res, pred[1] + dy * res, float(wrap_angle(angles[a]))])
        return CorrelativeResult(pose=pose, score=float(score))

    def _levels(
        self, grid: ProbabilityGrid, lx: int, ly: int, hx: int, hy: int, depth: int
    ) -> tuple[int, int, int, NDArray[np.uint8]]:
        """The pyramid over grid cells [lx, hx) x [ly, hy), from the cache if it covers."""
        c = self._cache
        if c is not None and c[0]() is grid and c[1] == grid.version and c[6] == depth:
            _, _, x0, y0, w, h, _, levels = c
            if x0 <= lx and y0 <= ly and hx <= x0 + w and hy <= y0 + h:
                return x0, y0, w, levels
        m = int(math.ceil(self.pyramid_margin_m / grid.resolution))
        x0, y0 = int(lx) - m, int(ly) - m
        w, h = int(hx) + m - x0, int(hy) + m - y0
        levels = _build_levels(grid, x0, y0, w, h, depth, self.unknown_probability)
        self._cache = (weakref.ref(grid), grid.version, x0, y0, w, h, depth, levels)
        return x0, y0, w, levels


# ---------------------------------------------------------------- refinement (numba kernels)


@njit(cache=True)
def _bicubic(g, p_unknown, u, v):  # type: ignore[no-untyped-def]
    """Catmull-Rom interpolation of g (unknown/outside -> p_unknown) at (u, v) in cell-centre
    units (u = 0 is the centre of column 0). Returns value, d/du, d/dv."""
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
def _normal_equations(g, p_unknown, ox, oy, res, pts, pose, prior, s_occ, w_t, w_r, H, b):  # type: ignore[no-untyped-def]
    """Cost 0.5 * sum r^2 at `pose`; fills H = J^T J and b = J^T r (3x3, 3).
    With s_occ = 1, w_t = w_r = 0 these are the bare occupancy terms."""
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    for i in range(3):
        b[i] = 0.0
        for j in range(3):
            H[i, j] = 0.0
    cost = 0.0
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
        b[0] += j0 * r
        b[1] += j1 * r
        b[2] += j2 * r
        H[0, 0] += j0 * j0
        H[0, 1] += j0 * j1
        H[0, 2] += j0 * j2
        H[1, 1] += j1 * j1
        H[1, 2] += j1 * j2
        H[2, 2] += j2 * j2
    for k in range(2):
        r = w_t * (pose[k] - prior[k])
        cost += r * r
        b[k] += w_t * r
        H[k, k] += w_t * w_t
    d = pose[2] - prior[2]
    d = d - 2.0 * math.pi * math.floor((d + math.pi) / (2.0 * math.pi))
    r = w_r * d
    cost += r * r
    b[2] += w_r * r
    H[2, 2] += w_r * w_r
    H[1, 0] = H[0, 1]
    H[2, 0] = H[0, 2]
    H[2, 1] = H[1, 2]
    return 0.5 * cost


@njit(cache=True)
def _solve3(A, y):  # type: ignore[no-untyped-def]
    """x with A x = y for a symmetric positive definite 3x3 A (Cholesky)."""
    l00 = math.sqrt(A[0, 0])
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
    w_r,  # type: ignore[no-untyped-def]
    max_iterations,
    step_tol_m,
    step_tol_rad,
    cost_tol,
):
    """Minimize the refinement cost from pose0; returns (pose, cost, iterations, converged)."""
    H = np.empty((3, 3))
    b = np.empty(3)
    Hn = np.empty((3, 3))
    bn = np.empty(3)
    A = np.empty((3, 3))
    pose = pose0.copy()
    cost = _normal_equations(g, p_unknown, ox, oy, res, pts, pose, prior, s_occ, w_t, w_r, H, b)
    lam = 1e-4
    converged = False
    it = 0
    while it < max_iterations:
        it += 1
        for i in range(3):
            for j in range(3):
                A[i, j] = H[i, j]
            A[i, i] += lam * H[i, i] + 1e-12
        delta = _solve3(A, -b)
        cand = pose + delta
        new_cost = _normal_equations(
            g, p_unknown, ox, oy, res, pts, cand, prior, s_occ, w_t, w_r, Hn, bn
        )
        small = (
            abs(delta[0]) < step_tol_m
            and abs(delta[1]) < step_tol_m
            and abs(delta[2]) < step_tol_rad
        )
        if new_cost <= cost:
            decrease = cost - new_cost
            pose = cand
            H[:, :] = Hn
            b[:] = bn
            cost = new_cost
            lam = max(lam * 0.3, 1e-9)
            if small or decrease <= cost_tol * cost:
                converged = True
                break
        else:
            if small:
                converged = True
                break
            lam *= 10.0
            if lam > 1e6:
                break
    return pose, cost, it, converged


@njit(cache=True)
def _mean_cell_probability(g, p_unknown, ox, oy, res, pts, pose):  # type: ignore[no-untyped-def]
    """Mean probability of the cells the points fall in (unknown/outside -> p_unknown)."""
    ny, nx = g.shape
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    acc = 0.0
    for i in range(pts.shape[0]):
        x = int(math.floor((pose[0] + c * pts[i, 0] - s * pts[i, 1] - ox) / res))
        y = int(math.floor((pose[1] + s * pts[i, 0] + c * pts[i, 1] - oy) / res))
        v = p_unknown
        if 0 <= x < nx and 0 <= y < ny:
            v = _p(g[y, x], p_unknown)
        acc += v
    return acc / max(pts.shape[0], 1)


@dataclass(frozen=True)
class RefineResult:
    """Refined T_submap_sensor and what the covariance needs.

    `information`: J^T J of the bare occupancy residuals 1 - P(T p_i) at the solution
    (3x3, [x, y, yaw]); `residual_variance`: sum (1 - P_i)^2 / max(N - 3, 1).
    """

    pose: FloatArray
    cost: float
    iterations: int
    converged: bool
    information: FloatArray
    residual_variance: float


class CeresLikeRefiner:
    """Levenberg-Marquardt refinement on the bicubic grid (see module doc for the cost).

    Weights are Cartographer's `occupied_space_weight` (residuals scaled by
    1/sqrt(N)), `translation_weight` (1/m) and `rotation_weight` (1/rad); the
    defaults keep the prior a weak regularizer, so an offset prediction does not bias
    the result (Cartographer's local defaults 10 and 40 trust a good IMU prediction).
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
        self.unknown_probability = _check_probability(unknown_probability)

    def refine(
        self,
        grid: ProbabilityGrid,
        points_sensor: ArrayLike,
        initial_pose: ArrayLike,
        prior_pose: ArrayLike | None = None,
    ) -> RefineResult:
        """Refine T_submap_sensor from `initial_pose`, regularized toward `prior_pose`
        (default: `initial_pose`). Needs at least 3 finite points."""
        pts = _finite_points(points_sensor, "points_sensor")
        if len(pts) < 3:
            raise CollabSlamError(f"refinement needs >= 3 finite points, got {len(pts)}")
        pose0 = np.asarray(initial_pose, dtype=np.float64).reshape(3).copy()
        prior = pose0 if prior_pose is None else np.asarray(prior_pose, np.float64).reshape(3)
        g, p_unknown = grid.data, self.unknown_probability
        ox, oy = (float(v) for v in grid.origin_xy)
        res = grid.resolution
        n = len(pts)
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
        )
        info = np.empty((3, 3))
        scratch = np.empty(3)
        half_ss = _normal_equations(
            g, p_unknown, ox, oy, res, pts, pose, pose, 1.0, 0.0, 0.0, info, scratch
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
    """`CeresLikeRefiner.refine` with default weights unless `refiner` is given."""
    return (refiner or CeresLikeRefiner()).refine(grid, points_sensor, initial_pose, prior_pose)


# ------------------------------------------------------------------------------- matching


@dataclass(frozen=True)
class MatchResult:
    """T_submap_sensor [x, y, yaw] (m, rad), its score (mean cell probability of the
    points, in [min_probability, max_probability]), covariance (3x3, see module doc),
    LM iterations, and `converged` (False: too few points, no correlative candidate or
    LM not converged; `pose` is then the best available estimate, the prediction when
    nothing could be matched). `correlative_score` is NaN when the search was skipped.
    """

    pose: FloatArray
    score: float
    covariance: FloatArray
    iterations: int
    converged: bool
    correlative_score: float = math.nan


class ScanMatcher:
    """Correlative search (optional) then refinement, with a covariance; see module doc.

    `covariance_prior_sigma_xy` (m) / `covariance_prior_sigma_yaw` (rad) bound the
    covariance of unconstrained directions; they default to the correlative windows.
    `min_num_points`: fewer finite points give a not-converged result.
    """

    def __init__(
        self,
        correlative: RealTimeCorrelativeMatcher | None = None,
        refiner: CeresLikeRefiner | None = None,
        use_correlative: bool = True,
        covariance_prior_sigma_xy: float | None = None,
        covariance_prior_sigma_yaw: float | None = None,
        min_num_points: int = 3,
    ) -> None:
        self.correlative = correlative or RealTimeCorrelativeMatcher()
        self.refiner = refiner or CeresLikeRefiner()
        self.use_correlative = bool(use_correlative)
        sxy = covariance_prior_sigma_xy or max(self.correlative.linear_window, 1e-3)
        syaw = covariance_prior_sigma_yaw or max(self.correlative.angular_window, 1e-3)
        self.prior_information = np.diag([1.0 / sxy**2, 1.0 / sxy**2, 1.0 / syaw**2])
        self.min_num_points = max(3, int(min_num_points))

    def match(
        self, grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
    ) -> MatchResult:
        """Match (N, 2) sensor-frame points against `grid` near `predicted_pose`
        (T_submap_sensor). Raises CollabSlamError for a grid with no scan or a bad shape;
        an empty or all-NaN scan gives `converged=False` at the prediction."""
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
            return MatchResult(pred.copy(), 0.0, np.linalg.inv(self.prior_information), 0, False)
        initial, prior, corr_score, found = pred, pred, math.nan, True
        if self.use_correlative:
            corr = self.correlative.match(grid, pts, pred)
            if corr is None:
                found = False
                logger.debug("correlative search found no candidate above min_score")
            else:
                initial, corr_score = corr.pose, corr.score
                prior = np.array([pred[0], pred[1], corr.pose[2]])
        ref = self.refiner.refine(grid, pts, initial, prior)
        info = ref.information / max(ref.residual_variance, 1e-12) + self.prior_information
        covariance = np.linalg.inv(info)
        covariance = 0.5 * (covariance + covariance.T)
        ox, oy = (float(v) for v in grid.origin_xy)
        score = _mean_cell_probability(
            grid.data, grid.min_probability, ox, oy, grid.resolution, pts, ref.pose
        )
        return MatchResult(
            ref.pose, float(score), covariance, ref.iterations, ref.converged and found, corr_score
        )


_default_matcher: ScanMatcher | None = None


def match(
    grid: ProbabilityGrid, points_sensor: ArrayLike, predicted_pose: ArrayLike
) -> MatchResult:
    """`ScanMatcher.match` with the default parameters (one shared instance)."""
    global _default_matcher
    if _default_matcher is None:
        _default_matcher = ScanMatcher()
    return _default_matcher.match(grid, points_sensor, predicted_pose)
