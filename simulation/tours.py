"""Scripted start poses and waypoint tours for a team of robots on any world.

Everything is planned on the world's own grid, on the cells whose centre keeps
a given clearance from every non-free cell (walls, unknown, the grid border):
8-connected Dijkstra (numba) for the paths, then line-of-sight shortcutting so
every straight segment between consecutive waypoints keeps the clearance too
(checked on the bilinearly interpolated clearance field, the one
`World.free_clearance` samples). Deterministic per seed.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

from common.errors import CollabSlamError, ConfigError
from simulation.raycast import cast_rays
from simulation.world import World, bilinear_at

logger = logging.getLogger(__name__)

__all__ = ["plan_tours", "start_poses"]

_SQRT2 = math.sqrt(2.0)
_PLAN_MARGIN_M = 0.02  # m planned on top of the requested clearance (interpolation slack)
_MAX_SEGMENT_M = 20.0  # m, longest straight segment the shortcutting tries


@njit(cache=True)
def _dijkstra(
    trav: NDArray[np.bool_],
    sources: NDArray[np.int64],
    targets: NDArray[np.bool_],
    dist: NDArray[np.float64],
    parent: NDArray[np.int64],
) -> int:
    """8-connected shortest paths over `trav` from the flat `sources`, no corner cutting,
    edge lengths 1 and 1.4 cells (integer costs 5 and 7, so a bucket queue (Dial) replaces
    the heap). Fills dist (cells, inf = unreached) and parent (-1 at sources). Stops at
    the first settled cell flagged in the flat `targets` and returns it (-1: none)."""
    h, w = trav.shape
    n = h * w
    flat = trav.ravel()
    big = np.iinfo(np.int64).max
    cost = np.full(n, big, dtype=np.int64)
    parent[:] = -1
    nb = 8  # > largest edge cost: live keys always fit in one turn of the ring
    head = np.full(nb, -1, dtype=np.int64)
    cap = 8 * n + sources.shape[0]  # each cell is pushed at most once per neighbour
    node = np.empty(cap, dtype=np.int32)
    nxt = np.empty(cap, dtype=np.int32)
    used = 0
    live = 0
    for s in sources:
        if flat[s] and cost[s] != 0:
            cost[s] = 0
            node[used] = s
            nxt[used] = head[0]
            head[0] = used
            used += 1
            live += 1
    dys = (-1, 1, 0, 0, -1, -1, 1, 1)
    dxs = (0, 0, -1, 1, -1, 1, -1, 1)
    found = -1
    d = 0
    while live > 0:
        b = d % nb
        e = head[b]
        if e < 0:
            d += 1
            continue
        head[b] = nxt[e]
        live -= 1
        u = np.int64(node[e])
        if cost[u] != d:
            continue  # stale entry
        if targets[u]:
            found = u
            break
        iy = u // w
        ix = u - iy * w
        for k in range(8):
            ny = iy + dys[k]
            nx = ix + dxs[k]
            if ny < 0 or ny >= h or nx < 0 or nx >= w:
                continue
            v = ny * w + nx
            if not flat[v]:
                continue
            if k >= 4:
                if not flat[iy * w + nx] or not flat[ny * w + ix]:
                    continue
                nd = d + 7
            else:
                nd = d + 5
            if nd < cost[v]:
                cost[v] = nd
                parent[v] = u
                bb = nd % nb
                node[used] = v
                nxt[used] = head[bb]
                head[bb] = used
                used += 1
                live += 1
    for i in range(n):
        dist[i] = np.inf if cost[i] == big else cost[i] / 5.0
    return found


@njit(cache=True)
def _segment_clear(
    field: NDArray[np.float64], x0: float, y0: float, x1: float, y1: float, thresh: float
) -> bool:
    """Whether the bilinear field stays >= thresh along the segment (cell coordinates),
    sampled every quarter cell."""
    n = int(math.ceil(math.hypot(x1 - x0, y1 - y0) / 0.25)) + 1
    for i in range(n + 1):
        t = i / n
        if bilinear_at(field, x0 + t * (x1 - x0), y0 + t * (y1 - y0)) < thresh:
            return False
    return True


@njit(cache=True)
def _shortcut(
    pts: NDArray[np.float64], field: NDArray[np.float64], thresh: float, max_len: float
) -> NDArray[np.int64]:
    """Greedy line-of-sight simplification of a polyline (cell coordinates): from each kept
    point, jump to the furthest next point reachable by a clear straight segment."""
    n = pts.shape[0]
    keep = np.empty(n, dtype=np.int64)
    keep[0] = 0
    m = 1
    i = 0
    while i < n - 1:
        j = i + 1
        while j + 1 < n:
            dx = pts[j + 1, 0] - pts[i, 0]
            dy = pts[j + 1, 1] - pts[i, 1]
            if math.hypot(dx, dy) > max_len:
                break
            if not _segment_clear(
                field, pts[i, 0], pts[i, 1], pts[j + 1, 0], pts[j + 1, 1], thresh
            ):
                break
            j += 1
        keep[m] = j
        m += 1
        i = j
    return keep[:m]


class _GridPlanner:
    """Traversable cells of a world for a clearance, and shortest paths on them."""

    def __init__(self, world: World, clearance: float) -> None:
        self.world = world
        self.field = world.free_clearance_grid
        self.thresh = clearance + _PLAN_MARGIN_M
        self.trav = np.ascontiguousarray(world.free & (self.field >= self.thresh))
        self.h, self.w = self.trav.shape
        self._dist = np.empty(self.trav.size)
        self._parent = np.empty(self.trav.size, dtype=np.int64)
        self._no_targets = np.zeros(self.trav.size, dtype=bool)

    def cell_of(self, xy: NDArray[np.float64]) -> NDArray[np.int64]:
        """Flat index of the nearest traversable cell to each (N, 2) point (-1 if none)."""
        iy, ix = np.nonzero(self.trav)
        if iy.size == 0:
            return np.full(len(xy), -1, dtype=np.int64)
        g = (np.asarray(xy, dtype=np.float64).reshape(-1, 2) - self.world.origin_xy) / (
            self.world.resolution
        )
        out = np.empty(len(g), dtype=np.int64)
        for k, (gx, gy) in enumerate(g):
            d2 = (ix + 0.5 - gx) ** 2 + (iy + 0.5 - gy) ** 2
            best = int(np.argmin(d2))
            out[k] = iy[best] * self.w + ix[best]
        return out

    def run(self, sources: ArrayLike, targets: NDArray[np.bool_] | None = None) -> int:
        """Dijkstra from flat sources; fills self.dist / self.parent; returns the reached
        target (-1 if none or no targets)."""
        src = np.asarray(sources, dtype=np.int64).reshape(-1)
        tg = self._no_targets if targets is None else targets
        return int(_dijkstra(self.trav, src, tg, self._dist, self._parent))

    @property
    def dist(self) -> NDArray[np.float64]:
        """Flat distances (m) of the last run."""
        return self._dist * self.world.resolution

    def path_to(self, target: int) -> NDArray[np.int64]:
        """Flat cells from the last run's source to target."""
        cells = [target]
        parent = self._parent
        while parent[cells[-1]] >= 0:
            cells.append(int(parent[cells[-1]]))
        return np.array(cells[::-1], dtype=np.int64)

    def centres(self, flat: ArrayLike) -> NDArray[np.float64]:
        """(N, 2) map-frame centres of flat cells."""
        f = np.asarray(flat, dtype=np.int64).reshape(-1)
        ij = np.stack([f % self.w, f // self.w], axis=1)
        return (ij + 0.5) * self.world.resolution + self.world.origin_xy


def start_poses(
    world: World, n_robots: int, seed: int, spacing: float = 1.5, clearance: float = 0.6
) -> NDArray[np.float64]:
    """(n_robots, 3) start poses [x, y, yaw] close together in the largest free region:
    each >= clearance (m) from any non-free cell, >= spacing (m) from the others, all
    facing the same way (the most open direction seen from the first robot).

    Raises CollabSlamError when the world has no such place for n_robots robots."""
    if n_robots < 1:
        raise ConfigError(f"n_robots must be >= 1, got {n_robots}")
    if not (spacing >= 0.0 and clearance >= 0.0):
        raise ConfigError(f"spacing and clearance must be >= 0, got {spacing}, {clearance}")
    rng = np.random.default_rng(seed)
    planner = _GridPlanner(world, clearance)
    labels, n = ndimage.label(planner.trav)
    if n == 0:
        raise CollabSlamError(
            f"world has no free cell {clearance} m away from walls and unknown space; "
            "cannot place robots"
        )
    sizes = np.bincount(labels.ravel())[1:]
    comp = labels == int(np.argmax(sizes)) + 1
    field = planner.field
    roomy = comp & (field >= max(clearance, 0.8 * float(field[comp].max())))
    iy, ix = np.nonzero(roomy)
    k = int(rng.integers(iy.size))
    planner.run([iy[k] * planner.w + ix[k]])
    dist = planner.dist
    cells = np.flatnonzero(np.isfinite(dist) & comp.ravel())
    cells = cells[np.argsort(dist[cells], kind="stable")]
    xy = planner.centres(cells)
    remaining = np.ones(len(cells), dtype=bool)
    chosen: list[int] = []
    for _ in range(n_robots):
        if not remaining.any():
            raise CollabSlamError(
                f"cannot place {n_robots} robots {spacing} m apart with {clearance} m "
                f"clearance in this world (only {len(chosen)} fit)"
            )
        i = int(np.argmax(remaining))
        chosen.append(i)
        remaining &= np.hypot(*(xy - xy[i]).T) >= spacing
    pos = xy[chosen]
    angles = np.linspace(-math.pi, math.pi, 72, endpoint=False)
    ranges = cast_rays(
        world.occupied, world.resolution, world.origin_xy, [*pos[0], 0.0], angles, 50.0
    )
    yaw = float(angles[int(np.argmax(np.where(np.isfinite(ranges), ranges, 50.0)))])
    return np.column_stack([pos, np.full(n_robots, yaw)])


def spread_start_poses(
    world: World, n_robots: int, seed: int, clearance: float = 0.6
) -> NDArray[np.float64]:
    """(n_robots, 3) start poses far apart (farthest-point sampling in path distance
    over the largest free region) with random headings: the "unknown start poses"
    case, where no robot starts near another or facing the same way."""
    if n_robots < 1:
        raise ConfigError(f"n_robots must be >= 1, got {n_robots}")
    rng = np.random.default_rng(seed)
    planner = _GridPlanner(world, clearance)
    labels, n = ndimage.label(planner.trav)
    if n == 0:
        raise CollabSlamError(f"world has no free cell {clearance} m away from walls")
    sizes = np.bincount(labels.ravel())[1:]
    comp = (labels == int(np.argmax(sizes)) + 1).ravel()
    cells = np.flatnonzero(comp)
    chosen = [int(cells[rng.integers(cells.size)])]
    nearest = np.full(comp.size, np.inf)
    for _ in range(1, n_robots):
        planner.run([chosen[-1]])
        nearest = np.minimum(nearest, planner.dist)
        score = np.where(comp & np.isfinite(nearest), nearest, -1.0)
        chosen.append(int(np.argmax(score)))
    pos = planner.centres(np.array(chosen))
    yaw = rng.uniform(-math.pi, math.pi, n_robots)
    return np.column_stack([pos, yaw])


def plan_tours(
    world: World,
    starts: ArrayLike,
    seed: int,
    length_m: float,
    clearance: float = 0.5,
    place_spacing: float = 2.0,
) -> list[NDArray[np.float64]]:
    """Per robot an (M, 2) array of map-frame waypoints, the first one its start.

    Each tour is about length_m (m) long and visits places spread over the world: the
    reachable free space is split into as many regions as robots (farthest-point
    anchors, geodesic Voronoi), each robot first flies to the far end of its own region,
    sweeps it nearest-place-first, then goes on to the rest of the world, revisiting
    when everything was seen. Paths stay on cells >= clearance (m) from any non-free
    cell, and every straight segment between waypoints keeps that clearance (except the
    first one if a start itself is closer). A tour ends early only when its robot
    cannot reach anywhere else; with no cell keeping the clearance at all, a tour is the
    start alone. Raises CollabSlamError if the world has no free space.
    """
    s = np.asarray(starts, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] < 2 or not np.all(np.isfinite(s)):
        raise ConfigError(f"starts must be an (N, 3) array of finite poses, got shape {s.shape}")
    if not (length_m >= 0.0 and math.isfinite(length_m)):
        raise ConfigError(f"length_m must be a finite number >= 0, got {length_m}")
    if not world.free.any():
        raise CollabSlamError("world has no free space: cannot plan tours")
    rng = np.random.default_rng(seed)
    start_xy = s[:, :2]
    planner = _GridPlanner(world, clearance)
    if not planner.trav.any():
        logger.warning("no free cell keeps %.2f m clearance: tours are the starts only", clearance)
        return [p[None].copy() for p in start_xy]

    start_cells = planner.cell_of(start_xy)
    planner.run(start_cells)
    reach = np.isfinite(planner.dist)
    places = _places(planner, reach, place_spacing, rng)
    anchors, owner = _regions(planner, places, start_cells, len(start_xy))
    order = rng.permutation(len(start_xy))
    tours = []
    for r in range(len(start_xy)):
        anchor = anchors[order[r] % len(anchors)]
        tours.append(
            _tour(
                planner, places, owner, anchor, start_xy[r], start_cells[r], length_m, place_spacing
            )
        )
    return tours


def _places(
    planner: _GridPlanner, reach: NDArray[np.bool_], spacing: float, rng: np.random.Generator
) -> NDArray[np.int64]:
    """One place per spacing x spacing block (randomly offset lattice): its reachable cell
    with the most clearance."""
    cells = np.flatnonzero(reach)
    b = max(1, int(round(spacing / planner.world.resolution)))
    off = rng.integers(0, b, 2)
    iy, ix = cells // planner.w, cells % planner.w
    block = ((iy + off[1]) // b) * (planner.w // b + 2) + (ix + off[0]) // b
    order = np.lexsort((-planner.field.ravel()[cells], block))
    first = np.r_[True, block[order][1:] != block[order][:-1]]
    return cells[order[first]]


def _regions(
    planner: _GridPlanner, places: NDArray[np.int64], start_cells: NDArray[np.int64], n: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Farthest-point anchors (indices into places) and each place's nearest anchor."""
    planner.run(start_cells)
    dmin = planner.dist[places]
    anchors: list[int] = []
    dists: list[NDArray[np.float64]] = []
    for _ in range(n):
        score = np.where(np.isfinite(dmin), dmin, -1.0)
        k = int(np.argmax(score))
        if score[k] <= 0.0 and anchors:
            break
        anchors.append(k)
        planner.run([places[k]])
        d = planner.dist[places]
        dists.append(d)
        dmin = np.minimum(dmin, d)
    owner = np.argmin(np.stack(dists), axis=0)
    return np.array(anchors, dtype=np.int64), np.asarray(owner, dtype=np.int64)


def _tour(
    planner: _GridPlanner,
    places: NDArray[np.int64],
    owner: NDArray[np.int64],
    anchor: int,
    start_xy: NDArray[np.float64],
    start: int,
    length_m: float,
    spacing: float,
) -> NDArray[np.float64]:
    """One robot's waypoints: legs from place to place, each simplified by line of sight,
    until the waypoint polyline is length_m long (cut there) or nothing is left to reach."""
    res = planner.world.resolution
    tree = cKDTree(planner.centres(places))
    visit_r = 0.75 * spacing
    visited = np.zeros(len(places), dtype=bool)
    excluded = np.zeros(len(places), dtype=bool)  # not reachable from this robot
    region = owner == owner[anchor]
    waypoints = [start_xy[None]]
    total, cur, legs, pass_len = 0.0, start, 0, 0.0
    max_legs = 4 * len(places) + 10

    def mark(cells: NDArray[np.int64]) -> None:
        for hit in tree.query_ball_point(planner.centres(cells), visit_r):
            visited[hit] = True

    mark(np.array([start]))
    visited[anchor] = False
    while total < length_m and legs < max_legs:
        legs += 1
        goal = -1
        wanted = [np.array([anchor])] if legs == 1 else []
        wanted += [
            np.flatnonzero(~visited & ~excluded & region),
            np.flatnonzero(~visited & ~excluded),
        ]
        for cand in wanted:
            if cand.size == 0:
                continue
            targets = np.zeros(planner.trav.size, dtype=bool)
            targets[places[cand]] = True
            goal = planner.run([cur], targets)
            if goal >= 0:
                break
            excluded[cand] = True
        if goal < 0:  # everything reachable was seen: start another pass, or stop
            if pass_len <= 0.0:
                break
            visited[:] = False
            mark(np.array([cur]))
            pass_len = 0.0
            continue
        cells = planner.path_to(goal)
        mark(cells)
        visited[tree.query_ball_point(planner.centres([goal])[0], res)] = True
        pts = planner.centres(cells)
        if legs == 1:
            pts = np.vstack([start_xy, pts])
        leg = _shortcut_points(planner, pts)[1:]
        if len(leg):
            step = float(np.sum(np.hypot(*np.diff(np.vstack([waypoints[-1][-1:], leg]), axis=0).T)))
            waypoints.append(leg)
            total += step
            pass_len += step
        cur = goal
    return _cut(np.vstack(waypoints), length_m)


def _shortcut_points(planner: _GridPlanner, pts: NDArray[np.float64]) -> NDArray[np.float64]:
    """Line-of-sight simplification of a map-frame polyline on the planning clearance."""
    g = np.ascontiguousarray((pts - planner.world.origin_xy) / planner.world.resolution)
    max_len = _MAX_SEGMENT_M / planner.world.resolution
    return pts[_shortcut(g, planner.field, planner.thresh, max_len)]


def _cut(pts: NDArray[np.float64], length_m: float) -> NDArray[np.float64]:
    """The polyline's first length_m metres (the last segment shortened)."""
    seg = np.hypot(*np.diff(pts, axis=0).T)
    cum = np.r_[0.0, np.cumsum(seg)]
    if cum[-1] <= length_m:
        return pts
    k = int(np.searchsorted(cum, length_m, side="right"))  # cum[k-1] <= L < cum[k]
    t = (length_m - cum[k - 1]) / seg[k - 1]
    end = pts[k - 1] + t * (pts[k] - pts[k - 1])
    return np.vstack([pts[:k], end]) if t > 1e-9 else pts[:k].copy()
