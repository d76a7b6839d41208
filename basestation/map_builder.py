"""The global 2-D occupancy grid, rebuilt from keyframes at their optimized poses.

New keyframes are inserted incrementally; when the optimizer moves keyframes
already in the map by more than `pose_moved_m` / `pose_moved_rad`, only the region
those keyframes cover (at their old and new poses) is re-rendered, from every
keyframe that reaches into it, at the new poses.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from common.config import MapConfig
from common.geometry import wrap_angle
from common.map_io import GridMap
from common.occupancy_grid import OccupancyGrid
from protocol.messages import Scan2D

log = logging.getLogger(__name__)


class MapBuilder:
    def __init__(self, cfg: MapConfig) -> None:
        self.cfg = cfg
        self.grid: OccupancyGrid | None = None
        self._inserted: dict[tuple[str, int], np.ndarray] = {}  # key -> pose used
        self._reach: dict[tuple[str, int], float] = {}  # key -> farthest ray end (m)
        self.rerenders = 0
        self.rerendered_cells = 0
        self.last_render_ms = 0.0

    def _beams(self, scan: Scan2D) -> tuple[np.ndarray, np.ndarray]:
        ranges = scan.ranges()
        # Quantized 0 ("no return"): treat as a max-range beam that clears free space.
        ranges[np.isnan(ranges)] = np.float32(scan.range_max)
        return ranges, scan.angles()

    def _reach_of(self, key: tuple[str, int], scan: Scan2D) -> float:
        if key not in self._reach:
            r, _ = self._beams(scan)  # no-return beams clear up to max_free_range_m
            r = np.where(r >= scan.range_max, np.minimum(r, self.cfg.max_free_range_m), r)
            self._reach[key] = float(r.max(initial=0.0))
        return self._reach[key]

    def _boxes(self, keys, scans, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per keyframe, the lower and upper corner of the box its rays can reach."""
        reach = np.array([self._reach_of(k, s) for k, s in zip(keys, scans, strict=True)])
        return poses[:, :2] - reach[:, None], poses[:, :2] + reach[:, None]

    def _insert(self, grid: OccupancyGrid, scan: Scan2D, pose: np.ndarray) -> None:
        r, a = self._beams(scan)
        grid.insert_scan(pose, r, a, 0.0, scan.range_max, max_free_range=self.cfg.max_free_range_m)

    def update(self, keys: list[tuple[str, int]], scans: list[Scan2D], poses: np.ndarray) -> bool:
        """Bring the grid up to date with keyframes `keys` at `poses` ([x, y, yaw] in map).

        Returns True if part of the grid was re-rendered because keyframes moved.
        """
        if not keys:
            return False
        t0 = time.perf_counter()
        poses = np.asarray(poses, dtype=np.float64)
        lo, hi = self._boxes(keys, scans, poses)
        c = self.cfg
        if self.grid is None:
            self.grid = OccupancyGrid.from_bounds(
                lo.min(axis=0) - 1.0, hi.max(axis=0) + 1.0, c.resolution_m,
                p_hit=c.p_hit, p_miss=c.p_miss, p_min=c.p_min, p_max=c.p_max,
            )  # fmt: skip
        else:
            self.grid.grow_to_include(lo.min(axis=0), hi.max(axis=0), 1.0)
        old = np.array([k in self._inserted for k in keys])
        moved = np.zeros(len(keys), dtype=bool)
        if old.any():
            before = np.array([self._inserted[k] for k, o in zip(keys, old, strict=True) if o])
            i_old = np.flatnonzero(old)
            d_xy = np.hypot(*(poses[i_old, :2] - before[:, :2]).T)
            d_th = np.abs(wrap_angle(poses[i_old, 2] - before[:, 2]))
            moved[i_old] = (d_xy > c.pose_moved_m) | (d_th > c.pose_moved_rad)
        if moved.any():
            self._rerender(keys, scans, poses, old, moved, lo, hi)
        for i in np.flatnonzero(~old):
            self._insert(self.grid, scans[i], poses[i])
            self._inserted[keys[i]] = poses[i].copy()
        self.last_render_ms = (time.perf_counter() - t0) * 1e3
        log.debug(
            "map: %d new keyframes, %d moved, %.1f ms",
            int((~old).sum()),
            int(moved.sum()),
            self.last_render_ms,
        )
        return bool(moved.any())

    def _rerender(self, keys, scans, poses, old, moved, lo, hi) -> None:
        """Re-render the box covering the moved keyframes at their old and new poses."""
        assert self.grid is not None
        i_mov = np.flatnonzero(moved)
        was = np.array([self._inserted[keys[i]][:2] for i in i_mov])
        reach = (hi[i_mov] - lo[i_mov]) / 2.0
        box_lo = np.minimum(lo[i_mov], was - reach).min(axis=0)
        box_hi = np.maximum(hi[i_mov], was + reach).max(axis=0)
        rows, cols = self.grid.region(box_lo, box_hi)
        pad = 3  # cells drawn around the box but not pasted (see OccupancyGrid.paste)
        h, w = self.grid.shape
        sub = self.grid.empty_like_region(
            slice(max(rows.start - pad, 0), min(rows.stop + pad, h)),
            slice(max(cols.start - pad, 0), min(cols.stop + pad, w)),
        )
        # every keyframe already drawn whose rays reach into the box is drawn again
        m = (pad + 2) * self.cfg.resolution_m  # and rays may reach a cell beyond the box
        touches = old & np.all(hi >= box_lo - m, axis=1) & np.all(lo <= box_hi + m, axis=1)
        for i in np.flatnonzero(touches):
            self._insert(sub, scans[i], poses[i])
            self._inserted[keys[i]] = poses[i].copy()
        self.grid.paste(rows, cols, sub)
        self.rerenders += 1
        self.rerendered_cells += sub.shape[0] * sub.shape[1]

    def gridmap(self, free_thresh: float | None = None) -> GridMap | None:
        """The map_server view; `free_thresh` overrides the config's (exploration reads
        a cell seen free more often than hit as free, p < 0.5)."""
        if self.grid is None:
            return None
        free = self.cfg.free_thresh if free_thresh is None else free_thresh
        return self.grid.to_gridmap(self.cfg.occupied_thresh, free)
