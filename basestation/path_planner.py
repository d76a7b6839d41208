"""Collision-free paths on the global grid with OMPL's RRT* (seed 002 §1.2).

The planning map: unknown cells count as free (seed 002: the robot discovers them on
the way), occupied cells are grown by `inflation_m` (the no-collision zone, plus two
cells so that the dense final check is conservative), and a
disc of `robot_clearance_m` around every other robot and along its current path is
blocked too. First the shortest 8-connected cell path on that planning map
(Dijkstra, cropped to the known part of the map plus `fallback_margin_m`, shortcut
greedily): if there is none, the goal is unreachable and RRT* is not run (it
would spend its whole budget, up to `attempts` times, finding nothing). Then RRT*
(`og.SimpleSetup`, path-length objective) runs for at most `budget_with_fallback`
x its budget (the whole budget, up to `attempts` times, if the cell path fails
the final check), stopping as soon as its path is within `rrt_good_enough` of
the grid path's length; its solution is simplified (shortcutting) and checked
densely against the planning map, so a returned path never crosses a blocked
cell. The shorter of the two is returned: RRT*'s first solution within its budget
can be the long way round a wall when a door is near (or nothing at all: long
detours through doors on a big map). The budget is `check_budget` state validity
checks, the same work on any machine however loaded (with the seeded generator,
the same questions in the same order get the same paths), capped at
`time_budget_s` of wall time; without `check_budget` only the wall time counts
(then the paths depend on the CPU's load). The
same question (start, goal, other robots) on the same grid is answered from memory:
an exploration step asks some several times. A start
inside the inflated zone (a robot close to a wall) is allowed: its path first
leaves the zone straight away from the wall (`PlanningMap.way_out`), and only if
there is no such way is the zone opened within `start_escape_m` of it
(`PlanningMap.open_escape`); a start outside every zone is given no way into one.
Either way a path never passes a wall closer than the robot already is, which the
agent's safety guard would refuse (docs/architecture.md: a lone drone on rooms15
held for 145 s in a door, 0.33 m from the jamb).

OMPL's random generator is seeded (`seed` of the first planner of the process: OMPL
accepts a seed only before its first sample) for repeatable plans.
"""

from __future__ import annotations

import logging
import math
import time
import zlib

import numpy as np
import ompl.base as ob
import ompl.geometric as og
import ompl.util as ou
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from basestation.grid_search import polyline_free, shortcut
from basestation.travel_distance import grid_path, wall_distance
from common.errors import ConfigError
from common.map_io import GridMap

log = logging.getLogger(__name__)
ou.setLogLevel(ou.LOG_WARN)


MEMO_SIZE = 512  # plans remembered for one grid


class PlanningMap:
    """The blocked-cell mask of a grid (module doc) and lookups in metres."""

    def __init__(
        self,
        grid: GridMap,
        inflation_m: float,
        others: list[ArrayLike] | None = None,
        robot_clearance_m: float = 1.0,
    ) -> None:
        if inflation_m < 0 or robot_clearance_m < 0:
            raise ConfigError("inflation and robot clearance must be >= 0 m")
        self.resolution = grid.resolution
        self.origin = np.array(grid.origin[:2], dtype=np.float64)
        occupied = grid.data > 0
        self.occupied = occupied
        self.inflation_m = float(inflation_m)
        self.wall_distance = wall_distance(occupied, grid.resolution)  # m, read-only
        self.blocked = self.wall_distance <= inflation_m
        self.blocked |= occupied
        # other robots: positions and paths, (N, 2) each; a path is blocked along its
        # segments, not only at its vertices (discs a quarter clearance apart: the
        # corridor's edge is within 1 % of the clearance of the segment)
        spacing = max(self.resolution, 0.25 * robot_clearance_m)
        for pts in others or []:
            p = np.atleast_2d(np.asarray(pts, dtype=np.float64))[:, :2]
            self.block_discs(densify(p, spacing) if len(p) > 1 else p, robot_clearance_m)
        h, w = self.blocked.shape
        self.extent = np.array([w, h], dtype=np.float64) * self.resolution

    def cells(self, xy: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        ij = np.floor((np.atleast_2d(xy) - self.origin) / self.resolution).astype(np.int64)
        return ij[:, 1], ij[:, 0]

    def is_free(self, xy: ArrayLike) -> NDArray[np.bool_]:
        """Per point: inside the map and not blocked."""
        iy, ix = self.cells(np.asarray(xy, dtype=np.float64))
        h, w = self.blocked.shape
        inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        out = np.zeros(len(ix), dtype=bool)
        out[inside] = ~self.blocked[iy[inside], ix[inside]]
        return out

    def block_discs(self, centres: NDArray[np.float64], radius: float, value: bool = True) -> None:
        """Set (or clear) the cells within `radius` of each centre (m)."""
        r = int(math.ceil(radius / self.resolution))
        yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
        disc = (xx * xx + yy * yy) * self.resolution**2 <= radius * radius
        h, w = self.blocked.shape
        iy, ix = self.cells(centres)
        for cy, cx in zip(iy, ix, strict=True):
            y0, y1, x0, x1 = cy - r, cy + r + 1, cx - r, cx + r + 1
            sy0, sx0 = max(0, -y0), max(0, -x0)
            y0, x0, y1, x1 = max(y0, 0), max(x0, 0), min(y1, h), min(x1, w)
            if y0 >= y1 or x0 >= x1:
                continue
            d = disc[sy0 : sy0 + (y1 - y0), sx0 : sx0 + (x1 - x0)]
            if value:
                self.blocked[y0:y1, x0:x1] |= d
            else:
                self.blocked[y0:y1, x0:x1] &= ~d

    def open_escape(self, start: NDArray[np.float64], radius: float) -> None:
        """Within `radius` of a robot at `start`: open the cells blocked by other robots'
        discs only, and, if the robot is inside a wall's zone (close to a wall), the
        zone's cells too (not the walls). A start outside every zone gets no way into
        one: a path from a drone 0.4 m from a door jamb could pass the jamb at 0.25 m."""
        iy, ix = self.cells(np.asarray(start, dtype=np.float64)[None, :2])
        h, w = self.blocked.shape
        cy, cx = int(iy[0]), int(ix[0])
        if not (0 <= cy < h and 0 <= cx < w):
            return
        r = int(math.ceil(radius / self.resolution))
        y0, y1, x0, x1 = max(cy - r, 0), min(cy + r + 1, h), max(cx - r, 0), min(cx + r + 1, w)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        disc = ((yy - cy) ** 2 + (xx - cx) ** 2) * self.resolution**2 <= radius * radius
        if not self.in_wall_zone(start):
            disc &= self.wall_distance[y0:y1, x0:x1] > self.inflation_m
        self.blocked[y0:y1, x0:x1] &= ~disc

    def in_wall_zone(self, xy: ArrayLike) -> bool:
        """Whether a point lies within the inflation of a wall (or on one)."""
        iy, ix = self.cells(np.asarray(xy, dtype=np.float64)[None, :2])
        h, w = self.blocked.shape
        if not (0 <= iy[0] < h and 0 <= ix[0] < w):
            return False
        return bool(self.wall_distance[iy[0], ix[0]] <= self.inflation_m)

    def way_out(self, start: NDArray[np.float64], max_m: float) -> NDArray[np.float64] | None:
        """From a point inside a wall's zone, the point straight away from the nearest
        wall (up the wall distance's gradient) where the zone ends, if that is within
        `max_m` and the way there keeps getting farther from the wall; else None."""
        s = np.asarray(start, dtype=np.float64)[:2]
        (cy,), (cx,) = self.cells(s[None])
        h, w = self.wall_distance.shape
        if not (1 <= cy < h - 1 and 1 <= cx < w - 1):
            return None
        d = self.wall_distance
        grad = np.array([d[cy, cx + 1] - d[cy, cx - 1], d[cy + 1, cx] - d[cy - 1, cx]])
        norm = float(np.hypot(*grad))
        if norm < 1e-9:
            return None
        step = 0.5 * self.resolution
        pts = s + np.arange(1, int(max_m / step) + 1)[:, None] * step * (grad / norm)
        py, px = self.cells(pts)
        inside = (py >= 0) & (py < h) & (px >= 0) & (px < w)
        if not inside.all():
            return None
        along = d[py, px]
        out = np.nonzero(along > self.inflation_m)[0]
        if not len(out) or (np.diff(along[: out[0] + 1]) < -1e-9).any():
            return None
        return pts[out[0]]

    def segment_free(self, path: NDArray[np.float64]) -> bool:
        """Whether every point along the polyline (sampled at a quarter cell) is free."""
        p = np.ascontiguousarray(path, dtype=np.float64).reshape(-1, 2)
        return bool(polyline_free(self.blocked, *self.origin, self.resolution, p))

    def walls_free(self, path: NDArray[np.float64]) -> bool:
        """Whether no point along the polyline is in a wall (the inflation may be)."""
        p = np.ascontiguousarray(path, dtype=np.float64).reshape(-1, 2)
        return bool(polyline_free(self.occupied, *self.origin, self.resolution, p))


_seeded = False


def _seed_ompl_once(seed: int) -> None:
    """OMPL has one process-wide generator that can be seeded only before first use."""
    global _seeded
    if not _seeded:
        ou.RNG.setSeed(int(seed) + 1)  # 0 means "random" to OMPL
        _seeded = True


class PathPlanner:
    def __init__(
        self,
        inflation_m: float = 0.4,
        robot_clearance_m: float = 1.0,
        time_budget_s: float = 0.3,
        start_escape_m: float = 0.5,
        seed: int = 0,
        attempts: int = 3,
        robot_radius_m: float = 0.2,
        fallback_margin_m: float = 2.0,
        rrt_good_enough: float = 1.2,
        budget_with_fallback: float = 0.25,
        check_budget: int | None = None,
    ) -> None:
        if not time_budget_s > 0:
            raise ConfigError(f"planning time budget must be > 0 s, got {time_budget_s}")
        self.inflation_m = float(inflation_m)
        self.robot_clearance_m = float(robot_clearance_m)
        self.time_budget_s = float(time_budget_s)
        self.start_escape_m = float(start_escape_m)
        self.attempts = max(1, int(attempts))
        self.robot_radius_m = float(robot_radius_m)
        self.fallback_margin_m = float(fallback_margin_m)
        self.rrt_good_enough = float(rrt_good_enough)
        self.budget_with_fallback = float(budget_with_fallback)
        if check_budget is not None and check_budget < 1:
            raise ConfigError(f"planning check budget must be >= 1, got {check_budget}")
        self.check_budget = check_budget
        self.validity_checks = 0  # states RRT* checked, all plans
        self.plans = 0  # paths searched for (not answered from memory)
        self.fallbacks = 0  # plans that came from the grid path, not RRT*
        # the same question on the same grid gets the same answer (an exploration step
        # asks some several times: a robot that must wait tries every way it has)
        self._memo: dict[tuple[bytes, bytes, tuple[bytes, ...]], NDArray[np.float64] | None] = {}
        self._memo_grid: tuple[object, ...] | None = None
        self.detours_shortened = 0  # of those, RRT* had a path but a longer one
        _seed_ompl_once(seed)

    def plan(
        self,
        grid: GridMap,
        start: ArrayLike,
        goal: ArrayLike,
        others: list[ArrayLike] | None = None,
    ) -> NDArray[np.float64] | None:
        """An (N, 2) path from start to goal [x, y] (m, map frame), or None if none was
        found within the budget (or the goal is blocked). `others`: other robots'
        positions / current paths, (M, 2) arrays, kept `robot_clearance_m` away from."""
        s = np.asarray(start, dtype=np.float64)[:2]
        g = np.asarray(goal, dtype=np.float64)[:2]
        key = (
            s.tobytes(), g.tobytes(),
            tuple(np.asarray(o, dtype=np.float64).tobytes() for o in others or []),
        )  # fmt: skip
        grid_key = (grid.data.shape, grid.origin, zlib.crc32(np.ascontiguousarray(grid.data)))
        if grid_key != self._memo_grid or len(self._memo) >= MEMO_SIZE:
            self._memo_grid, self._memo = grid_key, {}
        if key not in self._memo:
            self.plans += 1
            self._memo[key] = self._plan(grid, s, g, others)
        path = self._memo[key]
        return None if path is None else path.copy()

    def _plan(
        self,
        grid: GridMap,
        s: NDArray[np.float64],
        g: NDArray[np.float64],
        others: list[ArrayLike] | None,
    ) -> NDArray[np.float64] | None:
        # RRT* searches with two more cells of margin than asked, so that the final
        # check on the asked map, at a quarter cell, does not catch a clipped corner
        margin = 2.0 * grid.resolution
        pm = self._map(grid, s, others, margin)
        check = self._map(grid, s, others, 0.0)
        if pm.in_wall_zone(s):  # close to a wall: leave its zone straight away from it
            out = pm.way_out(s, self.start_escape_m + margin)
            if out is not None and check.segment_free(np.array([s, out])):
                rest = self._plan(grid, out, g, others)
                return None if rest is None else np.vstack([s[None], rest])
        if not pm.is_free(g[None])[0]:
            log.debug("goal %s is blocked", g)
            return None
        if not pm.is_free(s[None])[0]:
            log.debug("start %s is inside an obstacle", s)
            return None
        if pm.segment_free(np.array([s, g])):
            return np.array([s, g])
        cells = self._grid_path(grid, pm, s, g)
        if cells is None:
            log.debug("no path from %s to %s on the planning map", s, g)
            return None
        usable = check.segment_free(cells)
        reference = path_length(cells)
        path = self._rrt_star(pm, check, s, g, self.rrt_good_enough * reference, usable)
        if path is not None and (not usable or path_length(path) <= reference):
            return path
        if not usable:
            return None
        self.fallbacks += 1
        if path is not None:
            self.detours_shortened += 1
            log.debug("RRT* %.1f m, grid path %.1f m: grid path used", path_length(path), reference)
        else:
            log.debug("RRT* found no path in its budget: grid path of %d points used", len(cells))
        return cells

    def clear_of(self, grid: GridMap, path: ArrayLike, others: list[ArrayLike]) -> bool:
        """Whether `path` ((N, 2), from the robot's position) keeps out of the inflation
        and `robot_clearance_m` away from `others`, as a path from `plan` would."""
        p = np.asarray(path, dtype=np.float64).reshape(-1, 2)
        return self._map(grid, p[0], others, 0.0).segment_free(p)

    def approachable(
        self, grid: GridMap, goals: ArrayLike, max_shift_m: float
    ) -> NDArray[np.float64]:
        """Goals [x, y] moved out of the no-collision zone: each goal that `plan` would
        refuse as blocked (inside the inflation around a wall, as a frontier cell next
        to a wall or a door jamb often is) becomes the nearest cell centre that `plan`
        accepts, if that lies within `max_shift_m` and the straight line to it crosses
        no occupied cell (never the other side of a wall). Rows of NaN: no such cell.
        Other robots are not considered here."""
        g = np.asarray(goals, dtype=np.float64).reshape(-1, 2)
        out = g.copy()
        if not len(g):
            return out
        pm = PlanningMap(grid, self.inflation_m + 2.0 * grid.resolution)  # as plan() checks goals
        free = pm.is_free(g)
        if free.all():
            return out
        h, w = pm.blocked.shape
        reach = int(math.ceil(max_shift_m / pm.resolution)) + 1  # cells: a window this wide
        for k in np.flatnonzero(~free):  # ... around the goal holds every cell it may move to
            iy, ix = (int(v[0]) for v in pm.cells(g[k]))
            y0, x0 = max(iy - reach, 0), max(ix - reach, 0)
            window = pm.blocked[y0 : iy + reach + 1, x0 : ix + reach + 1]
            if not (0 <= ix < w and 0 <= iy < h) or window.all():
                out[k] = np.nan
                continue
            _, (ny, nx) = ndimage.distance_transform_edt(window, return_indices=True)
            cell = np.array([x0 + nx[iy - y0, ix - x0], y0 + ny[iy - y0, ix - x0]])
            c = pm.origin + (cell + 0.5) * pm.resolution
            n = max(2, int(math.ceil(np.hypot(*(c - g[k])) / (0.25 * pm.resolution))) + 1)
            line = g[k] + np.linspace(0.0, 1.0, n)[:, None] * (c - g[k])
            ly, lx = pm.cells(line)
            crosses = bool(pm.occupied[np.clip(ly, 0, h - 1), np.clip(lx, 0, w - 1)].any())
            out[k] = c if np.hypot(*(c - g[k])) <= max_shift_m and not crosses else np.nan
        return out

    def _grid_path(
        self, grid: GridMap, pm: PlanningMap, s: NDArray[np.float64], g: NDArray[np.float64]
    ) -> NDArray[np.float64] | None:
        """The shortest cell path on `pm` (module doc), shortcut; None if there is none."""
        known_y, known_x = np.nonzero(grid.data >= 0)
        iy, ix = pm.cells(np.array([s, g]))
        m = int(math.ceil(self.fallback_margin_m / pm.resolution))
        h, w = pm.blocked.shape
        x0 = max(int(min(known_x.min(initial=ix.min()), ix.min())) - m, 0)
        y0 = max(int(min(known_y.min(initial=iy.min()), iy.min())) - m, 0)
        x1 = min(int(max(known_x.max(initial=ix.max()), ix.max())) + m + 1, w)
        y1 = min(int(max(known_y.max(initial=iy.max()), iy.max())) + m + 1, h)
        origin = pm.origin + np.array([x0, y0]) * pm.resolution
        cells = grid_path(~pm.blocked[y0:y1, x0:x1], origin, pm.resolution, s, g)
        if cells is None:
            return None
        # greedy shortcut: from each kept cell the farthest one still in sight
        return cells[shortcut(pm.blocked, *pm.origin, pm.resolution, cells)]

    def _map(
        self, grid: GridMap, s: NDArray[np.float64], others: list[ArrayLike] | None, margin: float
    ) -> PlanningMap:
        pm = PlanningMap(grid, self.inflation_m + margin, others, self.robot_clearance_m + margin)
        pm.open_escape(s, self.start_escape_m)
        pm.blocked |= pm.occupied  # only the inflation is cleared around the start
        if not pm.is_free(s[None])[0]:  # ... but the robot is where it is: map noise
            pm.block_discs(s[None], self.robot_radius_m, value=False)  # must not trap it
        return pm

    def _rrt_star(
        self,
        pm: PlanningMap,
        check: PlanningMap,
        s: NDArray[np.float64],
        g: NDArray[np.float64],
        good_enough_m: float,
        have_fallback: bool,
    ) -> NDArray[np.float64] | None:
        """RRT*'s simplified path, or None. It stops as soon as its path is at most
        `good_enough_m` long; with a usable fallback it gets one budget, not `attempts`."""
        space = ob.RealVectorStateSpace(2)
        bounds = ob.RealVectorBounds(2)
        for k in range(2):
            bounds.setLow(k, float(pm.origin[k]))
            bounds.setHigh(k, float(pm.origin[k] + pm.extent[k]))
        space.setBounds(bounds)
        ss = og.SimpleSetup(space)
        h, w = pm.blocked.shape
        blocked = pm.blocked.tobytes()  # one byte a cell: read faster than the array
        ox, oy, res = float(pm.origin[0]), float(pm.origin[1]), pm.resolution

        def valid(state: ob.State) -> bool:
            self.validity_checks += 1
            ix = int((state[0] - ox) / res)
            iy = int((state[1] - oy) / res)
            return 0 <= ix < w and 0 <= iy < h and not blocked[iy * w + ix]

        ss.setStateValidityChecker(valid)
        si = ss.getSpaceInformation()
        si.setStateValidityCheckingResolution(0.5 * res / float(pm.extent.max()))
        a, b = space.allocState(), space.allocState()
        a[0], a[1], b[0], b[1] = float(s[0]), float(s[1]), float(g[0]), float(g[1])
        ss.setStartAndGoalStates(a, b, 0.5 * res)
        objective = ob.PathLengthOptimizationObjective(si)
        objective.setCostThreshold(ob.Cost(float(good_enough_m)))
        ss.getProblemDefinition().setOptimizationObjective(objective)
        ss.setPlanner(og.RRTstar(si))
        share = self.budget_with_fallback if have_fallback else 1.0
        for _ in range(1 if have_fallback else self.attempts):  # solve() grows the same tree
            ss.solve(self._termination(share))
            if ss.haveExactSolutionPath():
                break
        else:
            return None
        raw = self._path(ss, s, g)
        # shortcutting to the end (simplifyMax) is repeatable; a time limit is not
        ss.simplifySolution(0.0 if self.check_budget is not None else 0.05)
        for path in (self._path(ss, s, g), raw):  # shortcutting may clip a corner
            if check.segment_free(path):
                return path
        log.debug("RRT* path touches a blocked cell: rejected")
        return None

    def _termination(self, share: float) -> ob.PlannerTerminationCondition:
        """When one solve() stops: after `share` x `check_budget` more validity checks
        (the same work, and so the same path, however loaded the machine is), or at
        `share` x `time_budget_s` of this thread's CPU time, whichever comes first (CPU,
        not wall: a live base station plans on a worker thread while others take in
        keyframes; by wall time its plans had got a fraction of the budget, and failed)."""
        deadline = time.thread_time() + share * self.time_budget_s
        if self.check_budget is None:
            return ob.timedPlannerTerminationCondition(share * self.time_budget_s)
        last = self.validity_checks + max(1, int(share * self.check_budget))
        return ob.PlannerTerminationCondition(
            lambda: self.validity_checks >= last or time.thread_time() >= deadline
        )

    @staticmethod
    def _path(
        ss: og.SimpleSetup, s: NDArray[np.float64], g: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        p = ss.getSolutionPath()
        path = np.array([[p.getState(i)[0], p.getState(i)[1]] for i in range(p.getStateCount())])
        path[0], path[-1] = s, g
        return path


def path_length(path: NDArray[np.float64]) -> float:
    """Length (m) of an (N, 2) polyline."""
    return float(np.hypot(*np.diff(path, axis=0).T).sum())


def unknown_length(grid: GridMap, path: NDArray[np.float64]) -> float:
    """m of an (N, 2) polyline over unknown cells of `grid` (sampled at a quarter cell)."""
    step = 0.25 * grid.resolution
    p = densify(np.asarray(path, dtype=np.float64).reshape(-1, 2), step)
    ij = np.floor((p - np.asarray(grid.origin[:2])) / grid.resolution).astype(np.int64)
    h, w = grid.data.shape
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    unknown = np.ones(len(p), dtype=bool)
    unknown[inside] = grid.data[ij[inside, 1], ij[inside, 0]] < 0
    return float(np.hypot(*np.diff(p, axis=0).T)[unknown[:-1]].sum())


def densify(path: NDArray[np.float64], spacing_m: float) -> NDArray[np.float64]:
    """Waypoints at most `spacing_m` apart along the polyline: a follower that turns
    toward the next waypoint early then cuts corners by little."""
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / spacing_m)))
        out.append(a + np.linspace(0.0, 1.0, n + 1)[1:, None] * (b - a))
    return np.vstack(out)
