"""What a scan-match target is made of (`basestation.scan_verifier` builds it): the
likelihood field the correlative search scores on, line normals for point-to-line
ICP, the ICP normal equations (numba), and the `Target` that bundles them."""

from __future__ import annotations

import math
from dataclasses import dataclass
from dataclasses import field as dc_field

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree

from agent.probability_grid import ProbabilityGrid
from common.geometry import se2_transform_points

FloatArray = NDArray[np.float64]

FIELD_FLOOR = 1e-3  # what a cell far from every target point (or outside) scores


class LikelihoodField:
    """The correlative score grid of a target, shaped like a `ProbabilityGrid` for the
    matcher (`data` [iy, ix] float32, `origin_xy`, `resolution`, `shape`, `version`).

    Cells hold exp(-d^2 / 2 sigma^2) with d (m) the distance from the cell to the
    nearest cell holding a target point; 0 where that is below 1/255 (read as floor).
    """

    def __init__(self, points: FloatArray, resolution: float, sigma: float) -> None:
        pad = int(math.ceil(3.5 * sigma / resolution)) + 2
        lo = np.floor(points.min(axis=0) / resolution).astype(np.int64) - pad
        hi = np.floor(points.max(axis=0) / resolution).astype(np.int64) + pad
        nx, ny = (int(v) for v in hi - lo + 1)
        self.resolution = float(resolution)
        self.origin_xy = lo.astype(np.float64) * resolution
        cells = np.floor(points / resolution).astype(np.int64) - lo
        empty = np.ones((ny, nx), dtype=bool)
        empty[cells[:, 1], cells[:, 0]] = False
        d = distance_transform_edt(empty) * resolution
        f = np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)
        f[f < 1.0 / 255.0] = 0.0
        self.data: NDArray[np.float32] = f
        self.version = 0
        self.num_scans = 1
        self.min_probability = FIELD_FLOOR

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) in cells."""
        return (int(self.data.shape[0]), int(self.data.shape[1]))

    def score(self, points_b: FloatArray, T_a_b: FloatArray) -> float:
        """Mean field value of the points moved by T_a_b (outside or far: the floor)."""
        if len(points_b) == 0:
            return 0.0
        uv = np.floor((se2_transform_points(T_a_b, points_b) - self.origin_xy) / self.resolution)
        ix, iy = uv[:, 0].astype(np.int64), uv[:, 1].astype(np.int64)
        ny, nx = self.shape
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        v = np.full(len(points_b), FIELD_FLOOR)
        v[inside] = self.data[iy[inside], ix[inside]]
        v[v <= 0.0] = FIELD_FLOOR
        return float(v.mean())


@dataclass(frozen=True, eq=False)
class Target:
    """What a target node's scans become (frame a): build with `ScanVerifier.build_target`.

    `points` (N, 2) m, voxel-filtered; `normals` (N, 2) unit line normals, valid where
    `has_line`; `tree` a KD-tree of `points`; `field` the correlative score grid;
    `extent` [min x, min y, max x, max y] (m) of the points; `free_space` the scans
    inserted with their rays into a probability grid, when their origins were given;
    `facing` the side of each point's surface its scan saw (`facing_normals`), likewise.
    """

    points: FloatArray
    normals: FloatArray
    has_line: NDArray[np.bool_]
    tree: cKDTree
    field: LikelihoodField
    extent: FloatArray
    free_space: ProbabilityGrid | None
    facing: FloatArray | None = None  # see `facing_normals`; None without scan origins
    # correlative matchers (each caches its pyramid) and coarse fields, by purpose
    _cache: dict[str, object] = dc_field(default_factory=dict, repr=False)


def line_normals(
    points: FloatArray, tree: cKDTree, k: int, radius: float, max_flatness: float
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """PCA over the k nearest points within `radius`: unit normals (N, 2) and whether
    the neighbourhood is a line (>= 3 points, lambda_min / lambda_max <= max_flatness)."""
    n = len(points)
    k = min(k, n)
    dist, idx = tree.query(points, k=k, distance_upper_bound=radius)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    valid = idx < n
    nb = points[np.minimum(idx, n - 1)]
    w = valid.astype(np.float64)
    cnt = w.sum(axis=1)
    mean = (nb * w[..., None]).sum(axis=1) / cnt[:, None]
    d = (nb - mean[:, None, :]) * w[..., None]
    sxx = np.einsum("ij,ij->i", d[..., 0], d[..., 0])
    syy = np.einsum("ij,ij->i", d[..., 1], d[..., 1])
    sxy = np.einsum("ij,ij->i", d[..., 0], d[..., 1])
    half_tr = 0.5 * (sxx + syy)
    disc = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy**2, 0.0))
    lam_max, lam_min = half_tr + disc, half_tr - disc
    major = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of the line
    normals = np.stack([-np.sin(major), np.cos(major)], axis=1)
    has_line = (cnt >= 3) & (lam_max > 0.0) & (lam_min <= max_flatness * lam_max)
    return normals, has_line


def facing_normals(
    points: FloatArray, sensors: FloatArray, normals: FloatArray, has_line: NDArray[np.bool_]
) -> FloatArray:
    """(N, 2) unit vectors: each point's line normal turned toward the sensor that saw it
    (`sensors`, (N, 2) m), i.e. the side of the surface its scan saw; where no line was
    fit, the direction to that sensor."""
    view = sensors - points
    view = view / np.maximum(np.hypot(view[:, 0], view[:, 1]), 1e-9)[:, None]
    flip = np.einsum("ij,ij->i", normals, view) < 0.0
    turned = np.where(flip[:, None], -normals, normals)
    return np.where(has_line[:, None], turned, view)


def facing_correspondences(
    target: Target, moved: FloatArray, sensor_xy: FloatArray, idx: NDArray[np.intp]
) -> NDArray[np.intp]:
    """`idx` (nearest target point of each query point, `moved` into frame a; len(points)
    for none) without the pairs whose target surface, as its scan saw it, faces away from
    the sensor that saw the query point (`sensor_xy`, (N, 2), frame a): a query point on
    the far side of a thin wall is not on the face the target saw. Such pairs pulled
    matches through walls toward the target: in the simulator, ICP started at the true
    pose slid 3-5 cm, ~1 % of the distance between the two nodes."""
    if target.facing is None:
        return idx
    n = len(target.points)
    has = np.flatnonzero(idx < n)
    away = np.einsum("ij,ij->i", target.facing[idx[has]], sensor_xy[has] - moved[has]) < 0.0
    if not away.any():
        return idx
    out = idx.copy()
    out[has[away]] = n
    return out


@njit(cache=True)
def icp_normal_equations(q, pose, idx, tp, tn, line, H, g):  # type: ignore[no-untyped-def]
    """Fill H = J^T J, g = J^T r of the ICP residuals at `pose` (T_a_b, additive in
    frame a); idx[i] >= len(tp) means no correspondence. Returns (sum r^2, residuals)."""
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    n_t = tp.shape[0]
    for i in range(3):
        g[i] = 0.0
        for j in range(3):
            H[i, j] = 0.0
    ss = 0.0
    n_res = 0
    for i in range(q.shape[0]):
        j = idx[i]
        if j >= n_t:
            continue
        rx = c * q[i, 0] - s * q[i, 1]
        ry = s * q[i, 0] + c * q[i, 1]
        ex = pose[0] + rx - tp[j, 0]
        ey = pose[1] + ry - tp[j, 1]
        if line[j]:
            nx = tn[j, 0]
            ny = tn[j, 1]
            r = nx * ex + ny * ey
            jac = (nx, ny, -nx * ry + ny * rx)
            for a in range(3):
                g[a] += jac[a] * r
                for b in range(3):
                    H[a, b] += jac[a] * jac[b]
            ss += r * r
            n_res += 1
        else:
            # point-to-point: rows [1, 0, -ry] and [0, 1, rx]
            H[0, 0] += 1.0
            H[1, 1] += 1.0
            H[0, 2] -= ry
            H[2, 0] -= ry
            H[1, 2] += rx
            H[2, 1] += rx
            H[2, 2] += rx * rx + ry * ry
            g[0] += ex
            g[1] += ey
            g[2] += -ry * ex + rx * ey
            ss += ex * ex + ey * ey
            n_res += 2
    return ss, n_res
