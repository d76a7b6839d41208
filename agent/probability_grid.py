"""A submap's probability grid, like Cartographer's `ProbabilityGrid` (2-D).

Conventions (same as `common.occupancy_grid` / `common.map_io.GridMap`):
- the grid lives in its submap's frame; cell (ix, iy) covers
  [ox + ix * res, ox + (ix + 1) * res) x [oy + iy * res, oy + (iy + 1) * res),
  where `origin_xy = (ox, oy)` is the lower-left corner of cell (0, 0);
- arrays are indexed `[iy, ix]`, so `shape = (ny, nx)`.

Each cell stores an occupancy probability (float32) clamped to
[min_probability, max_probability] (Cartographer: [0.1, 0.9]); the value 0 marks a
cell never observed ("unknown"). What a matcher reads there is its choice:
`agent.scan_matcher` uses 0.5 by default, Cartographer uses min_probability.

Insertion (Cartographer's `ProbabilityGridRangeDataInserter2D`): every hit cell is
updated with the odds of `p_hit` (an unknown cell becomes `p_hit`), then every cell
the ray from the sensor to the hit crosses (exact Amanatides-Woo traversal, end cell
excluded) with the odds of `p_miss`. Each cell is updated at most once per scan and
hits win over misses: a wall cell hit by one beam is not cleared by a grazing
neighbour beam.

Grazing rays (`grazing_keep_cells`, not in Cartographer): a ray that meets a surface at a
shallow angle runs along it over its last cells, and clearing them erodes the wall
where no beam of that scan hits it. Along a corridor every scan did so to the walls a
few metres ahead, which then read ~0.5 against ~0.9 behind the drone, and each match
slid back towards the surer cells: local SLAM came up 20 % short over 40 m of a plain
3 m corridor (0.2 % with the rule; misses off altogether: 0.1 %). So the part of a hit
ray within `grazing_keep_cells` cells of the surface it hit is not cleared. The surface
is the line through the hit's two neighbours in beam order, taken only where the three
points lie within a cell of one line and their gaps stay under max(0.5 m, 10 % of the
range) (else a depth edge: the whole ray clears); the kept tail is at most
`GRAZING_TAIL_MAX_M`. The grid grows (by whole cells, plus `grow_margin_m`) to hold every
scan; `version` counts changes so matchers can cache what they derive from it.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from agent.voxel_filter import finite_points
from common.errors import CollabSlamError, ConfigError
from common.geometry import se2_transform_points

logger = logging.getLogger(__name__)

UNKNOWN = np.float32(0.0)  # stored value of a never-observed cell
GRAZING_TAIL_MAX_M = 2.0  # m, the longest tail of a grazing ray left uncleared


@njit(cache=True)
def _update(p: float, odds: float, p_min: float, p_max: float) -> float:
    """Cell probability after one observation with likelihood ratio `odds` (unknown -> prior)."""
    if p == 0.0:
        q = odds / (1.0 + odds)
    else:
        o = p * odds  # odds(q) = odds(p) * odds  <=>  q = p odds / (1 - p + p odds)
        q = o / (1.0 - p + o)
    return min(max(q, p_min), p_max)


@njit(cache=True)
def _insert_scan(
    prob: np.ndarray,
    stamp: np.ndarray,
    scan_id: int,
    su: float,
    sv: float,
    hits_uv: np.ndarray,
    misses_uv: np.ndarray,
    hit_odds: float,
    miss_odds: float,
    p_min: float,
    p_max: float,
    miss_rays: bool,
    tails: np.ndarray,
) -> None:
    """Apply one scan. (su, sv) is the sensor and `hits_uv`/`misses_uv` the ray ends,
    in continuous cell units (u = (x - ox) / res); all must lie inside the grid.
    `misses_uv` are ray ends without a return: their whole ray is free space.
    `tails[k]`: the fraction of hit ray k, at its end, left uncleared.
    """
    ny, nx = prob.shape
    sid = np.uint32(scan_id)
    for k in range(hits_uv.shape[0]):
        ix = int(math.floor(hits_uv[k, 0]))
        iy = int(math.floor(hits_uv[k, 1]))
        if 0 <= ix < nx and 0 <= iy < ny and stamp[iy, ix] != sid:
            stamp[iy, ix] = sid
            prob[iy, ix] = _update(prob[iy, ix], hit_odds, p_min, p_max)
    n_hits = hits_uv.shape[0] if miss_rays else 0
    for k in range(n_hits + misses_uv.shape[0]):
        if k < n_hits:
            eu = hits_uv[k, 0]
            ev = hits_uv[k, 1]
        else:
            eu = misses_uv[k - n_hits, 0]
            ev = misses_uv[k - n_hits, 1]
        # Amanatides-Woo traversal of every cell the segment crosses.
        ix = int(math.floor(su))
        iy = int(math.floor(sv))
        du = eu - su
        dv = ev - sv
        step_x = 1 if du > 0.0 else -1
        step_y = 1 if dv > 0.0 else -1
        # t (0 at the sensor, 1 at the end) between / to the next column and row boundary
        inv_du = 1.0 / abs(du) if du != 0.0 else math.inf
        inv_dv = 1.0 / abs(dv) if dv != 0.0 else math.inf
        t_x = ((ix + 1.0 - su) if du > 0.0 else (su - ix)) * inv_du if du != 0.0 else math.inf
        t_y = ((iy + 1.0 - sv) if dv > 0.0 else (sv - iy)) * inv_dv if dv != 0.0 else math.inf
        # cells before the end cell; a miss ray clears its end cell too
        n = abs(int(math.floor(eu)) - ix) + abs(int(math.floor(ev)) - iy) + (k >= n_hits)
        # a hit ray's tail along the surface it grazes (t > t_keep) is not cleared
        t_keep = 1.0 - tails[k] if k < n_hits else 2.0
        for _ in range(n):
            if min(t_x, t_y) > t_keep:
                break
            if 0 <= ix < nx and 0 <= iy < ny and stamp[iy, ix] != sid:
                stamp[iy, ix] = sid
                prob[iy, ix] = _update(prob[iy, ix], miss_odds, p_min, p_max)
            along_x = t_x < t_y  # branch-free stepping
            t_x += inv_du if along_x else 0.0
            t_y += 0.0 if along_x else inv_dv
            ix += step_x if along_x else 0
            iy += 0 if along_x else step_y


def grazing_tails(
    rays: NDArray[np.float64], resolution: float, keep_cells: float
) -> NDArray[np.float64]:
    """Per hit ray (N, 2: sensor to hit, m, in beam order), the fraction of its length,
    at its end, that lies within `keep_cells` cells of the surface it hit (module doc);
    0 where the surface is not known or `keep_cells` is 0."""
    out = np.zeros(len(rays))
    if len(rays) < 3 or keep_cells <= 0.0:
        return out
    prev, mid, nxt = rays[:-2], rays[1:-1], rays[2:]
    rng = np.hypot(mid[:, 0], mid[:, 1])
    along = nxt - prev
    length = np.maximum(np.hypot(along[:, 0], along[:, 1]), 1e-12)
    back, ahead = mid - prev, nxt - mid
    gap_limit = np.maximum(0.5, 0.1 * rng)
    off_line = np.abs(back[:, 0] * along[:, 1] - back[:, 1] * along[:, 0]) / length
    surface = (
        (np.hypot(back[:, 0], back[:, 1]) <= gap_limit)
        & (np.hypot(ahead[:, 0], ahead[:, 1]) <= gap_limit)
        & (length > 1e-9)
        & (off_line <= resolution)
    )
    sin_incidence = np.abs(mid[:, 0] * along[:, 1] - mid[:, 1] * along[:, 0]) / (
        np.maximum(rng, 1e-9) * length
    )
    tail_m = np.minimum(
        keep_cells * resolution / np.maximum(sin_incidence, 1e-3), GRAZING_TAIL_MAX_M
    )
    out[1:-1] = np.where(surface, np.minimum(tail_m / np.maximum(rng, 1e-9), 1.0), 0.0)
    return out


def _odds(p: float) -> float:
    return p / (1.0 - p)


@njit(cache=True, inline="always")
def cell_probability(v, p_unknown):  # type: ignore[no-untyped-def]
    """A stored cell value as a probability: 0 (never observed) reads `p_unknown`."""
    return v if v > 0.0 else p_unknown


class ProbabilityGrid:
    """Occupancy probabilities of one submap; grows when a scan reaches past its edge.

    `resolution` in m per cell, `origin_xy` (m) the lower-left corner of cell (0, 0)
    in the submap frame, `shape = (ny, nx)` the initial size in cells.
    """

    def __init__(
        self,
        resolution: float,
        origin_xy: ArrayLike,
        shape: tuple[int, int],
        *,
        min_probability: float = 0.1,
        max_probability: float = 0.9,
        grow_margin_m: float = 2.0,
    ) -> None:
        if not (math.isfinite(resolution) and resolution > 0.0):
            raise ConfigError(f"resolution must be > 0 m, got {resolution}")
        if not (0.0 < min_probability < 0.5 < max_probability < 1.0):
            raise ConfigError(
                f"need 0 < min_probability < 0.5 < max_probability < 1, got "
                f"{min_probability}, {max_probability}"
            )
        ny, nx = (int(v) for v in shape)
        if ny < 1 or nx < 1:
            raise ConfigError(f"grid shape must be positive (ny, nx), got {shape}")
        origin = np.asarray(origin_xy, dtype=np.float64).reshape(2)
        if not np.all(np.isfinite(origin)):
            raise ConfigError(f"origin_xy must be finite, got {origin_xy}")
        self.resolution = float(resolution)
        self.origin_xy = origin
        self.min_probability = float(min_probability)
        self.max_probability = float(max_probability)
        self.grow_margin_cells = max(1, int(math.ceil(grow_margin_m / self.resolution)))
        self._prob = np.zeros((ny, nx), dtype=np.float32)
        self._stamp: NDArray[np.uint32] | None = np.zeros((ny, nx), dtype=np.uint32)
        self.num_scans = 0
        self.version = 0  # bumped by every change; matchers key their caches on it

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) in cells."""
        return (int(self._prob.shape[0]), int(self._prob.shape[1]))

    @property
    def data(self) -> NDArray[np.float32]:
        """The live probability array [iy, ix] (0 = unknown). Read-only by contract."""
        return self._prob

    @property
    def frozen(self) -> bool:
        """True once `freeze()` was called; a frozen grid accepts no more scans."""
        return self._stamp is None

    def probability(self, unknown: float = math.nan) -> NDArray[np.float32]:
        """Copy of the probabilities [iy, ix], unknown cells set to `unknown`."""
        p = self._prob.copy()
        p[p == UNKNOWN] = unknown
        return p

    def known_mask(self) -> NDArray[np.bool_]:
        """Cells observed at least once."""
        return self._prob != UNKNOWN

    def to_occupied_mask(self, threshold: float = 0.5) -> NDArray[np.bool_]:
        """Known cells with probability > `threshold`."""
        return self._prob > threshold

    def cell_centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """x (nx,) and y (ny,) coordinates (m, submap frame) of the cell centres."""
        ny, nx = self.shape
        res = self.resolution
        xs = self.origin_xy[0] + (np.arange(nx) + 0.5) * res
        ys = self.origin_xy[1] + (np.arange(ny) + 0.5) * res
        return xs, ys

    def insert(
        self,
        T_submap_sensor: ArrayLike,
        points_sensor: ArrayLike,
        miss_rays: bool = True,
        p_hit: float = 0.55,
        p_miss: float = 0.49,
        *,
        miss_points_sensor: ArrayLike | None = None,
        grazing_keep_cells: float = 0.0,
    ) -> None:
        """Insert one scan taken at `T_submap_sensor` [x, y, yaw].

        `points_sensor` (N, 2): returns (m, sensor frame), non-finite rows skipped.
        `miss_points_sensor` (M, 2): optional ends of rays with no return (e.g. max-range
        beams cut to a fixed length); their whole ray, end cell included, is free space.
        `miss_rays=False` inserts only the hits. `grazing_keep_cells` > 0: the tails of
        rays grazing a surface are not cleared (module doc; the points must then be in
        beam order).
        """
        if self._stamp is None:
            raise CollabSlamError("cannot insert into a frozen probability grid")
        if not (0.5 < p_hit < 1.0 and 0.0 < p_miss < 0.5):
            raise ConfigError(f"need 0.5 < p_hit < 1 and 0 < p_miss < 0.5, got {p_hit}, {p_miss}")
        T = np.asarray(T_submap_sensor, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(T)):
            raise CollabSlamError(f"T_submap_sensor must be finite, got {T}")
        hits_xy = self._to_submap(T, points_sensor, "points_sensor")
        misses_xy = (
            self._to_submap(T, miss_points_sensor, "miss_points_sensor")
            if miss_points_sensor is not None
            else np.zeros((0, 2))
        )
        self._ensure_contains(np.vstack([hits_xy, misses_xy, T[None, :2]]))
        hits = (hits_xy - self.origin_xy) / self.resolution
        misses = (misses_xy - self.origin_xy) / self.resolution
        sensor_uv = (T[:2] - self.origin_xy) / self.resolution
        self.num_scans += 1
        self.version += 1
        scan_id = self.num_scans  # stamps start at 0, so scan 1 is the first marker
        _insert_scan(
            self._prob,
            self._stamp,
            scan_id,
            float(sensor_uv[0]),
            float(sensor_uv[1]),
            hits,
            misses,
            _odds(p_hit),
            _odds(p_miss),
            self.min_probability,
            self.max_probability,
            bool(miss_rays),
            grazing_tails(hits_xy - T[None, :2], self.resolution, grazing_keep_cells),
        )

    def freeze(self) -> None:
        """Crop to the observed cells and drop the per-scan bookkeeping (finished submaps)."""
        if self._stamp is None:
            return
        self._stamp = None
        known = self.known_mask()
        if not known.any():
            return
        rows = np.flatnonzero(known.any(axis=1))
        cols = np.flatnonzero(known.any(axis=0))
        y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
        self._prob = np.ascontiguousarray(self._prob[y0:y1, x0:x1])
        self.origin_xy = self.origin_xy + np.array([x0, y0]) * self.resolution
        self.version += 1

    # -- internals ---------------------------------------------------------------------

    def _to_submap(self, T: NDArray[np.float64], points: ArrayLike, name: str) -> NDArray:
        """(N, 2) sensor-frame points -> submap frame (m), non-finite rows dropped."""
        p = finite_points(points, name)
        return se2_transform_points(T, p)

    def _ensure_contains(self, xy: NDArray[np.float64]) -> None:
        """Grow (keeping cells on the same lattice) so every point of `xy` (m) is inside."""
        ny, nx = self.shape
        uv = (xy - self.origin_xy) / self.resolution
        lo = np.floor(uv.min(axis=0)).astype(np.int64)
        hi = np.floor(uv.max(axis=0)).astype(np.int64)
        if lo[0] >= 0 and lo[1] >= 0 and hi[0] < nx and hi[1] < ny:
            return
        m = self.grow_margin_cells
        x0 = min(0, int(lo[0]) - m)
        y0 = min(0, int(lo[1]) - m)
        x1 = max(nx, int(hi[0]) + 1 + m)
        y1 = max(ny, int(hi[1]) + 1 + m)
        prob = np.zeros((y1 - y0, x1 - x0), dtype=np.float32)
        prob[-y0 : -y0 + ny, -x0 : -x0 + nx] = self._prob
        stamp = np.zeros_like(prob, dtype=np.uint32)
        assert self._stamp is not None
        stamp[-y0 : -y0 + ny, -x0 : -x0 + nx] = self._stamp
        self._prob, self._stamp = prob, stamp
        self.origin_xy = self.origin_xy + np.array([x0, y0], dtype=np.float64) * self.resolution
        logger.debug("probability grid grown to %s cells", self._prob.shape)
