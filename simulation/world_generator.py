"""Procedural floor plans for the simulator, and the shipped worlds.

A plan is drawn in "building metres" (x right, y up, the building's lower-left
corner at (0, 0)) as a union of FREE shapes: rectangles and thick polylines.
Walls are then everything within `wall_m` of free space that is not free, so
two free rectangles left `partition_m` apart get a partition wall between them,
and a small free rectangle across that gap is a door. What lies further away
(outside the building, solid blocks inside it) stays UNKNOWN (-1), like a
prior floor plan. Solid boxes (pillars, furniture) are occupied cells inside
free space. The grid origin puts building (0, 0) at map (0, 0).

Shipped worlds (seed 002 experiments): `bshape` (Fig. 8), `rooms15` (Fig. 10),
`floor30x25` (Fig. 9). `random_floor` makes rooms-and-corridors floors that no
test has seen. Every generated world passes `validate_world`: one 4-connected
free region, and one region for the centre of a drone of radius 0.25 m with a
0.1 m margin.

CLI: `python -m simulation.world_generator --out simulation/worlds` rewrites the
shipped worlds.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from common.errors import CollabSlamError, ConfigError
from common.logging_setup import setup_logging
from common.map_io import GridMap, write_map

logger = logging.getLogger(__name__)

__all__ = [
    "SHIPPED_KINDS",
    "generate_world",
    "random_floor",
    "validate_world",
    "main",
]

SHIPPED_KINDS = ("bshape", "rooms15", "floor30x25")
RESOLUTION_M = 0.05  # m per cell of every shipped world
WALL_M = 0.15  # m, outer wall thickness
PARTITION_M = 0.10  # m, gap left between two free rectangles = interior wall thickness
DOOR_M = 1.2  # m, door opening (a 0.5 m drone passes with 0.35 m to spare)
MARGIN_M = 1.0  # m of unknown around the building
DRONE_RADIUS_M = 0.25
PASS_MARGIN_M = 0.1

Rect = tuple[float, float, float, float]  # (x0, y0, x1, y1), building metres


@dataclass
class _Plan:
    """Free shapes and solid boxes of a floor, in building metres."""

    width_m: float
    height_m: float
    free_rects: list[Rect] = field(default_factory=list)
    polylines: list[tuple[NDArray[np.float64], float]] = field(default_factory=list)
    solids: list[Rect] = field(default_factory=list)
    rooms: list[Rect] = field(default_factory=list)  # where furniture may go
    doors: list[Rect] = field(default_factory=list)  # openings furniture keeps away from

    def room(self, x0: float, y0: float, x1: float, y1: float) -> None:
        self.free_rects.append((x0, y0, x1, y1))
        self.rooms.append((x0, y0, x1, y1))

    def door_x(self, x_wall: float, yc: float, width: float = DOOR_M) -> None:
        """Door through the vertical partition [x_wall, x_wall + PARTITION_M] centred at yc."""
        self.opening((x_wall, yc - width / 2, x_wall + PARTITION_M, yc + width / 2))

    def door_y(self, y_wall: float, xc: float, width: float = DOOR_M) -> None:
        """Door through the horizontal partition [y_wall, y_wall + PARTITION_M] centred at xc."""
        self.opening((xc - width / 2, y_wall, xc + width / 2, y_wall + PARTITION_M))

    def opening(self, rect: Rect) -> None:
        self.free_rects.append(rect)
        self.doors.append(rect)


class _Raster:
    """Cell-index conversion for a plan drawn with MARGIN_M of unknown around it."""

    def __init__(self, width_m: float, height_m: float, resolution: float, margin: float) -> None:
        self.res = resolution
        self.margin = margin
        self.w = int(round((width_m + 2 * margin) / resolution))
        self.h = int(round((height_m + 2 * margin) / resolution))

    def idx(self, v: float) -> int:
        return int(round((v + self.margin) / self.res))

    def rect_mask(self, rects: Sequence[Rect]) -> NDArray[np.bool_]:
        mask = np.zeros((self.h, self.w), dtype=bool)
        for x0, y0, x1, y1 in rects:
            ix0, ix1 = max(self.idx(x0), 0), min(self.idx(x1), self.w)
            iy0, iy1 = max(self.idx(y0), 0), min(self.idx(y1), self.h)
            mask[iy0:iy1, ix0:ix1] = True
        return mask

    def polyline_mask(self, points: NDArray[np.float64], width: float) -> NDArray[np.bool_]:
        """Cells whose centre lies within width/2 of the polyline (round joins and caps)."""
        xs = (np.arange(self.w) + 0.5) * self.res - self.margin
        ys = (np.arange(self.h) + 0.5) * self.res - self.margin
        px, py = np.meshgrid(xs, ys)
        best = np.full(px.shape, np.inf)
        for a, b in zip(points[:-1], points[1:], strict=True):
            d = b - a
            t = ((px - a[0]) * d[0] + (py - a[1]) * d[1]) / max(float(d @ d), 1e-12)
            t = np.clip(t, 0.0, 1.0)
            best = np.minimum(best, np.hypot(px - a[0] - t * d[0], py - a[1] - t * d[1]))
        return best <= width / 2


def _rasterize(plan: _Plan, resolution: float) -> GridMap:
    ras = _Raster(plan.width_m, plan.height_m, resolution, MARGIN_M)
    free = ras.rect_mask(plan.free_rects)
    for pts, width in plan.polylines:
        free |= ras.polyline_mask(pts, width)
    k = max(1, int(round(WALL_M / resolution)))
    walls = ndimage.binary_dilation(free, structure=np.ones((2 * k + 1, 2 * k + 1), bool))
    data = np.full((ras.h, ras.w), -1, dtype=np.int8)
    data[walls] = 100
    data[free] = 0
    data[ras.rect_mask(plan.solids) & free] = 100
    return GridMap(data=data, resolution=resolution, origin=(-MARGIN_M, -MARGIN_M, 0.0))


# ------------------------------------------------------------------------------ validation


def _passable(free: NDArray[np.bool_], resolution: float, radius: float) -> NDArray[np.bool_]:
    """Free cells whose centre is >= radius from every non-free cell's boundary."""
    edt = ndimage.distance_transform_edt(np.pad(free, 1))[1:-1, 1:-1]
    return free & (edt * resolution - 0.5 * resolution >= radius)


def _n_components(mask: NDArray[np.bool_]) -> int:
    return int(ndimage.label(mask)[1])


def validate_world(
    grid: GridMap, drone_radius: float = DRONE_RADIUS_M, margin: float = PASS_MARGIN_M
) -> None:
    """Raise CollabSlamError unless the free cells form one 4-connected region and the
    cells a drone centre can reach (>= drone_radius + margin from any non-free cell)
    form one region too (no door too narrow, no unreachable room)."""
    free = grid.free_mask()
    n_free = _n_components(free)
    if n_free != 1:
        raise CollabSlamError(f"world has {n_free} free regions, expected exactly 1")
    n_pass = _n_components(_passable(free, grid.resolution, drone_radius + margin))
    if n_pass != 1:
        raise CollabSlamError(
            f"world has {n_pass} regions passable for a drone of radius {drone_radius} m "
            f"(+{margin} m), expected exactly 1"
        )


# ------------------------------------------------------------------------------ furniture


def _furnish(plan: _Plan, rng: np.random.Generator, per_room: float, resolution: float) -> None:
    """Put boxes (desks, cabinets) against room walls, keeping the world valid."""
    n = int(round(per_room * len(plan.rooms)))
    boxes: list[Rect] = []
    for _ in range(n):
        x0, y0, x1, y1 = plan.rooms[int(rng.integers(len(plan.rooms)))]
        bw, bd = float(rng.uniform(0.6, 1.6)), float(rng.uniform(0.4, 0.8))
        side = int(rng.integers(4))
        if side in (0, 1):  # against the bottom / top wall
            if x1 - x0 < bw + 1.0:
                continue
            bx = float(rng.uniform(x0 + 0.3, x1 - 0.3 - bw))
            by = y0 if side == 0 else y1 - bd
            boxes.append((bx, by, bx + bw, by + bd))
        else:  # against the left / right wall
            if y1 - y0 < bw + 1.0:
                continue
            by = float(rng.uniform(y0 + 0.3, y1 - 0.3 - bw))
            bx = x0 if side == 2 else x1 - bd
            boxes.append((bx, by, bx + bd, by + bw))
    keep_out = 0.8  # m between a box and any door
    boxes = [
        b
        for b in boxes
        if not any(
            b[0] < d[2] + keep_out
            and d[0] < b[2] + keep_out
            and b[1] < d[3] + keep_out
            and d[1] < b[3] + keep_out
            for d in plan.doors
        )
    ]
    ras = _Raster(plan.width_m, plan.height_m, resolution, MARGIN_M)
    free = _rasterize(plan, resolution).free_mask()

    def valid(mask: NDArray[np.bool_]) -> bool:
        return (
            _n_components(mask) == 1
            and _n_components(_passable(mask, resolution, DRONE_RADIUS_M + PASS_MARGIN_M)) == 1
        )

    def add(group: list[Rect]) -> None:
        """Accept the whole group if the world stays valid, else split it (few checks when
        most boxes are fine; deterministic)."""
        nonlocal free
        if not group:
            return
        trial = free & ~ras.rect_mask(group)
        if valid(trial):
            plan.solids.extend(group)
            free = trial
        elif len(group) > 1:
            add(group[: len(group) // 2])
            add(group[len(group) // 2 :])

    add(boxes)


# ------------------------------------------------------------------------------ shipped plans


def _bshape_plan() -> _Plan:
    """Seed 002 Fig. 8: an upright letter B, 13.5 x 20 m, 2.5 m corridors looping around
    two solid blocks; the spine and the middle bar are shared by both loops."""
    p = _Plan(13.5, 20.0)
    p.free_rects += [
        (0.0, 0.0, 2.5, 20.0),  # spine
        (0.0, 17.5, 9.0, 20.0),  # top bar
        (0.0, 8.75, 10.0, 11.25),  # middle bar
        (0.0, 0.0, 9.5, 2.5),  # bottom bar
    ]
    upper = [(8.0, 18.75), (9.5, 18.75), (11.25, 17.0), (11.25, 12.75), (9.5, 10.0), (8.0, 10.0)]
    lower = [(8.0, 10.0), (10.5, 10.0), (12.25, 8.25), (12.25, 3.0), (10.5, 1.25), (8.0, 1.25)]
    p.polylines += [(np.array(upper), 2.5), (np.array(lower), 2.5)]
    # Shallow alcoves (1 m wide, 0.5 m deep) break the symmetry of the long corridors.
    p.free_rects += [(-0.5, 4.0, 0.0, 5.0), (-0.5, 14.0, 0.0, 15.0), (5.0, 20.0, 6.0, 20.5)]
    p.free_rects += [(5.5, -0.5, 6.5, 0.0), (2.5, 13.0, 3.0, 14.2), (6.0, 2.5, 7.0, 3.0)]
    return p


def _rooms15_plan() -> _Plan:
    """Seed 002 Fig. 10: a 15 x 15 m room set, six rooms off a 2 m corridor."""
    p = _Plan(15.0, 15.0)
    p.free_rects.append((0.0, 6.5, 15.0, 8.5))  # corridor
    top, bottom = (8.6, 15.0), (0.0, 6.4)
    for x0, x1 in ((0.0, 4.45), (4.55, 9.45), (9.55, 15.0)):
        p.room(x0, top[0], x1, top[1])
    for x0, x1 in ((0.0, 5.95), (6.05, 9.95), (10.05, 15.0)):
        p.room(x0, bottom[0], x1, bottom[1])
    for xc in (2.0, 7.5, 11.0):
        p.door_y(8.5, xc)  # corridor -> top rooms
    for xc in (4.5, 8.3, 13.5):
        p.door_y(6.4, xc)  # corridor -> bottom rooms
    p.door_x(4.45, 13.0)  # top-left <-> top-middle
    p.door_x(9.95, 2.0)  # bottom-middle <-> bottom-right
    return p


def _floor30x25_plan() -> _Plan:
    """Seed 002 Fig. 9: a 30 x 25 m office floor: a corridor loop, offices, an open hall
    with pillars and two labs."""
    p = _Plan(30.0, 25.0)
    p.free_rects += [
        (0.0, 11.5, 21.0, 13.5),  # main corridor (H)
        (19.0, 0.0, 21.0, 25.0),  # cross corridor (V)
        (0.0, 5.0, 19.0, 7.0),  # lower corridor (L)
        (0.0, 7.0, 2.0, 11.5),  # left connector closing the loop H-V-L
    ]
    # Offices above H: two deep labs and two split offices.
    p.room(0.0, 13.6, 4.65, 25.0)
    p.room(4.75, 13.6, 9.45, 19.2)
    p.room(4.75, 19.3, 9.45, 25.0)
    p.room(9.55, 13.6, 14.2, 19.2)
    p.room(9.55, 19.3, 14.2, 25.0)
    p.room(14.3, 13.6, 18.9, 25.0)
    for xc in (2.3, 7.0, 12.0, 16.5):
        p.door_y(13.5, xc)
    p.door_y(19.2, 6.0)
    p.door_y(19.2, 12.8)
    p.door_x(18.9, 22.0)  # top-right office -> V corridor
    # Offices between L and H (doors alternate).
    p.room(2.1, 7.1, 7.7, 11.4)
    p.room(7.8, 7.1, 13.3, 11.4)
    p.room(13.4, 7.1, 18.9, 11.4)
    p.door_y(11.4, 5.0)
    p.door_y(7.0, 10.5)
    p.door_y(11.4, 16.0)
    p.door_x(7.7, 9.0)
    # Offices below L.
    for i, (x0, x1) in enumerate(((0.0, 4.65), (4.75, 9.45), (9.55, 14.2), (14.3, 18.9))):
        p.room(x0, 0.0, x1, 4.9)
        p.door_y(4.9, (x0 + x1) / 2 + (0.8 if i % 2 else -0.8))
    # Open hall right of V with a wide opening and pillars.
    p.room(21.1, 13.6, 30.0, 25.0)
    p.door_x(21.0, 18.0, width=4.0)
    for px in (24.0, 27.2):
        for py in (16.5, 19.5, 22.5):
            p.solids.append((px - 0.2, py - 0.2, px + 0.2, py + 0.2))
    # Two labs below the hall, each reachable from V, joined by an internal door.
    p.room(21.1, 7.1, 30.0, 13.5)
    p.room(21.1, 0.0, 30.0, 7.0)
    p.door_x(21.0, 10.0)
    p.door_x(21.0, 3.0)
    p.door_y(7.0, 27.0)
    p.door_y(13.5, 28.5)  # lab -> hall
    return p


# ------------------------------------------------------------------------------ random floors


@dataclass
class _Node:
    rect: tuple[int, int, int, int]  # cells, half-open [x0, x1) x [y0, y1)
    corridor: bool


def _bsp(
    rect: tuple[int, int, int, int],
    rng: np.random.Generator,
    depth: int,
    out: list[_Node],
    p: dict[str, int],
) -> None:
    x0, y0, x1, y1 = rect
    w, h = x1 - x0, y1 - y0
    if w <= p["max_room"] and h <= p["max_room"]:
        out.append(_Node(rect, False))
        return
    if depth >= 2 and w <= 2 * p["max_room"] and h <= 2 * p["max_room"] and rng.random() < 0.12:
        out.append(_Node(rect, False))  # an open hall
        return
    vertical = w >= h  # split line is vertical (cuts x)
    length = w if vertical else h
    with_corridor = depth < 3 and length >= 2 * p["min_room"] + p["corridor"] + 2 * p["gap"]
    with_corridor = with_corridor and (depth == 0 or rng.random() < 0.5)
    middle = p["corridor"] + 2 * p["gap"] if with_corridor else p["gap"]
    lo, hi = p["min_room"], length - p["min_room"] - middle
    if hi < lo:
        out.append(_Node(rect, False))
        return
    s = int(rng.integers(lo, hi + 1))
    a0 = (x0 if vertical else y0) + s  # end of the first half
    b0 = a0 + middle  # start of the second half
    if vertical:
        first, second = (x0, y0, a0, y1), (b0, y0, x1, y1)
        corr = (a0 + p["gap"], y0, b0 - p["gap"], y1)
    else:
        first, second = (x0, y0, x1, a0), (x0, b0, x1, y1)
        corr = (x0, a0 + p["gap"], x1, b0 - p["gap"])
    if with_corridor:
        out.append(_Node(corr, True))
    _bsp(first, rng, depth + 1, out, p)
    _bsp(second, rng, depth + 1, out, p)


def _shared_wall(
    a: tuple[int, int, int, int], b: tuple[int, int, int, int], gap: int
) -> tuple[int, int, int, int] | None:
    """The gap rectangle between two nodes separated by exactly `gap` cells, or None."""
    for axis in (0, 1):
        o = 1 - axis
        lo, hi = max(a[o], b[o]), min(a[o + 2], b[o + 2])
        if hi <= lo:
            continue
        for p, q in ((a, b), (b, a)):
            if q[axis] - p[axis + 2] == gap:
                g0, g1 = p[axis + 2], q[axis]
                return (g0, lo, g1, hi) if axis == 0 else (lo, g0, hi, g1)
    return None


class _UnionFind:
    def __init__(self, n: int) -> None:
        self.parent = list(range(n))

    def find(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def union(self, i: int, j: int) -> bool:
        ri, rj = self.find(i), self.find(j)
        if ri == rj:
            return False
        self.parent[ri] = rj
        return True


def random_floor(
    seed: int,
    width_m: float = 24.0,
    height_m: float = 18.0,
    *,
    resolution: float = RESOLUTION_M,
    corridor_m: float = 2.0,
    min_room_m: float = 3.0,
    max_room_m: float = 7.0,
    void_fraction: float = 0.15,
    loop_fraction: float = 0.2,
    furniture_per_room: float = 0.7,
) -> GridMap:
    """A random rooms-and-corridors floor of about width_m x height_m (m), deterministic
    per seed: binary space partitioning with corridors at the first levels, a random
    spanning tree of doors plus a few extra doors (loops), some rooms left out as solid
    blocks (irregular outline), furniture against the walls. Always valid
    (`validate_world`)."""
    if not (width_m >= 2 * min_room_m and height_m >= 2 * min_room_m):
        raise ConfigError(
            f"random_floor: width_m and height_m must be >= {2 * min_room_m} m, "
            f"got {width_m} x {height_m}"
        )
    rng = np.random.default_rng(seed)
    c = 1.0 / resolution
    p = {
        "corridor": int(round(corridor_m * c)),
        "gap": max(1, int(round(PARTITION_M * c))),
        "min_room": int(round(min_room_m * c)),
        "max_room": int(round(max_room_m * c)),
    }
    door = int(round(DOOR_M * c))
    jamb = int(round(0.3 * c))
    nodes: list[_Node] = []
    _bsp((0, 0, int(round(width_m * c)), int(round(height_m * c))), rng, 0, nodes, p)

    walls: list[tuple[int, int, tuple[int, int, int, int]]] = []
    for i in range(len(nodes)):
        for j in range(i + 1, len(nodes)):
            g = _shared_wall(nodes[i].rect, nodes[j].rect, p["gap"])
            if g is not None and max(g[2] - g[0], g[3] - g[1]) >= door + 2 * jamb:
                walls.append((i, j, g))

    # Leave some rooms out (solid blocks) while the rest stays connected.
    alive = np.ones(len(nodes), dtype=bool)
    rooms = [i for i, n in enumerate(nodes) if not n.corridor]
    for i in rng.permutation(rooms)[: int(void_fraction * len(rooms))]:
        alive[i] = False
        if not _connected(alive, walls):
            alive[i] = True
    # If the door graph is not connected, keep its largest part.
    uf = _UnionFind(len(nodes))
    for i, j, _ in walls:
        if alive[i] and alive[j]:
            uf.union(i, j)
    roots = [uf.find(i) for i in range(len(nodes))]
    counts: dict[int, float] = {}
    for i in np.flatnonzero(alive):
        r = roots[i]
        counts[r] = counts.get(r, 0.0) + _area(nodes[i].rect)
    keep_root = max(counts, key=lambda r: counts[r])
    alive &= np.array([r == keep_root for r in roots])

    # Doors: corridor-corridor walls open fully; then a random spanning tree; then loops.
    openings: list[tuple[int, int, int, int]] = []
    uf = _UnionFind(len(nodes))
    order = rng.permutation(len(walls))
    live_walls = [walls[k] for k in order if alive[walls[k][0]] and alive[walls[k][1]]]
    live_walls.sort(key=lambda w: -(nodes[w[0]].corridor + nodes[w[1]].corridor))
    for i, j, g in live_walls:
        both = nodes[i].corridor and nodes[j].corridor
        if both:
            uf.union(i, j)
            openings.append(g)
        elif uf.union(i, j) or rng.random() < loop_fraction:
            openings.append(_door_in(g, door, jamb, rng))

    plan = _Plan(width_m, height_m)
    cell = resolution
    for i in np.flatnonzero(alive):
        x0, y0, x1, y1 = nodes[i].rect
        rect = (x0 * cell, y0 * cell, x1 * cell, y1 * cell)
        plan.free_rects.append(rect)
        if not nodes[i].corridor:
            plan.rooms.append(rect)
            _maybe_pillars(plan, rect, rng)
    for x0, y0, x1, y1 in openings:
        plan.opening((x0 * cell, y0 * cell, x1 * cell, y1 * cell))
    _furnish(plan, rng, furniture_per_room, resolution)
    grid = _rasterize(plan, resolution)
    validate_world(grid)
    logger.debug(
        "random floor seed %d: %d rooms, %d openings", seed, len(plan.rooms), len(openings)
    )
    return grid


def _area(r: tuple[int, int, int, int]) -> float:
    return float((r[2] - r[0]) * (r[3] - r[1]))


def _connected(alive: NDArray[np.bool_], walls: list[tuple[int, int, object]]) -> bool:
    uf = _UnionFind(len(alive))
    for i, j, _ in walls:
        if alive[i] and alive[j]:
            uf.union(i, j)
    roots = {uf.find(i) for i in np.flatnonzero(alive)}
    return len(roots) <= 1


def _door_in(
    g: tuple[int, int, int, int], door: int, jamb: int, rng: np.random.Generator
) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = g
    if x1 - x0 >= y1 - y0:  # horizontal wall: the door runs along x
        s = int(rng.integers(x0 + jamb, x1 - jamb - door + 1))
        return (s, y0, s + door, y1)
    s = int(rng.integers(y0 + jamb, y1 - jamb - door + 1))
    return (x0, s, x1, s + door)


def _maybe_pillars(plan: _Plan, rect: Rect, rng: np.random.Generator) -> None:
    """Pillars on a 3-4 m lattice in rooms larger than 9 m on a side."""
    x0, y0, x1, y1 = rect
    if min(x1 - x0, y1 - y0) < 9.0:
        return
    step = float(rng.uniform(3.0, 4.0))
    for px in np.arange(x0 + step, x1 - 1.5, step):
        for py in np.arange(y0 + step, y1 - 1.5, step):
            plan.solids.append((px - 0.2, py - 0.2, px + 0.2, py + 0.2))


# ------------------------------------------------------------------------------ public API


def generate_world(
    kind: str,
    seed: int = 0,
    *,
    resolution: float = RESOLUTION_M,
    width_m: float = 24.0,
    height_m: float = 18.0,
    furniture_per_room: float = 0.7,
) -> GridMap:
    """A world of `kind` ('bshape', 'rooms15', 'floor30x25' or 'random'), deterministic per
    seed. For the shipped kinds the layout is fixed and the seed only places furniture
    (bshape has none); width_m and height_m are used by 'random' only."""
    if not (resolution > 0.0 and math.isfinite(resolution)):
        raise ConfigError(f"resolution must be > 0, got {resolution}")
    if kind == "random":
        return random_floor(
            seed, width_m, height_m, resolution=resolution, furniture_per_room=furniture_per_room
        )
    plans = {"bshape": _bshape_plan, "rooms15": _rooms15_plan, "floor30x25": _floor30x25_plan}
    if kind not in plans:
        raise ConfigError(f"unknown world kind {kind!r}; expected one of {[*plans, 'random']}")
    plan = plans[kind]()
    if plan.rooms and furniture_per_room > 0.0:
        _furnish(plan, np.random.default_rng(seed), furniture_per_room, resolution)
    grid = _rasterize(plan, resolution)
    validate_world(grid)
    return grid


def main(argv: Sequence[str] | None = None) -> int:
    """Regenerate the shipped worlds (map_server YAML + PGM) into --out."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--kinds", nargs="+", default=list(SHIPPED_KINDS), help="worlds to write")
    parser.add_argument("--seed", type=int, default=0, help="furniture / random-floor seed")
    args = parser.parse_args(argv)
    setup_logging("INFO", "world_generator")
    try:
        for kind in args.kinds:
            grid = generate_world(kind, args.seed)
            name = kind if kind != "random" else f"random_{args.seed}"
            write_map(grid, args.out / f"{name}.yaml")
            free_m2 = np.count_nonzero(grid.free_mask()) * grid.resolution**2
            logger.info(
                "wrote %s: %d x %d cells (%.1f x %.1f m), %.0f m^2 free",
                args.out / f"{name}.yaml",
                grid.width,
                grid.height,
                grid.width * grid.resolution,
                grid.height * grid.resolution,
                free_m2,
            )
    except CollabSlamError as exc:
        logger.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
