"""Laser scan preprocessing for local SLAM.

Drops NaN, infinite and out-of-range returns; turns beams into points in the
gravity-aligned body frame using the IMU's roll and pitch (a tilted planar
laser's points are rotated into 3-D and projected back to the horizontal
plane; points that land near the floor are dropped); cuts no-return beams to
`missing_data_ray_length_m` so they can clear free space; and thins the cloud
for matching (adaptive voxel filter) and for insertion (fixed voxel filter).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from agent.voxel_filter import adaptive_voxel_filter, voxel_filter
from common.config import LocalSlamConfig

log = logging.getLogger(__name__)


@dataclass
class PreparedScan:
    points: NDArray[np.float64]  # (N, 2) returns, level body frame (m), voxel-filtered
    match_points: NDArray[np.float64]  # (M, 2) adaptive-voxel-filtered subset for matching
    miss_points: NDArray[np.float64]  # (K, 2) ends of no-return rays, cut to a fixed length
    dropped_invalid: int  # NaN / inf / out-of-range beams


class ScanPreprocessor:
    def __init__(self, cfg: LocalSlamConfig) -> None:
        self.cfg = cfg
        self._angles_cache: tuple[float, float, int, NDArray[np.float64]] | None = None

    def _trig(self, angle_min: float, inc: float, n: int) -> NDArray[np.float64]:
        key = (angle_min, inc, n)
        if self._angles_cache is None or self._angles_cache[:3] != key:
            a = angle_min + inc * np.arange(n)
            self._angles_cache = (*key, np.column_stack([np.cos(a), np.sin(a)]))
        return self._angles_cache[3]

    def prepare(
        self,
        angle_min: float,
        angle_increment: float,
        range_max: float,
        ranges: NDArray[np.float32],
        roll: float = 0.0,
        pitch: float = 0.0,
        altitude: float | None = None,
        range_min: float = 0.0,
    ) -> PreparedScan:
        """`range_min`: the laser's; readings below it (its own frame, an error code)
        are neither returns nor free space, as below `min_range_m`."""
        c = self.cfg
        r = np.asarray(ranges, dtype=np.float64)
        cs = self._trig(angle_min, angle_increment, r.size)
        finite = np.isfinite(r)
        hit_max = min(c.max_range_m, range_max)
        valid = finite & (r >= max(c.min_range_m, range_min, 1e-3)) & (r < hit_max)
        no_return = (finite & (r >= range_max)) | (np.isposinf(r))
        hits = cs[valid] * r[valid, None]
        misses = cs[no_return] * c.missing_data_ray_length_m
        if roll or pitch:
            hits, keep = self._level(hits, roll, pitch, altitude)
            hits = hits[keep]
            misses, _ = self._level(misses, roll, pitch, None)
        points = voxel_filter(hits, c.voxel_filter_size_m) if len(hits) else hits
        match_points = adaptive_voxel_filter(
            points, c.adaptive_max_length_m, c.adaptive_min_num_points, c.max_range_m
        )
        return PreparedScan(
            points, match_points, misses, int(r.size - valid.sum() - no_return.sum())
        )

    def level_ranges(
        self,
        angle_min: float,
        angle_increment: float,
        range_max: float,
        ranges: NDArray[np.float32],
        roll: float,
        pitch: float,
        altitude: float | None,
    ) -> NDArray[np.float32]:
        """A tilted scan's readings as a keyframe carries them: -inf (no reading) where
        it met the floor, the others as they were (a tilt of a few degrees changes a
        reading's level distance and bearing by well under 1 %: taking the levelled
        distance at the beam's own bearing did no better in `make run`). A laser pitched
        5.8 degrees at 1 m meets the floor ~10 m ahead, and keyframes had carried those
        readings to the base station's map as walls."""
        r = np.asarray(ranges, dtype=np.float64)
        if not (roll or pitch):
            return np.asarray(ranges, dtype=np.float32)
        hit = np.isfinite(r) & (r > 0.0) & (r < range_max)
        xy = self._trig(angle_min, angle_increment, r.size)[hit] * r[hit, None]
        _, keep = self._level(xy, roll, pitch, altitude)
        out = r.copy()
        out[hit] = np.where(keep, r[hit], -np.inf)
        return out.astype(np.float32)

    def _level(
        self, xy: NDArray[np.float64], roll: float, pitch: float, altitude: float | None
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Rotate sensor-plane points by roll/pitch into the level frame; keep xy.

        Returns (xy, keep) where keep drops points within floor_margin of the floor.
        """
        cr, sr = np.cos(roll), np.sin(roll)
        cp, sp = np.cos(pitch), np.sin(pitch)
        # R = Ry(pitch) @ Rx(roll) applied to [x, y, 0]
        x = cp * xy[:, 0] + sp * sr * xy[:, 1]
        y = cr * xy[:, 1]
        z = -sp * xy[:, 0] + cp * sr * xy[:, 1]
        keep = np.ones(len(xy), dtype=bool)
        if altitude is not None:
            keep = z > -altitude + self.cfg.floor_margin_m
        return np.column_stack([x, y]), keep
