"""How soon any team could know 95 % of a world: a floor under `time_to_95_s`.

A cell is known once some drone has had it in line of sight (within laser range). A
drone that has flown `d` metres from the start can only have looked from places at
most `d` away by the shortest way (with its collision disc's clearance). So however
many drones fly and however they split up, no cell is known before the travel
distance of the nearest place that sees it: `first_seen_m`, one pass over every
viewpoint. The fraction `fraction` of the reachable free area is not known before the
distance that many cells are first seen within, flown at `speed` from rest at
`accel`. The map's own lag (scans to keyframes to the base station, a map published
each sync) comes on top, and the team size does not enter: the floor is tight where
the mission is one long way (bshape), loose where it is many (random floor plans).

Sampled: viewpoints on a `viewpoint_m` grid, `rays` beams each (360 deg: a drone can
turn), so a cell seen only from between the samples may count as seen a little
later; treat the result as a bound to within ~`viewpoint_m` of travel.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from basestation.travel_distance import travel_distances
from common.map_io import GridMap
from common.metrics import reachable_free


def first_seen_m(
    world: GridMap,
    starts_xy: ArrayLike,
    radius_m: float = 0.25,
    range_m: float = 30.0,
    viewpoint_m: float = 0.4,
    rays: int = 720,
) -> NDArray[np.float64]:
    """Travel distance (m) from the nearest start at which each reachable free cell is
    first in line of sight (`inf`: never), one value per cell of
    `reachable_free(world, starts_xy)` in `np.nonzero` order."""
    region = reachable_free(world, starts_xy)
    occupied = world.occupied_mask()
    clear = ndimage.distance_transform_edt(~occupied) * world.resolution > radius_m
    step = max(1, int(round(viewpoint_m / world.resolution)))
    iy, ix = np.nonzero((region & clear)[step // 2 :: step, step // 2 :: step])
    cells = np.column_stack([ix, iy]) * step + step // 2
    starts = np.asarray(starts_xy, dtype=np.float64).reshape(-1, 2)
    views = np.vstack([starts, world.cell_to_world(cells)])
    dist = travel_distances(world, starts, views, radius_m).min(axis=0)
    dist[: len(starts)] = 0.0
    order = np.argsort(dist)
    order = order[np.isfinite(dist[order])]
    h, w = occupied.shape
    seen = np.full((h, w), np.inf)
    angles = np.linspace(0.0, 2.0 * np.pi, rays, endpoint=False)
    reach = min(range_m, float(np.hypot(h, w)) * world.resolution)
    s = np.arange(0.0, reach, world.resolution)
    dx, dy = np.cos(angles)[:, None] * s, np.sin(angles)[:, None] * s  # (rays, steps)
    o = np.asarray(world.origin[:2])
    for k in order:
        cx = np.floor((views[k, 0] + dx - o[0]) / world.resolution).astype(np.int64)
        cy = np.floor((views[k, 1] + dy - o[1]) / world.resolution).astype(np.int64)
        inside = (cx >= 0) & (cy >= 0) & (cx < w) & (cy < h)
        cx, cy = np.clip(cx, 0, w - 1), np.clip(cy, 0, h - 1)
        stop = occupied[cy, cx] | ~inside
        first = np.where(stop.any(axis=1), stop.argmax(axis=1), len(s))
        ray_cells = np.arange(len(s))[None, :] < first[:, None]
        vy, vx = cy[ray_cells], cx[ray_cells]
        seen[vy, vx] = np.minimum(seen[vy, vx], dist[k])
    ry, rx = np.nonzero(region)
    return seen[ry, rx]


def time_to_fraction_bound_s(
    world: GridMap,
    starts_xy: ArrayLike,
    fraction: float = 0.95,
    speed: float = 1.0,
    accel: float = 1.0,
    **kwargs: float,
) -> float | None:
    """Sim time (s) before which no team starting at `starts_xy` can know `fraction`
    of the reachable free area (None: never, from any place reachable)."""
    d = np.sort(first_seen_m(world, starts_xy, **kwargs))
    need = int(np.ceil(fraction * len(d))) - 1
    if need < 0 or not np.isfinite(d[need]):
        return None
    return float(travel_time_s(d[need], speed, accel))


def travel_time_s(distance_m: float, speed: float, accel: float) -> float:
    """Time to fly `distance_m` from rest at most at `speed`, accelerating at `accel`."""
    ramp = speed * speed / accel  # m to reach speed
    if distance_m <= ramp / 2.0:
        return float(np.sqrt(2.0 * distance_m / accel))
    return float(speed / accel + (distance_m - ramp / 2.0) / speed)
