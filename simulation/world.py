"""A simulated 2.5-D world: a 2-D floor plan extruded upwards.

The floor plan is a `common.map_io.GridMap` (map_server format). Occupied cells
are walls of unlimited height; free cells are flyable; unknown cells (outside
the building, solid blocks) are neither: the laser passes through them, the
quadrotor may fly over them, but tours and start poses stay on free cells.
The border of the grid counts as a wall for clearance.
"""

from __future__ import annotations

import logging
import math
from functools import cached_property
from pathlib import Path

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from common.errors import ConfigError
from common.map_io import GridMap, read_map
from common.world_files import SHIPPED_WORLDS, SHIPPED_WORLDS_DIR, resolve_world
from simulation.raycast import BlockGrid, block_grid

logger = logging.getLogger(__name__)

__all__ = ["SHIPPED_WORLDS", "SHIPPED_WORLDS_DIR", "World", "resolve_world"]


@njit(cache=True)
def bilinear_at(field: NDArray[np.float64], x: float, y: float) -> float:
    """Bilinear interpolation of a cell-centred (H, W) field at continuous cell
    coordinates (x, y), measured from the lower-left grid corner (cell centres at
    i + 0.5); 0 outside the grid."""
    h, w = field.shape
    if not (x >= 0.0 and x <= w and y >= 0.0 and y <= h):
        return 0.0
    u = min(max(x - 0.5, 0.0), w - 1.0)
    v = min(max(y - 0.5, 0.0), h - 1.0)
    i0 = min(int(u), max(w - 2, 0))
    j0 = min(int(v), max(h - 2, 0))
    i1 = min(i0 + 1, w - 1)
    j1 = min(j0 + 1, h - 1)
    fu = u - i0
    fv = v - j0
    return (1.0 - fv) * ((1.0 - fu) * field[j0, i0] + fu * field[j0, i1]) + fv * (
        (1.0 - fu) * field[j1, i0] + fu * field[j1, i1]
    )


@njit(cache=True)
def sample_kernel(
    field: NDArray[np.float64],
    solid: NDArray[np.bool_],
    gx: NDArray[np.float64],
    gy: NDArray[np.float64],
    out: NDArray[np.float64],
) -> None:
    """`bilinear_at` for each point (gx[k], gy[k]); 0 where the point's cell is `solid`
    or outside the grid."""
    h, w = field.shape
    for k in range(gx.shape[0]):
        x = gx[k]
        y = gy[k]
        if not (x >= 0.0 and x < w and y >= 0.0 and y < h) or solid[int(y), int(x)]:
            out[k] = 0.0
        else:
            out[k] = bilinear_at(field, x, y)


@njit(cache=True)
def exact_clearance_kernel(
    field: NDArray[np.float64],
    occupied: NDArray[np.bool_],
    gx: NDArray[np.float64],
    gy: NDArray[np.float64],
    window: int,
    out: NDArray[np.float64],
) -> None:
    """Distance (cells) from each point (gx[k], gy[k]) to the nearest occupied cell square
    or the grid border: exact when that is < window - 1 cells (all cells within +-window
    are searched), else the interpolated `field` (in cells) but at least window - 1. 0 in
    occupied cells and outside the grid."""
    h, w = occupied.shape
    for k in range(gx.shape[0]):
        x = gx[k]
        y = gy[k]
        if not (x >= 0.0 and x < w and y >= 0.0 and y < h):
            out[k] = 0.0
            continue
        ix = int(x)
        iy = int(y)
        if occupied[iy, ix]:
            out[k] = 0.0
            continue
        best = min(x, w - x, y, h - y)
        for j in range(max(iy - window, 0), min(iy + window + 1, h)):
            dy = max(j - y, y - (j + 1.0), 0.0)
            if dy >= best:
                continue
            for i in range(max(ix - window, 0), min(ix + window + 1, w)):
                if occupied[j, i]:
                    dx = max(i - x, x - (i + 1.0), 0.0)
                    d = math.sqrt(dx * dx + dy * dy)
                    if d < best:
                        best = d
        if best < window - 1:
            out[k] = best
        else:
            out[k] = max(bilinear_at(field, x, y), window - 1.0)


def _clearance_field(obstacle: NDArray[np.bool_], resolution: float) -> NDArray[np.float64]:
    """Per cell: distance (m) from the cell centre to the nearest obstacle cell's boundary
    (centre-to-centre distance minus half a cell, >= 0), the grid border counting as an
    obstacle ring just outside the grid."""
    padded = np.pad(obstacle, 1, constant_values=True)
    edt = ndimage.distance_transform_edt(~padded)[1:-1, 1:-1]
    return np.maximum(edt * resolution - 0.5 * resolution, 0.0)


class World:
    """A floor plan with precomputed occupancy masks and clearance fields.

    `clearance` is the exact distance from a point to the nearest occupied cell square
    (or the grid border) up to `EXACT_CLEARANCE_M`; beyond that it is interpolated from
    the per-cell distance transform (within half a cell). `free_clearance` (distance to
    any non-free cell, for planning) is always the bilinear interpolation of its
    per-cell field: exact near a single axis-aligned wall, up to half a cell too small on
    the medial axis between two walls, up to ~0.2 cell too large next to an outside
    corner.
    """

    EXACT_CLEARANCE_M = 0.6

    def __init__(self, grid: GridMap) -> None:
        self.grid = grid
        self.occupied: NDArray[np.bool_] = grid.occupied_mask()
        self.free: NDArray[np.bool_] = grid.free_mask()
        self.resolution = float(grid.resolution)
        self.origin_xy = np.array(grid.origin[:2], dtype=np.float64)
        # WGS84 point at map (0, 0, 0): the world frame is ENU there (None: not given)
        self.geo_origin = grid.wgs84_origin
        # (H, W) metres from each cell centre to the nearest occupied cell.
        self.clearance_grid = _clearance_field(self.occupied, self.resolution)
        self._not_free = ~self.free
        self._clearance_cells = self.clearance_grid / self.resolution
        self._window = int(math.ceil(self.EXACT_CLEARANCE_M / self.resolution)) + 2

    @classmethod
    def load(cls, name_or_path: str | Path) -> World:
        """Load a shipped world by name or any map_server YAML by path."""
        path = resolve_world(name_or_path)
        world = cls(read_map(path))
        logger.info(
            "world %s: %d x %d cells at %.3f m, %.1f m^2 free",
            path.name,
            world.grid.width,
            world.grid.height,
            world.resolution,
            world.free_area_m2,
        )
        return world

    @cached_property
    def ray_blocks(self) -> BlockGrid:
        """Coarse occupancy for fast `cast_rays` on this world."""
        return block_grid(self.occupied)

    @cached_property
    def free_clearance_grid(self) -> NDArray[np.float64]:
        """(H, W) metres from each cell centre to the nearest NON-free cell (occupied,
        unknown or beyond the grid); 0 on non-free cells. Used for planning."""
        field = _clearance_field(self._not_free, self.resolution)
        field[self._not_free] = 0.0
        return field

    @property
    def free_area_m2(self) -> float:
        """Area of the free cells (m^2)."""
        return float(np.count_nonzero(self.free)) * self.resolution**2

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the grid in the map frame (m)."""
        x0, x1, y0, y1 = self.grid.extent
        return (x0, y0, x1, y1)

    def to_grid_coords(self, xy: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(N, 2) map-frame points -> continuous cell coordinates (gx, gy), each (N,)."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        g = (p - self.origin_xy) / self.resolution
        return np.ascontiguousarray(g[:, 0]), np.ascontiguousarray(g[:, 1])

    def _sample(
        self, field: NDArray[np.float64], solid: NDArray[np.bool_], xy: ArrayLike
    ) -> NDArray[np.float64]:
        gx, gy = self.to_grid_coords(xy)
        out = np.empty(gx.shape[0], dtype=np.float64)
        sample_kernel(field, solid, gx, gy, out)
        return out

    def clearance(self, xy: ArrayLike) -> NDArray[np.float64]:
        """(N,) metres from each (N, 2) point to the nearest occupied cell (or the grid
        border); 0 inside occupied cells and outside the grid. Exact below
        EXACT_CLEARANCE_M (see the class docstring)."""
        gx, gy = self.to_grid_coords(xy)
        out = np.empty(gx.shape[0], dtype=np.float64)
        exact_clearance_kernel(self._clearance_cells, self.occupied, gx, gy, self._window, out)
        return out * self.resolution

    def free_clearance(self, xy: ArrayLike) -> NDArray[np.float64]:
        """(N,) metres from each point to the nearest non-free cell; 0 on non-free cells."""
        return self._sample(self.free_clearance_grid, self._not_free, xy)

    def in_free_cell(self, xy: ArrayLike) -> NDArray[np.bool_]:
        """(N,) whether each point lies in a free cell of the grid."""
        cells = self.grid.world_to_cell(xy)
        inside = self.grid.in_bounds(cells)
        out = np.zeros(len(cells), dtype=bool)
        out[inside] = self.free[cells[inside, 1], cells[inside, 0]]
        return out

    def is_free(self, xy: ArrayLike, radius: float = 0.0) -> NDArray[np.bool_]:
        """(N,) whether a disc of `radius` (m) centred at each point lies in free space:
        the centre is in a free cell and its clearance to occupied cells is >= radius."""
        if not (radius >= 0.0 and math.isfinite(radius)):
            raise ConfigError(f"radius must be a finite number >= 0, got {radius}")
        return self.in_free_cell(xy) & (self.clearance(xy) >= radius)
