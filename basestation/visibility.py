"""Which frontiers a robot will see from its path (line of sight within sensor range).

A robot flying to its goal scans everything in line of sight of its way, within the
range at which its laser maps reliably and inside its field of view (laser sectors
point along the direction of flight). A frontier it will see that way is likely gone
before another robot could get there: coordinated exploration makes such frontiers
cost more for the others (Burgard et al. 2005's utility reduction by expected
visibility, in place of a fixed radius around the goal only).

Line of sight is read on the current grid: every cell between the viewpoint and the
frontier (but the last `end_margin_m`, the frontier's own edge) must be free.
Unknown cells block it: whether a wall stands in them is not known yet.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from common.geometry import wrap_angle
from common.map_io import GridMap


def viewpoints(
    path: NDArray[np.float64], spacing_m: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """((M, 2) points every `spacing_m` along a polyline and its end, (M,) heading of
    flight at each: the direction of the segment it lies on)."""
    seg = np.diff(path, axis=0)
    lengths = np.hypot(*seg.T)
    keep = lengths > 1e-9
    if not keep.any():
        return path[-1:].copy(), np.zeros(1)
    path = np.vstack([path[:1], path[1:][keep]])
    seg, lengths = seg[keep], lengths[keep]
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    s = np.append(np.arange(0.0, cum[-1], spacing_m), cum[-1])
    k = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    frac = ((s - cum[k]) / lengths[k])[:, None]
    points = path[k] + frac * seg[k]
    return points, np.arctan2(seg[k, 1], seg[k, 0])


def seen_from(
    grid: GridMap,
    points: NDArray[np.float64],
    headings: NDArray[np.float64],
    targets: NDArray[np.float64],
    range_m: float,
    fov_rad: float,
    end_margin_m: float = 0.15,
) -> NDArray[np.bool_]:
    """(N,) whether each target is in line of sight of at least one viewpoint, within
    `range_m` and within `fov_rad` (total) around that viewpoint's heading."""
    seen = np.zeros(len(targets), dtype=bool)
    if not len(targets) or not len(points):
        return seen
    d = targets[None, :, :] - points[:, None, :]  # (M, N, 2)
    dist = np.hypot(d[..., 0], d[..., 1])
    bearing = np.abs(wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - headings[:, None]))
    pm, pn = np.nonzero((dist <= range_m) & (bearing <= 0.5 * fov_rad))
    if not len(pm):
        return seen
    free = grid.free_mask()
    step = 0.5 * grid.resolution
    n_samples = max(2, int(np.ceil(range_m / step)))
    t = np.arange(n_samples) * step  # m along each ray
    length = np.maximum(dist[pm, pn] - end_margin_m, 0.0)
    unit = d[pm, pn] / np.maximum(dist[pm, pn], 1e-9)[:, None]
    xy = points[pm][:, None, :] + unit[:, None, :] * t[None, :, None]  # (P, S, 2)
    cells = grid.world_to_cell(xy.reshape(-1, 2))
    inside = grid.in_bounds(cells)
    ok = np.zeros(len(cells), dtype=bool)
    ok[inside] = free[cells[inside, 1], cells[inside, 0]]
    ok = ok.reshape(len(pm), n_samples) | (t[None, :] > length[:, None])
    clear = ok.all(axis=1)
    seen[np.unique(pn[clear])] = True
    return seen


def unknown_in_view(
    grid: GridMap, points: NDArray[np.float64], radius_m: float, rays: int = 72
) -> NDArray[np.float64]:
    """(N,) m^2 of unknown cells a 360-degree look from each point would take in within
    `radius_m`: rays pass free and unknown cells and stop at the first occupied one or
    the grid's edge (optimistic: walls not mapped yet do not block). The information a
    frontier is worth: a door into an unexplored room against a pocket in a corner."""
    out = np.zeros(len(points))
    if not len(points) or radius_m <= 0.0:
        return out
    res = grid.resolution
    step = 0.5 * res  # half a cell: a ray does not slip between diagonal wall cells
    r = np.arange(1, max(2, int(np.ceil(radius_m / step))) + 1) * step  # (S,) m
    theta = np.linspace(0.0, 2.0 * np.pi, rays, endpoint=False)
    # each ray as cell offsets from the cell a look starts in (R, S)
    dx = np.rint(np.cos(theta)[:, None] * r[None, :] / res).astype(np.int32)
    dy = np.rint(np.sin(theta)[:, None] * r[None, :] / res).astype(np.int32)
    c = grid.world_to_cell(np.asarray(points, dtype=np.float64)[:, :2]).astype(np.int32)
    ix = c[:, 0, None, None] + dx[None]  # (N, R, S)
    iy = c[:, 1, None, None] + dy[None]
    h, w = grid.data.shape
    inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    value = grid.data[np.clip(iy, 0, h - 1), np.clip(ix, 0, w - 1)]
    value = np.where(inside, value, 100)  # outside the grid: blocks
    open_ = np.logical_and.accumulate(value <= 0, axis=2)  # free or unknown, no wall yet
    area = r * step * (2.0 * np.pi / rays)  # m^2 a sample stands for
    return ((value < 0) & open_).sum(axis=1) @ area
