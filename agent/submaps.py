"""Cartographer's two overlapping active submaps (`ActiveSubmaps2D`).

Every scan goes into the (up to) two active submaps. A new submap starts when the
newer one holds `scans_per_submap` scans; the older one is then finished when it
holds 2 * `scans_per_submap`, so each finished submap holds 2N scans and every scan
after the first N lands in two submaps. Scans are matched against the older active
submap (`matching_submap()`), the most complete one.

Frames: `local` is the agent's local SLAM frame. A submap's frame is the pose of its
first scan, `T_local_submap`; its grid lives in that frame.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from agent.probability_grid import ProbabilityGrid
from common.errors import CollabSlamError, ConfigError
from common.geometry import se2_compose, se2_inverse

logger = logging.getLogger(__name__)


class Submap:
    """One submap: its pose in the local frame, its grid, and its scan count."""

    def __init__(
        self,
        index: int,
        T_local_submap: ArrayLike,
        resolution: float,
        initial_size_m: float,
        p_hit: float,
        p_miss: float,
        grazing_keep_cells: float = 0.0,
    ) -> None:
        self.index = index
        self.T_local_submap = np.asarray(T_local_submap, dtype=np.float64).reshape(3).copy()
        n = max(1, int(math.ceil(initial_size_m / resolution)))
        half = 0.5 * n * resolution
        # Cells stay on a lattice aligned with the submap origin.
        self.grid = ProbabilityGrid(resolution, (-half, -half), (n, n))
        self.p_hit = p_hit
        self.p_miss = p_miss
        self.grazing_keep_cells = grazing_keep_cells
        self.finished = False

    @property
    def num_scans(self) -> int:
        return self.grid.num_scans

    def to_submap(self, T_local_sensor: ArrayLike) -> NDArray[np.float64]:
        """T_submap_sensor from T_local_sensor."""
        return se2_compose(se2_inverse(self.T_local_submap), T_local_sensor)

    def to_local(self, T_submap_sensor: ArrayLike) -> NDArray[np.float64]:
        """T_local_sensor from T_submap_sensor."""
        return se2_compose(self.T_local_submap, T_submap_sensor)

    def insert(
        self,
        T_local_sensor: ArrayLike,
        points_sensor: ArrayLike,
        miss_points_sensor: ArrayLike | None = None,
    ) -> None:
        if self.finished:
            raise CollabSlamError(f"submap {self.index} is finished")
        self.grid.insert(
            self.to_submap(T_local_sensor),
            points_sensor,
            p_hit=self.p_hit,
            p_miss=self.p_miss,
            miss_points_sensor=miss_points_sensor,
            grazing_keep_cells=self.grazing_keep_cells,
        )

    def finish(self) -> None:
        """No more scans; the grid is cropped to what was observed."""
        self.finished = True
        self.grid.freeze()


class ActiveSubmaps:
    """The two active submaps plus the finished ones.

    `resolution` (m/cell), `scans_per_submap` N (a finished submap holds 2N scans),
    `initial_size_m`: side of a new submap's grid (it grows as needed),
    `max_finished_submaps`: keep at most this many finished submaps (oldest dropped;
    None keeps all).
    """

    def __init__(
        self,
        resolution: float = 0.05,
        scans_per_submap: int = 90,
        *,
        p_hit: float = 0.55,
        p_miss: float = 0.49,
        initial_size_m: float = 10.0,
        max_finished_submaps: int | None = None,
        grazing_keep_cells: float = 0.0,
    ) -> None:
        if scans_per_submap < 1:
            raise ConfigError(f"scans_per_submap must be >= 1, got {scans_per_submap}")
        if max_finished_submaps is not None and max_finished_submaps < 0:
            raise ConfigError(f"max_finished_submaps must be >= 0, got {max_finished_submaps}")
        self.resolution = float(resolution)
        self.scans_per_submap = int(scans_per_submap)
        self.p_hit = float(p_hit)
        self.p_miss = float(p_miss)
        self.initial_size_m = float(initial_size_m)
        self.max_finished_submaps = max_finished_submaps
        self.grazing_keep_cells = float(grazing_keep_cells)
        self.active: list[Submap] = []  # oldest first, at most 2
        self.finished: list[Submap] = []  # oldest first
        self._next_index = 0

    def matching_submap(self) -> Submap | None:
        """The submap to match the next scan against (the older active one); None
        before the first scan."""
        return self.active[0] if self.active else None

    def insert(
        self,
        T_local_sensor: ArrayLike,
        points_sensor: ArrayLike,
        miss_points_sensor: ArrayLike | None = None,
    ) -> list[Submap]:
        """Insert a scan (sensor-frame points, m) taken at `T_local_sensor`; returns the
        submaps it went into, oldest first. A submap finished by this scan has
        `finished` set and stays first in `active` until the next scan starts a new one.
        """
        T = np.asarray(T_local_sensor, dtype=np.float64).reshape(3)
        if not self.active or self.active[-1].num_scans == self.scans_per_submap:
            self._add_submap(T)
        for submap in self.active:
            submap.insert(T, points_sensor, miss_points_sensor)
        inserted = list(self.active)
        front = self.active[0]
        if front.num_scans == 2 * self.scans_per_submap:
            front.finish()
            logger.debug("submap %d finished (%d scans)", front.index, front.num_scans)
        return inserted

    def _add_submap(self, T_local_submap: NDArray[np.float64]) -> None:
        if len(self.active) == 2:
            done = self.active.pop(0)
            if not done.finished:  # cannot happen with the counts above
                done.finish()
            self.finished.append(done)
            limit = self.max_finished_submaps
            if limit is not None and len(self.finished) > limit:
                del self.finished[: len(self.finished) - limit]
        self.active.append(
            Submap(
                self._next_index,
                T_local_submap,
                self.resolution,
                self.initial_size_m,
                self.p_hit,
                self.p_miss,
                self.grazing_keep_cells,
            )
        )
        self._next_index += 1
