"""The global 2-D occupancy grid, rebuilt from keyframes at their optimized poses.

New keyframes are inserted incrementally; when the optimizer moves keyframes
already in the map by more than `pose_moved_m` / `pose_moved_rad`, the grid is
re-rendered from all keyframes at their new poses.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from common.config import MapConfig
from common.geometry import se2_transform_points, wrap_angle
from common.map_io import GridMap
from common.occupancy_grid import OccupancyGrid
from protocol.messages import Scan2D

log = logging.getLogger(__name__)


class MapBuilder:
    def __init__(self, cfg: MapConfig) -> None:
        self.cfg = cfg
        self.grid: OccupancyGrid | None = None
        self._inserted: dict[tuple[str, int], np.ndarray] = {}  # key -> pose used
        self.full_renders = 0
        self.last_render_ms = 0.0

    def _beams(self, scan: Scan2D) -> tuple[np.ndarray, np.ndarray]:
        ranges = scan.ranges()
        # Quantized 0 ("no return"): treat as a max-range beam that clears free space.
        ranges[np.isnan(ranges)] = np.float32(scan.range_max)
        return ranges, scan.angles()

    def _extent(self, scans: list[Scan2D], poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo = poses[:, :2].min(axis=0)
        hi = poses[:, :2].max(axis=0)
        for scan, pose in zip(scans, poses, strict=True):
            r, a = self._beams(scan)
            r = np.minimum(r, self.cfg.max_free_range_m)
            pts = se2_transform_points(pose, np.column_stack([r * np.cos(a), r * np.sin(a)]))
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
        return lo, hi

    def update(self, keys: list[tuple[str, int]], scans: list[Scan2D], poses: np.ndarray) -> bool:
        """Bring the grid up to date with keyframes `keys` at `poses` ([x, y, yaw] in map).

        Returns True if the whole grid was re-rendered.
        """
        if not keys:
            return False
        t0 = time.perf_counter()
        poses = np.asarray(poses, dtype=np.float64)
        old = [i for i, k in enumerate(keys) if k in self._inserted]
        moved = False
        if old:
            before = np.array([self._inserted[keys[i]] for i in old])
            d_xy = np.hypot(*(poses[old, :2] - before[:, :2]).T)
            d_th = np.abs(wrap_angle(poses[old, 2] - before[:, 2]))
            moved = bool(
                np.any(d_xy > self.cfg.pose_moved_m) or np.any(d_th > self.cfg.pose_moved_rad)
            )
        todo = (
            range(len(keys))
            if (moved or self.grid is None)
            else [i for i, k in enumerate(keys) if k not in self._inserted]
        )
        todo = list(todo)
        if not todo:
            return False
        lo, hi = self._extent([scans[i] for i in todo], poses[todo])
        c = self.cfg
        if self.grid is None:
            self.grid = OccupancyGrid.from_bounds(
                lo - 1.0,
                hi + 1.0,
                c.resolution_m,
                p_hit=c.p_hit,
                p_miss=c.p_miss,
                p_min=c.p_min,
                p_max=c.p_max,
            )
        else:
            self.grid.grow_to_include(lo, hi, 1.0)
        if moved:
            self.grid.clear()
            self._inserted.clear()
            self.full_renders += 1
        for i in todo:
            r, a = self._beams(scans[i])
            self.grid.insert_scan(
                poses[i], r, a, 0.0, scans[i].range_max, max_free_range=c.max_free_range_m
            )
            self._inserted[keys[i]] = poses[i].copy()
        self.last_render_ms = (time.perf_counter() - t0) * 1e3
        log.debug(
            "map: inserted %d keyframes (%s) in %.1f ms",
            len(todo),
            "full re-render" if moved else "incremental",
            self.last_render_ms,
        )
        return moved

    def gridmap(self) -> GridMap | None:
        if self.grid is None:
            return None
        return self.grid.to_gridmap(self.cfg.occupied_thresh, self.cfg.free_thresh)
