"""Random rooms-and-corridors floors no test has seen (binary space partition, doors
between neighbouring rooms, optional pillars); every one passes `validate_world`."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from common.errors import ConfigError
from common.map_io import GridMap
from simulation.floor_plan import (
    DOOR_M,
    PARTITION_M,
    RESOLUTION_M,
    Plan,
    Rect,
    furnish,
    rasterize,
    validate_world,
)

logger = logging.getLogger(__name__)


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

    plan = Plan(width_m, height_m)
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
    furnish(plan, rng, furniture_per_room, resolution)
    grid = rasterize(plan, resolution)
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


def _maybe_pillars(plan: Plan, rect: Rect, rng: np.random.Generator) -> None:
    """Pillars on a 3-4 m lattice in rooms larger than 9 m on a side."""
    x0, y0, x1, y1 = rect
    if min(x1 - x0, y1 - y0) < 9.0:
        return
    step = float(rng.uniform(3.0, 4.0))
    for px in np.arange(x0 + step, x1 - 1.5, step):
        for py in np.arange(y0 + step, y1 - 1.5, step):
            plan.solids.append((px - 0.2, py - 0.2, px + 0.2, py + 0.2))


# ------------------------------------------------------------------------------ public API
