"""Exact 2-D ray casting on an occupancy grid (Amanatides-Woo grid traversal).

Conventions (those of `common.map_io.GridMap`): `occupied[iy, ix]` is cell
(ix, iy), row 0 is the lowest y, and `origin_xy` is the map-frame position of
the lower-left corner of cell (0, 0). A beam returns the distance (m) from the
sensor to the point where it ENTERS the first occupied cell, i.e. the exact
distance to the cell's boundary, not to its centre. A sensor inside an
occupied cell reads 0. Beams that hit nothing within `range_max`, or that leave
the grid first, read +inf. The area outside the grid is empty.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError

__all__ = ["cast_rays"]


@njit(cache=True)
def _cast_kernel(
    occupied: NDArray[np.bool_],
    gx: float,
    gy: float,
    yaw: float,
    angles: NDArray[np.float64],
    max_cells: float,
    out: NDArray[np.float32],
    resolution: float,
) -> None:
    """One DDA traversal per beam; everything in cell units until the final scale."""
    h, w = occupied.shape
    inf = np.float32(np.inf)
    for k in range(angles.shape[0]):
        a = yaw + angles[k]
        dx = math.cos(a)
        dy = math.sin(a)
        # Clip the beam [0, max_cells] against the grid box [0, w] x [0, h] (slab method).
        t0 = 0.0
        t1 = max_cells
        if dx != 0.0:
            ta = (0.0 - gx) / dx
            tb = (w - gx) / dx
            t0 = max(t0, min(ta, tb))
            t1 = min(t1, max(ta, tb))
        elif gx < 0.0 or gx >= w:
            out[k] = inf
            continue
        if dy != 0.0:
            ta = (0.0 - gy) / dy
            tb = (h - gy) / dy
            t0 = max(t0, min(ta, tb))
            t1 = min(t1, max(ta, tb))
        elif gy < 0.0 or gy >= h:
            out[k] = inf
            continue
        if t0 > t1:
            out[k] = inf
            continue
        px = gx + t0 * dx
        py = gy + t0 * dy
        ix = min(max(int(math.floor(px)), 0), w - 1)
        iy = min(max(int(math.floor(py)), 0), h - 1)
        if dx > 0.0:
            step_x = 1
            t_max_x = t0 + (ix + 1.0 - px) / dx
            t_delta_x = 1.0 / dx
        elif dx < 0.0:
            step_x = -1
            t_max_x = t0 + (px - ix) / -dx
            t_delta_x = -1.0 / dx
        else:
            step_x = 0
            t_max_x = np.inf
            t_delta_x = np.inf
        if dy > 0.0:
            step_y = 1
            t_max_y = t0 + (iy + 1.0 - py) / dy
            t_delta_y = 1.0 / dy
        elif dy < 0.0:
            step_y = -1
            t_max_y = t0 + (py - iy) / -dy
            t_delta_y = -1.0 / dy
        else:
            step_y = 0
            t_max_y = np.inf
            t_delta_y = np.inf
        t = t0
        result = inf
        while t <= t1:
            if occupied[iy, ix]:
                result = np.float32(t * resolution)
                break
            if t_max_x < t_max_y:
                t = t_max_x
                t_max_x += t_delta_x
                ix += step_x
                if ix < 0 or ix >= w:
                    break
            else:
                t = t_max_y
                t_max_y += t_delta_y
                iy += step_y
                if iy < 0 or iy >= h:
                    break
        out[k] = result


def cast_rays(
    occupied: NDArray[np.bool_],
    resolution: float,
    origin_xy: ArrayLike,
    T_world_sensor: ArrayLike,
    angles: ArrayLike,
    range_max: float,
) -> NDArray[np.float32]:
    """Distances (m) from the sensor to the first occupied cell along each beam.

    occupied: (H, W) bool grid, `occupied[iy, ix]`.
    resolution: m per cell. origin_xy: (x, y) of the lower-left corner of cell (0, 0).
    T_world_sensor: sensor pose [x, y, yaw] in the map frame (m, m, rad).
    angles: (N,) beam angles (rad) in the sensor frame, counter-clockwise from +x.
    range_max: m; hits farther than this read +inf.
    Returns (N,) float32; +inf where no occupied cell lies within range_max on the grid.
    """
    occ = np.ascontiguousarray(occupied, dtype=np.bool_)
    if occ.ndim != 2:
        raise CollabSlamError(f"occupied must be a 2-D (H, W) grid, got shape {occ.shape}")
    if not (resolution > 0.0 and math.isfinite(resolution)):
        raise CollabSlamError(f"resolution must be > 0, got {resolution}")
    if not range_max > 0.0:
        raise CollabSlamError(f"range_max must be > 0, got {range_max}")
    pose = np.asarray(T_world_sensor, dtype=np.float64).reshape(-1)
    if pose.shape != (3,) or not np.all(np.isfinite(pose)):
        raise CollabSlamError(f"T_world_sensor must be 3 finite numbers [x, y, yaw], got {pose}")
    origin = np.asarray(origin_xy, dtype=np.float64).reshape(-1)[:2]
    ang = np.ascontiguousarray(angles, dtype=np.float64).reshape(-1)
    out = np.empty(ang.shape[0], dtype=np.float32)
    gx = (pose[0] - origin[0]) / resolution
    gy = (pose[1] - origin[1]) / resolution
    max_cells = min(float(range_max) / resolution, 1e12)
    _cast_kernel(occ, gx, gy, float(pose[2]), ang, max_cells, out, float(resolution))
    return out
