"""Travel distances on the global grid, for goal costs (eq. 3's distance term).

A straight-line distance sends a robot to the frontier just behind a wall; what
matters is how far it must fly. `travel_distances` runs Dijkstra (8-connected,
`basestation.grid_search`) on a coarse copy of the grid in which a cell is passable when
its centre is more than `clearance_m` from every occupied cell (unknown counts as
passable, as for the planner, but may cost more per m: `unknown_factor`). Robots and
frontiers off the passable cells are snapped to the nearest passable cell.
Unreachable pairs get `inf`.

`grid_path` is a shortest cell path (A*) on a given passable mask: the planner's
reference for RRT* and its fallback when RRT* finds nothing within its budget.
"""

from __future__ import annotations

import zlib

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from basestation.grid_search import grid_astar, grid_distances
from common.map_io import GridMap

_last_wall_distance: tuple[tuple[tuple[int, ...], float, int], NDArray[np.float64]] | None = None


def wall_distance(occupied: NDArray[np.bool_], resolution: float) -> NDArray[np.float64]:
    """Distance (m) from every cell to the nearest occupied one (read-only). One
    exploration step plans many paths and asks for many travel distances on the same
    grid: the last result is reused while the occupied cells are the same (a CRC of
    the mask, ~0.1 ms, against 10-20 ms for the transform of a 30 x 25 m map)."""
    global _last_wall_distance
    key = (occupied.shape, float(resolution), zlib.crc32(np.ascontiguousarray(occupied)))
    if _last_wall_distance is None or _last_wall_distance[0] != key:
        if occupied.any():
            dist = ndimage.distance_transform_edt(~occupied) * resolution
        else:  # (scipy measures from a point beside cell (0, 0): a wall zone in a corner)
            dist = np.full(occupied.shape, np.inf)
        dist.flags.writeable = False
        _last_wall_distance = (key, dist)
    return _last_wall_distance[1]


def travel_distances(
    grid: GridMap,
    sources: ArrayLike,
    targets: ArrayLike,
    clearance_m: float = 0.25,
    unknown_factor: float = 1.0,
    cell_m: float = 0.2,
) -> NDArray[np.float64]:
    """(len(sources), len(targets)) travel distances (m) between [x, y] points (map frame);
    each m through unknown cells counts `unknown_factor` times (>= 1)."""
    src = np.asarray(sources, dtype=np.float64).reshape(-1, 2)
    dst = np.asarray(targets, dtype=np.float64).reshape(-1, 2)
    out = np.full((len(src), len(dst)), np.inf)
    if not len(src) or not len(dst):
        return out
    step = max(1, int(round(cell_m / grid.resolution)))
    cell = step * grid.resolution
    occupied = grid.data > 0
    clear = wall_distance(occupied, grid.resolution) > clearance_m
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
        return (ny[iy, ix] * w + nx[iy, ix]).astype(np.int64)

    unknown = (grid.data < 0)[step // 2 :: step, step // 2 :: step]
    weight = np.where(unknown, unknown_factor, 1.0)
    passable = np.ascontiguousarray(passable)
    return _cached_distances(passable, cell, node(src), node(dst), weight)


# The distances found on the last coarse grid, per source node: {target node: m}. One
# exploration step asks several times on the same grid, mostly for the same frontiers
# (80 frontiers: 5 searches from every one, 5-12 s a step, on a 60 x 60 m map).
_last_rows: tuple[tuple[object, ...], dict[int, dict[int, float]]] | None = None


def _cached_distances(
    passable: NDArray[np.bool_], cell: float, src: NDArray[np.int64], dst: NDArray[np.int64],
    weight: NDArray[np.float64],
) -> NDArray[np.float64]:  # fmt: skip
    """`grid_distances`, its rows taken from the last calls' on the same grid (Dijkstra's
    distance to a target does not depend on the other targets: the same numbers)."""
    global _last_rows
    key = (passable.shape, cell, zlib.crc32(passable), zlib.crc32(np.ascontiguousarray(weight)))
    if _last_rows is None or _last_rows[0] != key:
        _last_rows = (key, {})
    rows = _last_rows[1]
    targets = dst.tolist()
    need = [k for k, s in enumerate(src.tolist()) if not rows.get(s, {}).keys() >= set(targets)]
    if need:
        found = grid_distances(passable, cell, src[need], dst, weight)
        for k, row in zip(need, found.tolist(), strict=True):
            rows.setdefault(int(src[k]), {}).update(zip(targets, row, strict=True))
    return np.array([[rows[s][t] for t in targets] for s in src.tolist()]).reshape(len(src), -1)


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
    nodes = grid_astar(np.ascontiguousarray(passable), resolution, src, dst, float(limit_m))
    if not len(nodes):
        return None
    iy, ix = np.divmod(nodes, w)
    path = o + (np.column_stack([ix, iy]) + 0.5) * resolution
    path[0], path[-1] = ends
    return path


def planning_order(
    need: list[str],
    goals: dict[str, NDArray[np.float64] | None],
    grid: GridMap,
    P: dict[str, NDArray[np.float64]],
    robot_radius_m: float,
    by_travel: bool = True,
) -> list[str]:
    """Robots in the order their paths are planned (each around those before it): with
    `by_travel`, the shortest way to its goal first, so that of robots queueing for one
    door the one that clears it soonest goes first and the others follow. Ties (and
    robots without a goal, last) by id: the order does not depend on message arrival."""
    with_goal = sorted(r for r in need if goals.get(r) is not None)
    if len(with_goal) < 2 or not by_travel:
        return with_goal + sorted(set(need) - set(with_goal))
    starts = np.array([P[r][:2] for r in with_goal])
    ends = np.array([goals[r] for r in with_goal])
    D = travel_distances(grid, starts, ends, robot_radius_m).diagonal()
    order = sorted(range(len(with_goal)), key=lambda k: (D[k], with_goal[k]))
    return [with_goal[k] for k in order] + sorted(set(need) - set(with_goal))
