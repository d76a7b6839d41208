"""Free-space tests of a scan match (see `basestation.scan_verifier`): does the query
contradict what the target saw, or the target what the query saw? A wrong match
between look-alike rooms passes score and overlap but puts walls where the other
side saw free space."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from agent.probability_grid import ProbabilityGrid
from basestation.match_target import Target
from common.errors import CollabSlamError

FloatArray = NDArray[np.float64]


def free_space_grid(
    resolution: float, parts: list[FloatArray], origins_in_a: list[ArrayLike]
) -> ProbabilityGrid:
    """The scans inserted with their rays (from their origins) into a probability grid."""
    origins = [np.asarray(o, dtype=np.float64).reshape(-1)[:2] for o in origins_in_a]
    allp = np.vstack([*parts, *[o[None] for o in origins]])
    if not np.all(np.isfinite(allp)):
        raise CollabSlamError("origins_in_a must be finite")
    lo = allp.min(axis=0) - 1.0
    size = np.ceil((allp.max(axis=0) + 1.0 - lo) / resolution).astype(int)
    grid = ProbabilityGrid(resolution, lo, (int(size[1]), int(size[0])))
    for pts, o in zip(parts, origins, strict=True):
        if len(pts):
            grid.insert(np.array([o[0], o[1], 0.0]), pts - o)
    return grid


def beam_violation_points(
    target: Target, raw: FloatArray, pose: FloatArray, margin: float
) -> float:
    """Fraction of the query's beams that passed through a target point: the point
    lies nearer to the query's sensor (the origin of frame b) than the returns of both
    beams around its bearing, by more than `margin` (m). Bearings in a gap of
    the query (no return over > 3 median beam spacings) count as unseen."""
    if len(raw) < 3:
        return 0.0
    order = np.argsort(np.arctan2(raw[:, 1], raw[:, 0]))
    b_q = np.arctan2(raw[order, 1], raw[order, 0])
    r_q = np.hypot(raw[order, 0], raw[order, 1])
    near = target.tree.query_ball_point(pose[:2], float(r_q.max()))
    if len(near) == 0:
        return 0.0
    p_a = target.points[np.asarray(near)]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = p_a - pose[:2]
    p_b = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    b_t = np.arctan2(p_b[:, 1], p_b[:, 0])
    r_t = np.hypot(p_b[:, 0], p_b[:, 1])
    # the beams k - 1 and k around each target bearing, on the circle
    b_ext = np.concatenate([b_q[-1:] - 2 * np.pi, b_q, b_q[:1] + 2 * np.pi])
    r_ext = np.concatenate([r_q[-1:], r_q, r_q[:1]])
    k = np.searchsorted(b_ext, b_t)
    spacing = float(np.median(np.diff(b_q)))
    seen = b_ext[k] - b_ext[k - 1] <= 3.0 * max(spacing, 1e-6)
    bound = np.minimum(r_ext[k], r_ext[k - 1]) - margin
    crossed = seen & (r_t < bound)
    # beam index k (1..n+1 on the extended circle) -> query beam, wrapped
    beams = np.unique(k[crossed] % len(b_q))
    return float(len(beams)) / len(b_q)


def beam_violation_grid(
    grid: ProbabilityGrid, beams: FloatArray, pose: FloatArray, margin: float
) -> float:
    """Fraction of the query's beams (points in frame b, sensor at its origin) whose
    ray crosses a cell the target's scans saw occupied (p >= 0.65) more than
    `margin` (m) before its return. On a grid, a stray point in a target
    scan (a person, noise) is outvoted by the scans that saw the cell free."""
    if len(beams) == 0:
        return 0.0
    r = np.hypot(beams[:, 0], beams[:, 1])
    step = grid.resolution
    n = int(np.ceil(r.max() / step))
    t = np.arange(1, n + 1) * step  # (S,) distances along every ray
    use = t[None, :] < (r[:, None] - margin)  # (B, S)
    dirs = beams / np.maximum(r, 1e-9)[:, None]
    c, s_ = math.cos(pose[2]), math.sin(pose[2])
    d_a = np.stack([c * dirs[:, 0] - s_ * dirs[:, 1], s_ * dirs[:, 0] + c * dirs[:, 1]], 1)
    xy = pose[:2] + t[None, :, None] * d_a[:, None, :]  # (B, S, 2) in frame a
    uv = np.floor((xy - grid.origin_xy) / step).astype(np.int64)
    ny, nx = grid.shape
    inside = use & (uv[..., 0] >= 0) & (uv[..., 0] < nx) & (uv[..., 1] >= 0) & (uv[..., 1] < ny)
    p = np.zeros(use.shape, dtype=np.float32)
    p[inside] = grid.data[uv[..., 1][inside], uv[..., 0][inside]]
    crossed = (p >= 0.65).any(axis=1)
    return float(np.count_nonzero(crossed)) / len(beams)


def target_free_violation(target: Target, moved: FloatArray, idx: NDArray[np.intp]) -> float:
    """Fraction of the query points (`moved`, in frame a) without a target point within
    the correspondence distance (`idx[i] >= len(target.points)`, from the KD-tree
    query) that fall in cells the target scans saw as free."""
    grid = target.free_space
    assert grid is not None
    lonely = moved[idx >= len(target.points)]
    if len(lonely) == 0:
        return 0.0
    uv = np.floor((lonely - grid.origin_xy) / grid.resolution).astype(np.int64)
    ny, nx = grid.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < nx) & (uv[:, 1] >= 0) & (uv[:, 1] < ny)
    p = grid.data[uv[inside, 1], uv[inside, 0]]
    free = (p > 0.0) & (p < 0.5)
    return float(np.count_nonzero(free)) / len(moved)
