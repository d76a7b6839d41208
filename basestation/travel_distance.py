"""Travel distances on the global grid, for goal costs (eq. 3's distance term).

A straight-line distance sends a robot to the frontier just behind a wall; what
matters is how far it must fly. `travel_distances` runs Dijkstra (8-connected,
scipy's csgraph) on a coarse copy of the grid in which a cell is passable when
its centre is more than `clearance_m` from every occupied cell (unknown counts as
passable, as for the planner). Robots and frontiers off the passable cells are
snapped to the nearest passable cell. Unreachable pairs get `inf`.

`grid_path` is the same Dijkstra on a given passable mask, returning the cell path:
the planner's fallback when RRT* finds nothing within its time budget.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from common.map_io import GridMap


def _graph(passable: NDArray[np.bool_], cell_m: float) -> coo_matrix:
    h, w = passable.shape
    idx = np.arange(h * w).reshape(h, w)
    rows, cols, vals = [], [], []
    for dy, dx, length in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, np.sqrt(2.0)), (1, -1, np.sqrt(2.0))):
        x0, x1 = max(0, -dx), w - max(0, dx)  # cells (y, x) whose neighbour (y+dy, x+dx) exists
        both = passable[: h - dy, x0:x1] & passable[dy:, x0 + dx : x1 + dx]
        rows.append(idx[: h - dy, x0:x1][both])
        cols.append(idx[dy:, x0 + dx : x1 + dx][both])
        vals.append(np.full(int(both.sum()), length * cell_m))
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    return coo_matrix((v, (r, c)), shape=(h * w, h * w))


def travel_distances(
    grid: GridMap,
    sources: ArrayLike,
    targets: ArrayLike,
    clearance_m: float = 0.25,
    cell_m: float = 0.2,
) -> NDArray[np.float64]:
    """(len(sources), len(targets)) travel distances (m) between [x, y] points (map frame)."""
    src = np.asarray(sources, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    out = np.full((len(src), len(dst)), np.inf)
    if not len(src) or not len(dst):
        return out
    step = max(1, int(round(cell_m / grid.resolution)))
    cell = step * grid.resolution
    occupied = grid.data > 0
    clear = ndimage.distance_transform_edt(~occupied) * grid.resolution > clearance_m
    passable = clear[step // 2 :: step, step // 2 :: step]
    if not passable.any():
        return out
    h, w = passable.shape
    origin = np.array(grid.origin[:2]) + (step // 2 + 0.5) * grid.resolution - 0.5 * cell
    # nearest passable coarse cell of every coarse cell (snapping)
    _, (ny, nx) = ndimage.distance_transform_edt(~passable, return_indices=True)

    def node(xy: NDArray[np.float64]) -> NDArray[np.int64]:
        ij = np.floor((xy - origin) / cell).astype(np.int64)
        ix, iy = np.clip(ij[:, 0], 0, w - 1), np.clip(ij[:, 1], 0, h - 1)
        return ny[iy, ix] * w + nx[iy, ix]

    d = dijkstra(_graph(passable, cell).tocsr(), directed=False, indices=node(src))
    return np.asarray(d, dtype=np.float64).reshape(len(src), -1)[:, node(dst)]


def grid_path(
    passable: NDArray[np.bool_], origin: ArrayLike, resolution: float, start: ArrayLike,
    goal: ArrayLike, limit_m: float = np.inf,
) -> NDArray[np.float64] | None:  # fmt: skip
    """Shortest 8-connected path (N, 2) of cell centres (m, map frame) from the cell of
    `start` to the cell of `goal` over `passable` (data[iy, ix], cell (0, 0) with its
    corner at `origin`); its ends are `start` and `goal` themselves. None when either
    cell is outside or not passable, or they are not connected by a path of at most
    `limit_m` (the search stops there)."""
    h, w = passable.shape
    o = np.asarray(origin, dtype=np.float64)[:2]
    ends = np.array([np.asarray(start, float)[:2], np.asarray(goal, float)[:2]])
    ij = np.floor((ends - o) / resolution).astype(np.int64)
    if np.any(ij < 0) or np.any(ij[:, 0] >= w) or np.any(ij[:, 1] >= h):
        return None
    if not passable[ij[:, 1], ij[:, 0]].all():
        return None
    src, dst = (int(i[1] * w + i[0]) for i in ij)
    d, pred = dijkstra(
        _graph(passable, resolution).tocsr(), directed=False, indices=src,
        return_predecessors=True, limit=float(limit_m),
    )  # fmt: skip
    if not np.isfinite(d[dst]):
        return None
    nodes = [dst]
    while nodes[-1] != src:
        nodes.append(int(pred[nodes[-1]]))
    iy, ix = np.divmod(np.array(nodes[::-1]), w)
    path = o + (np.column_stack([ix, iy]) + 0.5) * resolution
    path[0], path[-1] = ends
    return path
