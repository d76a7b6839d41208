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
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError

__all__ = ["BlockGrid", "block_grid", "cast_rays"]


@njit(cache=True)
def _slab(g, d, n, t0, t1):  # noqa: ANN001, ANN202 (numba kernel)
    """[t0, t1] narrowed to where g + t d (cells along one axis) lies in [0, n]; t0 > t1
    when it never does."""
    if d != 0.0:
        ta = (0.0 - g) / d
        tb = (n - g) / d
        return max(t0, min(ta, tb)), min(t1, max(ta, tb))
    if g < 0.0 or g >= n:
        return 1.0, 0.0
    return t0, t1


@njit(cache=True)
def _clip_beam(gx, gy, dx, dy, w, h, max_cells):  # noqa: ANN001, ANN202 (numba kernel)
    """The stretch [t0, t1] (cells along the beam) of [0, max_cells] inside the grid
    box [0, w] x [0, h] (slab method); t0 > t1 when the beam misses the box."""
    t0, t1 = _slab(gx, dx, w, 0.0, max_cells)
    return _slab(gy, dy, h, t0, t1)


@njit(cache=True)
def _axis_start(p, i, d, t, size):  # noqa: ANN001, ANN202 (numba kernel)
    """One axis of a grid traversal over cells `size` wide, at position p (cells) in
    cell i at beam parameter t, direction component d: (step, t of the next cell
    boundary, t between boundaries)."""
    if d > 0.0:
        return 1, t + ((i + 1) * size - p) / d, size / d
    if d < 0.0:
        return -1, t + (p - i * size) / -d, size / -d
    return 0, np.inf, np.inf


@njit(cache=True)
def _walk(occupied, px, py, dx, dy, t, t1, x_lo, x_hi, y_lo, y_hi):  # noqa: ANN001, ANN202
    """Cell by cell (Amanatides-Woo) from (px, py) (cells) at beam parameter t, inside
    the cells [x_lo, x_hi] x [y_lo, y_hi]: (True, t where the beam enters the first
    occupied cell), or (False, t) once past t1 or out of those cells."""
    ix = min(max(int(math.floor(px)), x_lo), x_hi)
    iy = min(max(int(math.floor(py)), y_lo), y_hi)
    step_x, t_max_x, t_delta_x = _axis_start(px, ix, dx, t, 1)
    step_y, t_max_y, t_delta_y = _axis_start(py, iy, dy, t, 1)
    while t <= t1:
        if occupied[iy, ix]:
            return True, t
        if t_max_x < t_max_y:
            t = t_max_x
            t_max_x += t_delta_x
            ix += step_x
            if ix < x_lo or ix > x_hi:
                break
        else:
            t = t_max_y
            t_max_y += t_delta_y
            iy += step_y
            if iy < y_lo or iy > y_hi:
                break
    return False, t


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
        t0, t1 = _clip_beam(gx, gy, dx, dy, w, h, max_cells)
        if t0 > t1:
            out[k] = inf
            continue
        px = gx + t0 * dx
        py = gy + t0 * dy
        hit, t = _walk(occupied, px, py, dx, dy, t0, t1, 0, w - 1, 0, h - 1)
        out[k] = np.float32(t * resolution) if hit else inf


@njit(cache=True)
def _cast_blocks_kernel(
    occupied: NDArray[np.bool_],
    blocks: NDArray[np.bool_],
    bsize: int,
    gx: float,
    gy: float,
    yaw: float,
    angles: NDArray[np.float64],
    max_cells: float,
    out: NDArray[np.float32],
    resolution: float,
) -> None:
    """Two-level traversal: DDA over bsize x bsize blocks, a fine DDA only inside blocks
    that hold an occupied cell. Same results as `_cast_kernel`."""
    h, w = occupied.shape
    hb, wb = blocks.shape
    inf = np.float32(np.inf)
    for k in range(angles.shape[0]):
        a = yaw + angles[k]
        dx = math.cos(a)
        dy = math.sin(a)
        t0, t1 = _clip_beam(gx, gy, dx, dy, w, h, max_cells)
        if t0 > t1:
            out[k] = inf
            continue
        px = gx + t0 * dx
        py = gy + t0 * dy
        cbx = min(max(int(math.floor(px / bsize)), 0), wb - 1)
        cby = min(max(int(math.floor(py / bsize)), 0), hb - 1)
        cstep_x, ct_max_x, ct_delta_x = _axis_start(px, cbx, dx, t0, bsize)
        cstep_y, ct_max_y, ct_delta_y = _axis_start(py, cby, dy, t0, bsize)
        t = t0
        result = inf
        done = False
        while t <= t1 and not done:
            if blocks[cby, cbx]:
                # Fine DDA restricted to this block's cells, starting at t.
                x_lo = cbx * bsize
                x_hi = min(x_lo + bsize, w) - 1
                y_lo = cby * bsize
                y_hi = min(y_lo + bsize, h) - 1
                qx = gx + t * dx
                qy = gy + t * dy
                done, tt = _walk(occupied, qx, qy, dx, dy, t, t1, x_lo, x_hi, y_lo, y_hi)
                if done:
                    result = np.float32(tt * resolution)
                if done or tt > t1:
                    break
            if ct_max_x < ct_max_y:
                t = ct_max_x
                ct_max_x += ct_delta_x
                cbx += cstep_x
                if cbx < 0 or cbx >= wb:
                    break
            else:
                t = ct_max_y
                ct_max_y += ct_delta_y
                cby += cstep_y
                if cby < 0 or cby >= hb:
                    break
        out[k] = result


@dataclass(frozen=True)
class BlockGrid:
    """Coarse occupancy (any occupied cell in each size x size block) that lets
    `cast_rays` skip empty space; build it once per grid with `block_grid`."""

    blocks: NDArray[np.bool_]  # (ceil(H / size), ceil(W / size))
    size: int
    shape: tuple[int, int]  # (H, W) of the fine grid it was built from


def block_grid(occupied: NDArray[np.bool_], size: int = 8) -> BlockGrid:
    """The BlockGrid of an (H, W) occupancy grid."""
    occ = np.asarray(occupied, dtype=np.bool_)
    if occ.ndim != 2 or size < 1:
        raise CollabSlamError(f"block_grid needs a 2-D grid and size >= 1, got {occ.shape}, {size}")
    h, w = occ.shape
    hb, wb = -(-h // size), -(-w // size)
    padded = np.zeros((hb * size, wb * size), dtype=np.bool_)
    padded[:h, :w] = occ
    blocks = padded.reshape(hb, size, wb, size).any(axis=(1, 3))
    return BlockGrid(np.ascontiguousarray(blocks), int(size), (h, w))


def cast_rays(
    occupied: NDArray[np.bool_],
    resolution: float,
    origin_xy: ArrayLike,
    T_world_sensor: ArrayLike,
    angles: ArrayLike,
    range_max: float,
    blocks: BlockGrid | None = None,
) -> NDArray[np.float32]:
    """Distances (m) from the sensor to the first occupied cell along each beam.

    occupied: (H, W) bool grid, `occupied[iy, ix]`.
    resolution: m per cell. origin_xy: (x, y) of the lower-left corner of cell (0, 0).
    T_world_sensor: sensor pose [x, y, yaw] in the map frame (m, m, rad).
    angles: (N,) beam angles (rad) in the sensor frame, counter-clockwise from +x.
    range_max: m; hits farther than this read +inf.
    blocks: optional `block_grid(occupied)`: same results, several times faster in open
    space (build it once per grid).
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
    if blocks is None:
        _cast_kernel(occ, gx, gy, float(pose[2]), ang, max_cells, out, float(resolution))
        return out
    if blocks.shape != occ.shape:
        raise CollabSlamError(
            f"blocks were built for a {blocks.shape} grid, occupied is {occ.shape}"
        )
    _cast_blocks_kernel(
        occ,
        blocks.blocks,
        blocks.size,
        gx,
        gy,
        float(pose[2]),
        ang,
        max_cells,
        out,
        float(resolution),
    )
    return out
