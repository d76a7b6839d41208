"""Evaluation metrics: trajectory error (ATE) and map coverage / accuracy.

All quantities are in the `map` frame of the ground truth, metres and radians.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from common.errors import CollabSlamError
from common.geometry import quat_to_yaw, wrap_angle
from common.map_io import FREE_MAX, OCCUPIED_MIN, GridMap
from common.trajectory_io import Trajectory

logger = logging.getLogger(__name__)


def associate(
    est: Trajectory, gt: Trajectory, max_dt: float = 0.1, with_z: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Pair every estimated pose with the ground truth interpolated at its stamp.

    Only est stamps inside gt's time span and within `max_dt` (s) of a gt sample are
    kept. gt positions are interpolated linearly, gt yaw linearly on the unwrapped
    angle. Returns (est, gt) arrays of shape (M, 3) [x, y, yaw], or (M, 4)
    [x, y, z, yaw] if `with_z`.
    """
    cols = 4 if with_z else 3
    empty = np.zeros((0, cols))
    if len(est) == 0 or len(gt) == 0:
        return empty, empty.copy()
    t_est, t_gt = est.stamps, gt.stamps
    inside = (t_est >= t_gt[0]) & (t_est <= t_gt[-1])
    right = np.clip(np.searchsorted(t_gt, t_est), 0, len(t_gt) - 1)
    left = np.clip(right - 1, 0, len(t_gt) - 1)
    nearest_dt = np.minimum(np.abs(t_est - t_gt[left]), np.abs(t_gt[right] - t_est))
    keep = inside & (nearest_dt <= max_dt)
    t = t_est[keep]

    gt_yaw = np.unwrap(quat_to_yaw(gt.quats_xyzw))
    gt_cols = [np.interp(t, t_gt, gt.positions[:, i]) for i in range(3)]
    gt_cols.append(wrap_angle(np.interp(t, t_gt, gt_yaw)))
    est_cols = [est.positions[keep, i] for i in range(3)]
    est_cols.append(quat_to_yaw(est.quats_xyzw[keep]))
    pick = [0, 1, 2, 3] if with_z else [0, 1, 3]
    return (
        np.column_stack([est_cols[i] for i in pick]).reshape(-1, cols),
        np.column_stack([gt_cols[i] for i in pick]).reshape(-1, cols),
    )


def _align_yaw_translation(
    est_xyz: NDArray[np.float64], gt_xyz: NDArray[np.float64]
) -> NDArray[np.float64]:
    """est positions moved by the rotation about z and 3-D translation that best fit gt
    (least squares; the x-y part is a 2-D Kabsch/Umeyama without scale)."""
    mu_e = est_xyz.mean(axis=0)
    mu_g = gt_xyz.mean(axis=0)
    e = est_xyz[:, :2] - mu_e[:2]
    g = gt_xyz[:, :2] - mu_g[:2]
    theta = np.arctan2(np.sum(e[:, 0] * g[:, 1] - e[:, 1] * g[:, 0]), np.sum(e * g))
    c, s = np.cos(theta), np.sin(theta)
    out = np.empty_like(est_xyz)
    out[:, 0] = c * e[:, 0] - s * e[:, 1] + mu_g[0]
    out[:, 1] = s * e[:, 0] + c * e[:, 1] + mu_g[1]
    out[:, 2] = est_xyz[:, 2] - mu_e[2] + mu_g[2]
    return out


def ate_rmse(
    est: Trajectory, gt: Trajectory, align: bool = False, max_dt: float = 0.1, with_z: bool = True
) -> float:
    """Absolute trajectory error: RMSE (m) of the 3-D position error after `associate`.

    `align=True` first applies the yaw rotation and 3-D translation that best fit the
    estimate to gt (the 4-DOF gauge freedom of a gravity-aligned SLAM system; for
    planar data this is the rigid 2-D Kabsch/Umeyama alignment).
    Raises CollabSlamError if fewer than 2 poses associate.
    """
    e, g = associate(est, gt, max_dt=max_dt, with_z=True)
    if len(e) < 2:
        raise CollabSlamError(
            f"ATE needs at least 2 associated poses, got {len(e)} "
            f"(est {len(est)} poses, gt {len(gt)} poses, max_dt {max_dt} s)"
        )
    p_est = _align_yaw_translation(e[:, :3], g[:, :3]) if align else e[:, :3]
    cols = 3 if with_z else 2  # with_z False: horizontal only (a 2-D graph; z is the altimeter)
    return float(np.sqrt(np.mean(np.sum((p_est[:, :cols] - g[:, :cols]) ** 2, axis=1))))


def _world_cells_of(grid: GridMap, world: GridMap) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """(H*W, 2) world cell [ix, iy] containing each `grid` cell centre, and which exist."""
    xs, ys = grid.cell_centers()
    cx, cy = np.meshgrid(xs, ys)
    cells = world.world_to_cell(np.column_stack([cx.ravel(), cy.ravel()]))
    return cells, world.in_bounds(cells)


def _distance_to(mask: NDArray[np.bool_], resolution: float) -> NDArray[np.float64]:
    """Distance (m) from each cell centre to the nearest cell centre in `mask`."""
    if not mask.any():
        return np.full(mask.shape, np.inf)
    return ndimage.distance_transform_edt(~mask, sampling=resolution)


WALL_TOLERANCE_M = 0.1  # map_accuracy's tolerance, also what map_coverage forgives at walls


def map_coverage(
    map_: GridMap,
    world: GridMap,
    region: NDArray[np.bool_] | None = None,
    wall_tolerance_m: float = WALL_TOLERANCE_M,
) -> float:
    """Fraction of the world's free cells (or of `region`, a mask over the world's
    cells) that `map_` knows: their centre falls in a free cell of `map_`, or in an
    occupied one while the world has a wall within `wall_tolerance_m` of the cell.

    The second case is the wall surface: a laser map's occupied cells hold the hits on
    it, and where a wall's edge does not line up with the map's cells, the world cell
    next to it (free in the world) has its centre in a map cell that is occupied.
    That cell has been seen, and `map_accuracy` (same tolerance) counts its label as
    right; read as free-only, 2.4-3.2 % of a world's reachable free area stayed
    "unknown" however long the robots looked (docs/architecture.md, "Exploration").
    `wall_tolerance_m` 0 counts map-free cells only.

    `map_` is sampled at the world's cell centres by the map cell containing each
    centre (resolutions and origins may differ); centres outside `map_` count as not
    covered. Raises CollabSlamError if the world has no free cell.
    """
    return coverage_of(CoverageTarget(world, region, wall_tolerance_m), map_)


class CoverageTarget:
    """The cells `map_coverage` counts, prepared once for many maps (a map history)."""

    def __init__(
        self,
        world: GridMap,
        region: NDArray[np.bool_] | None = None,
        wall_tolerance_m: float = WALL_TOLERANCE_M,
    ) -> None:
        if wall_tolerance_m < 0.0:
            raise CollabSlamError(f"wall_tolerance_m must be >= 0, got {wall_tolerance_m}")
        world_free = world.free_mask() if region is None else region
        self.n = int(world_free.sum())
        if self.n == 0:
            raise CollabSlamError("map_coverage: the world map has no free cell")
        iy, ix = np.nonzero(world_free)
        self.centres = world.cell_to_world(np.column_stack([ix, iy]))
        d_wall = _distance_to(world.occupied_mask(), world.resolution)
        self.near_wall = d_wall[iy, ix] <= wall_tolerance_m + 1e-9


def coverage_of(target: CoverageTarget, map_: GridMap) -> float:
    """`map_coverage` of `map_` over a prepared target."""
    v = map_.sample(target.centres)
    known = ((v >= 0) & (v <= FREE_MAX)) | ((v >= OCCUPIED_MIN) & target.near_wall)
    return float(np.count_nonzero(known)) / target.n


def _agreement(map_: GridMap, world: GridMap, tolerance_m: float) -> tuple[int, int, int, int]:
    """(free agreeing, free counted, occupied agreeing, occupied counted); see map_accuracy."""
    if tolerance_m < 0.0:
        raise CollabSlamError(f"tolerance_m must be >= 0, got {tolerance_m}")
    cells, inside = _world_cells_of(map_, world)
    m_free = map_.free_mask().ravel() & inside
    m_occ = map_.occupied_mask().ravel() & inside

    w_occ_mask = world.occupied_mask()
    w_free_mask = world.free_mask()
    w_known = w_occ_mask | w_free_mask
    d_occ = _distance_to(w_occ_mask, world.resolution)
    d_free = _distance_to(w_free_mask, world.resolution)
    ix, iy = cells[:, 0], cells[:, 1]
    tol = tolerance_m + 1e-9

    f_idx = np.flatnonzero(m_free)
    free_ok = int(np.count_nonzero(d_free[iy[f_idx], ix[f_idx]] <= tol))
    o_idx = np.flatnonzero(m_occ)
    o_idx = o_idx[w_known[iy[o_idx], ix[o_idx]]]
    occ_ok = int(np.count_nonzero(d_occ[iy[o_idx], ix[o_idx]] <= tol))
    logger.debug(
        "map agreement: %d/%d free and %d/%d occupied cells",
        free_ok,
        len(f_idx),
        occ_ok,
        len(o_idx),
    )
    return free_ok, len(f_idx), occ_ok, len(o_idx)


def map_accuracy(map_: GridMap, world: GridMap, tolerance_m: float = WALL_TOLERANCE_M) -> float:
    """Fraction of `map_`'s known cells (centre inside the world's extent) that agree
    with the world.

    Rule (the same for both labels, so neither free nor occupied is favoured):
    a map cell labelled L (free or occupied) agrees if the world has a cell labelled
    L within `tolerance_m` of it. Distances are measured between world cell centres
    (Euclidean distance transform of the world); a map cell is represented by the
    world cell containing its centre. The tolerance absorbs discretization where a
    laser map meets thin walls: hits land on the wall surface, which may fall in the
    free cell next to a 1-3 cell thick drawn wall, and the last free cell of a beam
    may overlap the wall's edge. A wall drawn 0.5 m off, or free space through a
    wall thicker than 2 * tolerance, disagrees.

    World-unknown cells (outside the building): a map-free cell over them disagrees
    unless world free space is within tolerance (the laser cannot see through walls);
    a map-occupied cell over them is not counted (hits on the outer side of an
    exterior wall are not checkable).

    Free cells far outnumber wall cells, so this fraction moves little when only
    walls are wrong; `map_accuracy_per_label` reports both labels separately.
    Raises CollabSlamError if no map cell is counted.
    """
    free_ok, free_n, occ_ok, occ_n = _agreement(map_, world, tolerance_m)
    if free_n + occ_n == 0:
        raise CollabSlamError("map_accuracy: the map has no known cell inside the world")
    return (free_ok + occ_ok) / (free_n + occ_n)


def map_walls_found(
    map_: GridMap, world: GridMap, tolerance_m: float = WALL_TOLERANCE_M
) -> float | None:
    """Fraction of the world's wall surface (its occupied cells next to free ones) that
    `map_` draws: an occupied map cell within `tolerance_m`. What `map_accuracy` cannot
    see: a map with no wall at all scores 0.96-0.99 there. None if the world has no wall
    surface (an open field)."""
    surface = world.occupied_mask() & ndimage.binary_dilation(world.free_mask())
    iy, ix = np.nonzero(surface)
    if not len(iy):
        return None
    cells, inside = _world_cells_of(map_, world)
    drawn = np.zeros(world.data.shape, dtype=bool)
    hit = cells[map_.occupied_mask().ravel() & inside]
    drawn[hit[:, 1], hit[:, 0]] = True
    d = _distance_to(drawn, world.resolution)
    return float(np.count_nonzero(d[iy, ix] <= tolerance_m + 1e-9)) / len(iy)


def map_accuracy_per_label(
    map_: GridMap, world: GridMap, tolerance_m: float = WALL_TOLERANCE_M
) -> tuple[float, float]:
    """(free, occupied): the `map_accuracy` agreement fraction of the map's free cells
    and of its occupied cells, each NaN if the map has no counted cell of that label."""
    free_ok, free_n, occ_ok, occ_n = _agreement(map_, world, tolerance_m)
    return (
        free_ok / free_n if free_n else float("nan"),
        occ_ok / occ_n if occ_n else float("nan"),
    )


def reachable_free(world: GridMap, starts_xy: ArrayLike) -> NDArray[np.bool_]:
    """The world's free cells connected (8-neighbours) to a start position: the free
    area robots starting there can reach and explore. Raises CollabSlamError if no
    start lies in free space."""
    free = world.free_mask()
    labels, _ = ndimage.label(free, structure=np.ones((3, 3)))
    cells = world.world_to_cell(np.asarray(starts_xy, dtype=np.float64).reshape(-1, 2))
    cells = cells[world.in_bounds(cells)]
    ids = {int(v) for v in labels[cells[:, 1], cells[:, 0]] if v > 0}
    if not ids:
        raise CollabSlamError("reachable_free: no start position lies in the world's free space")
    return np.isin(labels, sorted(ids))


def coverage_curve(
    history: list[tuple[float, GridMap]],
    world: GridMap,
    region: NDArray[np.bool_],
    wall_tolerance_m: float = WALL_TOLERANCE_M,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(sim times, fraction of `region` each snapshot of the map knew, `map_coverage`)."""
    target = CoverageTarget(world, region, wall_tolerance_m)
    t = np.array([s for s, _ in history], dtype=np.float64)
    c = np.array([coverage_of(target, g) for _, g in history], dtype=np.float64)
    return t, c


def time_to_coverage(
    times: NDArray[np.float64], coverage: NDArray[np.float64], fraction: float = 0.95
) -> float | None:
    """First time the coverage reached `fraction`, or None if it never did."""
    hit = np.flatnonzero(np.asarray(coverage) >= fraction)
    return float(times[hit[0]]) if len(hit) else None


def min_separation(trajectories: list[Trajectory]) -> float | None:
    """Smallest distance (m, horizontal) between any two robots at the same time, the
    later trajectories interpolated at the first one's stamps; None for < 2 robots."""
    if len(trajectories) < 2:
        return None
    t = trajectories[0].stamps
    xy = [
        np.column_stack([np.interp(t, tr.stamps, tr.positions[:, i]) for i in range(2)])
        for tr in trajectories
    ]
    best = np.inf
    for i in range(len(xy)):
        for j in range(i + 1, len(xy)):
            best = min(best, float(np.min(np.hypot(*(xy[i] - xy[j]).T))))
    return best


# latencies a long-running process keeps for its percentiles: the latest ones (a deque
# with this maxlen), not every one of a mission that runs for hours
TIMINGS_KEPT = 10_000


def percentiles(prefix: str, values: ArrayLike) -> dict[str, float | None]:
    """{prefix_p50, prefix_p95, prefix_max} of a list of timings (None when empty)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    if not len(v):
        return {f"{prefix}_p50": None, f"{prefix}_p95": None, f"{prefix}_max": None}
    return {
        f"{prefix}_p50": float(np.percentile(v, 50)),
        f"{prefix}_p95": float(np.percentile(v, 95)),
        f"{prefix}_max": float(v.max()),
    }
