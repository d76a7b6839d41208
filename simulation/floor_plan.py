"""Floor-plan building blocks for the simulator's worlds (see `world_generator`): a plan
in building metres as a union of FREE shapes plus solid boxes, its rasterization into
a map_server grid (walls = non-free cells within `wall_m` of free space, unknown
beyond), furniture placement, and `validate_world` (one free region, passable for a
drone of radius 0.25 m with a 0.1 m margin)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from common.errors import CollabSlamError
from common.map_io import GridMap

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
class Plan:
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


def rasterize(plan: Plan, resolution: float) -> GridMap:
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


def furnish(plan: Plan, rng: np.random.Generator, per_room: float, resolution: float) -> None:
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
    free = rasterize(plan, resolution).free_mask()

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
