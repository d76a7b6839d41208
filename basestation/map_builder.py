"""The global 2-D occupancy grid, rebuilt from keyframes at their optimized poses.

New keyframes are inserted incrementally. When the optimizer moves a keyframe already
in the map by more than `pose_moved_m` / `pose_moved_rad`, the square tiles
(`rerender_tile_m`) its rays can reach, at its old and at its new pose, are marked
dirty. Dirty tiles are redrawn one at a time, each from scratch from the keyframes
that reach into it (in insertion order, at the current poses; of the keyframes with
one view, `VIEW_M` x `VIEW_M` x `VIEW_RAD`, only the newest `VIEW_KEEP`), most-moved
tile first, within `rerender_budget_s` per `update`: a tile's redraw is resumable (it
stops between two keyframes and goes on at the next update), so the caller's thread
never spends O(all keyframes) at once however large the correction. A redrawn tile
replaces the grid's cells only when complete. `finish()` completes every pending
tile (the map written at shutdown is consistent with the final poses).

Memory per keyframe: its key, current and last drawn pose (float32: 1e-5 m at 100 m)
and reach, and its row in the key's index (40 bytes in numpy arrays, which grow by a
quarter: `common.growable`). The scans are not kept here when a
`scan_source` is given (the base station's keyframe store: recent scans in memory,
older ones read back from the database); they are fetched again, a few at a time,
when a tile is redrawn. Without one the builder keeps a reference to each scan.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from basestation.node_keys import NodeKeys
from common.config import MapConfig
from common.geometry import wrap_angle
from common.growable import empty, grown
from common.map_io import GridMap
from common.occupancy_grid import OccupancyGrid
from protocol.keyframe_payloads import NO_READING_MM, Scan2D

log = logging.getLogger(__name__)

NodeKey = tuple[str, int]
ScanSource = Callable[[list[NodeKey]], list[Scan2D]]  # the scans of keyframes (keys)
Tile = tuple[int, int]  # (column, row) of the tile lattice
PAD = 3  # cells drawn around a tile but not pasted (see OccupancyGrid.paste)
CHUNK = 512  # keyframes box-tested at once while redrawing a tile
BATCH = 16  # keyframes drawn per kernel call while redrawing (the budget is checked between)
# a keyframe's scan with fewer returns than this is not drawn: a laser that saw nothing
# (a dropout, fog, open space beyond its range) says nothing of free space, and its
# no-return beams would have cleared the walls around (the agent's `min_num_points`)
MIN_SCAN_RETURNS = 20
# A tile redraw draws the newest VIEW_KEEP keyframes of each view (VIEW_M x VIEW_M square,
# VIEW_RAD of heading). A drone flying over mapped ground keeps cutting keyframes, so
# drawing all would cost O(time flown): a 10-robot, 30-minute soak redrew ~14,000
# keyframes per tile. The newest, not the first: the first keyframes of a place often
# saw other drones still standing at the start, which later scans clear again.
VIEW_M = 0.5
VIEW_RAD = np.pi / 4
VIEW_KEEP = 3


def _geometry(scan: Scan2D) -> tuple[float, float, int, float]:
    return (scan.angle_min, scan.angle_increment, scan.ranges_mm.size, scan.range_max)


@dataclass
class _TileJob:
    """A tile being redrawn: `sub` holds the keyframes drawn so far (indices < next)."""

    tile: Tile
    sub: OccupancyGrid
    todo: np.ndarray  # keyframes chosen when the job started (rows < next), in order
    done: int = 0  # of todo drawn
    next: int = 0  # keyframes from here on were added during the job: all are drawn
    stale: float = 0.0  # > 0: keyframes drawn into it moved again (redraw it again)


# beam geometries whose angles are kept (a fleet has a few lasers; a driver whose
# angle_min jitters had made one per keyframe, 430 MB at 100,000)
ANGLE_GEOMETRIES_KEPT = 64


def _metres(mm: np.ndarray, range_max: float) -> np.ndarray:
    """Scan2D ranges (mm) as float32 m: a no return `range_max`, a no reading NaN."""
    r = mm.astype(np.float32) * np.float32(1e-3)
    r[mm == 0] = np.float32(range_max)
    r[mm == NO_READING_MM] = np.nan
    return r


def _returns(mm: np.ndarray) -> np.ndarray:
    """The returns (neither no return nor no reading) in each scan of ``mm``."""
    return np.count_nonzero((mm > 0) & (mm != NO_READING_MM), axis=-1)


class MapBuilder:
    def __init__(self, cfg: MapConfig, scan_source: ScanSource | None = None) -> None:
        """`scan_source`: reads keyframes' scans again for tile redraws (called on the
        caller's thread); None: the builder keeps every scan it is given."""
        self.cfg = cfg
        self.grid: OccupancyGrid | None = None
        self._rows: dict[str, np.ndarray] = {}  # robot -> row of each index (-1: none)
        # row -> key, as numbers (a tuple per keyframe would cost ~90 bytes)
        self._robot_ids: list[str] = []  # robot code -> robot id
        self._key_robot = empty((), np.int32)  # row -> robot code
        self._key_index = empty((), np.int32)  # row -> keyframe index
        self._source = scan_source
        self._held: list[Scan2D] = []  # row -> scan, without a scan_source
        # latest pose given, [x, y, yaw] in map, and the pose it was last drawn (or marked)
        # at; float64: float32 rounds a UTM-sized northing to 0.5 m (walls drawn double)
        self._pose = empty((3,), np.float64)
        self._drawn = empty((3,), np.float64)
        self._reach = empty((), np.float32)  # farthest ray end (m)
        self._n = 0
        self._angles: dict[tuple[float, float, int], np.ndarray] = {}
        self._anchor = np.zeros(2)  # world xy of the tile lattice's corner (0, 0)
        self._center: np.ndarray | None = None  # xy of the first keyframe: the map's middle
        self.beyond_radius = 0  # keyframes not drawn: farther from it than max_radius_m
        self._tile_cells = max(int(round(cfg.rerender_tile_m / cfg.resolution_m)), 10)
        self._dirty: dict[Tile, float] = {}  # tile -> largest move (m) since drawn
        self._job: _TileJob | None = None
        self.rerenders = 0  # tiles redrawn
        self.rerendered_cells = 0
        self.rerender_draws = 0  # keyframe insertions spent redrawing tiles
        self.rerender_skipped = 0  # keyframes a redraw left out (older ones of a view)
        self.last_render_ms = 0.0

    # --- keyframes ----------------------------------------------------------------------
    def rerender_stats(self) -> dict[str, int]:
        return {
            "map_rerenders": self.rerenders,  # tiles redrawn
            "map_rerendered_cells": self.rerendered_cells,
            "map_rerender_draws": self.rerender_draws,  # keyframes drawn into them
            "map_rerender_skipped": self.rerender_skipped,  # older ones of a view
            "map_rerender_pending": self.pending,
        }

    def _beams(self, scan: Scan2D) -> tuple[np.ndarray, np.ndarray]:
        """Ranges (m, float32; a no-return is a max-range beam that clears free space,
        a no-reading NaN, not drawn) and angles (rad, sensor frame; shared by scans of
        one geometry)."""
        mm = scan.ranges_mm
        r = _metres(mm, scan.range_max)
        geom = (scan.angle_min, scan.angle_increment, mm.size)
        a = self._angles.get(geom)
        if a is None:  # (a driver whose angle_min jitters: one each; the oldest go)
            while len(self._angles) >= ANGLE_GEOMETRIES_KEPT:
                del self._angles[next(iter(self._angles))]
            a = self._angles.setdefault(geom, scan.angles())
        return r, a

    def _reach_of(self, scan: Scan2D) -> float:
        if _returns(scan.ranges_mm) < MIN_SCAN_RETURNS:
            return 0.0  # (not drawn)
        r, _ = self._beams(scan)  # no-return beams clear up to max_free_range_m
        r = np.where(r >= scan.range_max, np.minimum(r, self.cfg.max_free_range_m), r)
        return float(np.nanmax(r, initial=0.0))

    def _scans_of(self, idx: Sequence[int]) -> list[Scan2D]:
        if self._source is None:
            return [self._held[i] for i in idx]
        robots, indices = self._key_robot[idx].tolist(), self._key_index[idx].tolist()
        keys = zip(robots, indices, strict=True)
        return self._source([(self._robot_ids[c], i) for c, i in keys])

    def _draw(
        self, grid: OccupancyGrid, idx: Sequence[int], scans: Sequence[Scan2D] | None = None
    ) -> None:
        """Draw keyframes `idx` into `grid` in order at their current poses; each run of
        scans of one geometry in one kernel call. `scans`: theirs, if at hand."""
        if scans is None:
            scans = self._scans_of(idx)
        start = 0
        while start < len(idx):
            first = scans[start]
            geom = _geometry(first)
            end = start + 1
            while end < len(idx) and _geometry(scans[end]) == geom:
                end += 1
            run = list(idx[start:end])
            mm = np.stack([s.ranges_mm for s in scans[start:end]])
            r = _metres(mm, first.range_max)  # as in _beams
            _, a = self._beams(first)
            seen = _returns(mm) >= MIN_SCAN_RETURNS
            if seen.any():
                grid.insert_scans(
                    self._pose[run][seen].astype(np.float64), r[seen], a, 0.0,
                    first.range_max, max_free_range=self.cfg.max_free_range_m,
                )  # fmt: skip
            start = end

    def _append(self, keys: list[NodeKey], scans: list[Scan2D], poses: np.ndarray) -> None:
        n, k = self._n, len(keys)
        for name in ("_pose", "_drawn", "_reach", "_key_robot", "_key_index"):
            setattr(self, name, grown(getattr(self, name), n + k))
        for j, (key, scan) in enumerate(zip(keys, scans, strict=True)):
            rows = self._rows.get(key[0])
            rows = empty((), np.int32) if rows is None else rows
            self._rows[key[0]] = rows = grown(rows, key[1] + 1, fill=-1)
            rows[key[1]] = n + j
            if key[0] not in self._robot_ids:
                self._robot_ids.append(key[0])
            self._key_robot[n + j] = self._robot_ids.index(key[0])
            self._key_index[n + j] = key[1]
            if self._source is None:
                self._held.append(scan)
            self._reach[n + j] = self._reach_of(scan)
        self._pose[n : n + k] = self._drawn[n : n + k] = poses
        self._n = n + k

    # --- update -------------------------------------------------------------------------
    def update(
        self,
        keys: Sequence[NodeKey],
        scans: list[Scan2D],
        poses: np.ndarray,
        budget_s: float | None = -1.0,
    ) -> bool:
        """Bring the grid up to date with keyframes `keys` at `poses` ([x, y, yaw] in map):
        insert the new ones, mark the tiles of moved ones dirty, and redraw dirty tiles
        for up to `budget_s` (s; -1: the config's `rerender_budget_s`; None: all).
        `scans[j]` is keyframe j's scan; only new keyframes' are read (CHUNK at a time:
        after a recovery they may come from the database).

        Returns True if keyframes already in the map moved (tiles were marked dirty).
        """
        if not keys:
            return False
        t0 = time.perf_counter()
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        keys = NodeKeys.of(keys)
        new = np.flatnonzero(self._rows_of(keys) < 0).tolist()
        n_old = self._n
        parts = [new[i : i + CHUNK] for i in range(0, len(new), CHUNK)]
        part_scans: list[Scan2D] = []
        for part in parts:
            part_scans = [scans[j] for j in part]
            self._append([keys[j] for j in part], part_scans, poses[part])
        idx = self._rows_of(keys)
        self._pose[idx] = poses
        lo, hi = self._within_reach(*self._boxes(slice(n_old, self._n)))
        c = self.cfg
        if self.grid is None and len(lo):
            self.grid = OccupancyGrid.from_bounds(
                lo.min(axis=0) - 1.0, hi.max(axis=0) + 1.0, c.resolution_m,
                p_hit=c.p_hit, p_miss=c.p_miss, p_min=c.p_min, p_max=c.p_max,
            )  # fmt: skip
            self._anchor = np.array(self.grid.origin_xy)
        elif len(lo):
            self.grid.grow_to_include(lo.min(axis=0), hi.max(axis=0), 1.0)
        old = idx[idx < n_old]
        moved = self._mark_moved(old)
        last_new = self._n if self.grid is not None else n_old  # none drawn without a grid
        for k, i in enumerate(range(n_old, last_new, CHUNK)):  # bounded after a recovery
            last = k == len(parts) - 1  # its scans are still at hand
            self._draw(self.grid, range(i, min(i + CHUNK, self._n)), part_scans if last else None)
        self.work(None if budget_s is None else c.rerender_budget_s if budget_s < 0 else budget_s)
        self.last_render_ms = (time.perf_counter() - t0) * 1e3
        log.debug(
            "map: %d new keyframes, %d moved, %d tiles pending, %.1f ms",
            self._n - n_old, moved, self.pending, self.last_render_ms,
        )  # fmt: skip
        return moved > 0

    def _rows_of(self, keys: NodeKeys) -> np.ndarray:
        """Each key's row in the arrays (-1: not in the map yet); numpy per robot."""
        out = np.full(len(keys), -1, dtype=np.int64)
        for rid, idx, span in keys.spans():
            rows = self._rows.get(rid)
            if rows is not None:
                known = idx < len(rows)
                out[span][known] = rows[idx[known]]
        return out

    def _boxes(
        self, rows: slice | np.ndarray, poses: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners (m) of the boxes the keyframes' rays can reach."""
        p = self._pose[rows] if poses is None else poses
        r = self._reach[rows][:, None]
        return p[:, :2] - r, p[:, :2] + r

    def _within_reach(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The boxes of keyframes within `max_radius_m` of the first one, cut to that
        square: the map stops there (a keyframe one far GNSS fix pulled 465 km away had
        the grid allocate 133 TiB). Those beyond are counted, logged, and not drawn."""
        if self._center is None and len(lo):
            self._center = (lo[0] + hi[0]) / 2.0
        if not len(lo):
            return lo, hi
        r, c = self.cfg.max_radius_m, self._center
        ok = np.all(np.abs((lo + hi) / 2.0 - c) <= r, axis=1)
        if not ok.all():
            far = int((~ok).sum())
            self.beyond_radius += far
            log.error("map: %d keyframes more than map.max_radius_m = %g m from the first "
                      "one are not drawn (%d so far)", far, r, self.beyond_radius)  # fmt: skip
        return np.maximum(lo[ok], c - r), np.minimum(hi[ok], c + r)

    def _mark_moved(self, idx: np.ndarray) -> int:
        """Mark dirty the tiles of keyframes `idx` that moved since drawn; returns #moved."""
        c = self.cfg
        d_xy = np.hypot(*(self._pose[idx, :2] - self._drawn[idx, :2]).T)
        d_th = np.abs(wrap_angle(self._pose[idx, 2] - self._drawn[idx, 2]))
        # a turn under pose_moved_rad still moves far walls (0.0045 rad: 0.2 m at 50 m): so
        # does a farthest ray end moved by two cells
        reach_moved = d_xy + d_th * self._reach[idx]
        far = reach_moved > 2.0 * c.resolution_m
        is_moved = (d_xy > c.pose_moved_m) | (d_th > c.pose_moved_rad) | far
        moved = idx[is_moved]
        if len(moved) == 0:
            return 0
        # how far its farthest ray end moved (m): the tile's priority
        size = reach_moved[is_moved]
        m = (PAD + 2) * c.resolution_m  # rays may reach a cell beyond their box
        span = self._tile_cells * c.resolution_m
        for poses in (self._drawn[moved], self._pose[moved]):
            lo, hi = self._boxes(moved, poses)
            lo = np.maximum(lo, self._center - self.cfg.max_radius_m)  # no tiles beyond
            hi = np.minimum(hi, self._center + self.cfg.max_radius_m)
            t_lo = np.floor((lo - m - self._anchor) / span).astype(np.int64)
            t_hi = np.floor((hi + m - self._anchor) / span).astype(np.int64)
            for tx in range(int(t_lo[:, 0].min()), int(t_hi[:, 0].max()) + 1):
                in_x = (t_lo[:, 0] <= tx) & (t_hi[:, 0] >= tx)
                for ty in range(int(t_lo[:, 1].min()), int(t_hi[:, 1].max()) + 1):
                    hit = in_x & (t_lo[:, 1] <= ty) & (t_hi[:, 1] >= ty)
                    if hit.any():
                        self._mark((tx, ty), float(size[hit].max()))
        self._drawn[moved] = self._pose[moved]
        return len(moved)

    def _mark(self, tile: Tile, moved_m: float) -> None:
        if self._job is not None and self._job.tile == tile:
            self._job.stale = max(self._job.stale, moved_m)
        else:
            self._dirty[tile] = max(self._dirty.get(tile, 0.0), moved_m)

    def arrays_nbytes(self) -> int:
        """Bytes of the per-keyframe arrays (capacity)."""
        arrays = (self._pose, self._drawn, self._reach, self._key_robot, self._key_index)
        return sum(a.nbytes for a in (*arrays, *self._rows.values()))

    # --- tile redraws -------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Tiles waiting to be redrawn (including the one in progress)."""
        return len(self._dirty) + (self._job is not None)

    def finish(self) -> None:
        """Redraw every pending tile now (before writing the map)."""
        self.work(None)

    def work(self, budget_s: float | None) -> None:
        """Redraw dirty tiles, most-moved first, for about `budget_s` (None: all). At
        least one keyframe is drawn per call if any tile is pending."""
        if self.grid is None:
            return
        deadline = None if budget_s is None else time.perf_counter() + budget_s
        while self._job is not None or self._dirty:
            if self._job is None:
                tile = max(self._dirty, key=self._dirty.__getitem__)
                del self._dirty[tile]
                self._job = self._start(tile)
            if not self._advance(self._job, deadline):
                return
            self._paste(self._job)
            if self._job.stale > 0.0:
                self._dirty[self._job.tile] = self._job.stale
            self._job = None
            if deadline is not None and time.perf_counter() >= deadline:
                return

    def _tile_cells_of(self, tile: Tile) -> tuple[int, int]:
        """(row, col) of the tile's first cell in the grid's current lattice."""
        assert self.grid is not None
        res = self.cfg.resolution_m
        off = np.rint((self._anchor - np.array(self.grid.origin_xy)) / res).astype(int)
        return int(off[1]) + tile[1] * self._tile_cells, int(off[0]) + tile[0] * self._tile_cells

    def _start(self, tile: Tile) -> _TileJob:
        assert self.grid is not None
        drawn = self._reach[: self._n] > 0.0  # blank scans take no place among a view's newest
        reaching = np.flatnonzero(self._reaches(tile, slice(0, self._n)) & drawn)
        todo = self._newest_per_view(reaching)
        self.rerender_skipped += len(reaching) - len(todo)
        if len(todo):  # keyframes a correction moved past the grid's edge draw here
            self._grow_for(tile)
        r0, c0 = self._tile_cells_of(tile)
        t = self._tile_cells
        sub = self.grid.empty_like_region(
            slice(r0 - PAD, r0 + t + PAD), slice(c0 - PAD, c0 + t + PAD)
        )
        return _TileJob(tile, sub, todo, next=self._n)

    def _grow_for(self, tile: Tile) -> None:
        """The grid grown to hold `tile` (within `max_radius_m`): the grid had only grown
        for new keyframes, so moved ones lost what they drew past its edge for good (0 of
        335 wall cells after a 20 m shift). Grown only for a tile drawn into, not for
        every move: a keyframe thrown 400 m for one update and back had left it 51 M
        cells."""
        assert self.grid is not None and self._center is not None
        res = self.cfg.resolution_m
        lo = self._anchor + np.array(tile) * self._tile_cells * res
        hi = lo + self._tile_cells * res
        lo, hi = (
            np.maximum(lo, self._center - self.cfg.max_radius_m),
            np.minimum(hi, self._center + self.cfg.max_radius_m),
        )
        if np.all(lo < hi):
            self.grid.grow_to_include(lo, hi, PAD * res)

    def _reaches(self, tile: Tile, rows: slice) -> np.ndarray:
        """Which keyframes of `rows` have rays that may reach into `tile` (bool)."""
        res = self.cfg.resolution_m
        t_lo = self._anchor + np.array(tile) * self._tile_cells * res
        t_hi = t_lo + self._tile_cells * res
        m = (PAD + 2) * res
        lo, hi = self._boxes(rows)
        return np.all(hi >= t_lo - m, axis=1) & np.all(lo <= t_hi + m, axis=1)

    def _newest_per_view(self, idx: np.ndarray) -> np.ndarray:
        """Of keyframes `idx` (ascending), the newest VIEW_KEEP of each view, ascending."""
        p = self._pose[idx]
        ix = np.floor(p[:, 0] / VIEW_M).astype(np.int64) & 0xFFFFFF
        iy = np.floor(p[:, 1] / VIEW_M).astype(np.int64) & 0xFFFFFF
        ih = np.floor((p[:, 2] + np.pi) / VIEW_RAD).astype(np.int64) % round(2 * np.pi / VIEW_RAD)
        views = (ix << 28) | (iy << 4) | ih
        order = np.lexsort((idx, views))  # by view, then age
        v = views[order]
        last = np.r_[np.flatnonzero(v[1:] != v[:-1]), len(v) - 1]  # each view's newest
        group_end = np.repeat(last, np.diff(np.r_[-1, last]))
        keep = group_end - np.arange(len(v)) < VIEW_KEEP
        return np.sort(idx[order[keep]])

    def _advance(self, job: _TileJob, deadline: float | None) -> bool:
        """Draw the job's chosen keyframes, then every keyframe reaching into the tile
        that was added since the job started; True when done."""
        drew = False
        while True:
            if job.done == len(job.todo):
                if job.next >= self._n:
                    return True
                rows = slice(job.next, min(self._n, job.next + CHUNK))
                job.todo = rows.start + np.flatnonzero(self._reaches(job.tile, rows))
                job.done, job.next = 0, rows.stop
            for b in range(job.done, len(job.todo), BATCH):
                if drew and deadline is not None and time.perf_counter() >= deadline:
                    return False
                self._draw(job.sub, job.todo[b : b + BATCH].tolist())
                self.rerender_draws += len(job.todo[b : b + BATCH])
                job.done = min(b + BATCH, len(job.todo))
                drew = True

    def _paste(self, job: _TileJob) -> None:
        assert self.grid is not None
        r0, c0 = self._tile_cells_of(job.tile)
        h, w = self.grid.shape
        t = self._tile_cells
        rows = slice(min(max(r0, 0), h), min(max(r0 + t, 0), h))
        cols = slice(min(max(c0, 0), w), min(max(c0 + t, 0), w))
        if rows.stop > rows.start and cols.stop > cols.start:
            self.grid.paste(rows, cols, job.sub)
            self.rerendered_cells += (rows.stop - rows.start) * (cols.stop - cols.start)
        self.rerenders += 1

    def gridmap(self, free_thresh: float | None = None) -> GridMap | None:
        """The map_server view; `free_thresh` overrides the config's (exploration reads
        a cell seen free more often than hit as free, p < 0.5)."""
        if self.grid is None:
            return None
        free = self.cfg.free_thresh if free_thresh is None else free_thresh
        return self.grid.to_gridmap(self.cfg.occupied_thresh, free)
