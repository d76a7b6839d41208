"""Multi-robot exploration on the global map (seed 002 §1.2): frontiers -> goals -> paths.

`ExplorationManager.step` takes the latest global grid (and the boxes the map changed
in), every robot's pose in `map` and returns, per robot, a new path in `map` when it
needs one: it has none, reached its goal, its goal is no longer a frontier, or the
map or another robot now blocks its path. Frontiers (`FrontierDetector`) that no
robot can reach are skipped; goals are assigned jointly (eq. 3, `GoalAssigner`) and
each path is planned with RRT* (`PathPlanner`) around the other robots and their
paths. A frontier the map itself kept a robot from reaching `max_failures` times is given
up (one only blocked by other robots for now is not). When
no frontier is left, `done` is True (exploration halts) until a new map brings more;
a robot that goes silent is `release`d and its goal becomes free.

Pure logic over numpy arrays: the base station node feeds it and sends the paths,
transformed into each robot's `odom` frame (`common.geometry.map_to_odom`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basestation.frontiers import Box, Frontier, FrontierDetector
from basestation.goal_assigner import AssignmentWeights, GoalAssigner
from basestation.path_planner import PathPlanner, PlanningMap
from common.config import Config
from common.map_io import GridMap

log = logging.getLogger(__name__)


@dataclass
class _Task:
    goal: NDArray[np.float64]
    path: NDArray[np.float64]  # (N, 2) map frame


@dataclass
class ExplorationManager:
    detector: FrontierDetector = field(default_factory=FrontierDetector)
    assigner: GoalAssigner = field(default_factory=lambda: GoalAssigner(AssignmentWeights()))
    planner: PathPlanner = field(default_factory=PathPlanner)
    goal_reached_m: float = 0.5  # a robot this close to its goal needs a new one
    frontier_gone_m: float = 0.6  # a goal with no frontier this close has vanished
    tasks: dict[str, _Task] = field(default_factory=dict)
    frontiers: list[Frontier] = field(default_factory=list)
    done: bool = False
    unreachable: int = 0
    max_failures: int = 8  # failed plans before a frontier is given up
    _failures: list[tuple[NDArray[np.float64], int]] = field(default_factory=list)
    _stopped: set[str] = field(default_factory=set)

    def step(
        self,
        grid: GridMap,
        poses: dict[str, ArrayLike],
        touched: list[Box] | None = None,
    ) -> dict[str, NDArray[np.float64] | None]:
        """New paths (map frame, (N, 2)) for the robots that need one; None tells a
        robot to stop (nothing left for it). Robots not in the result keep theirs."""
        self.frontiers = [
            f for f in self.detector.update(grid, touched) if not self._given_up(f.goal)
        ]
        P = {r: np.asarray(p, dtype=np.float64)[:3] for r, p in poses.items()}
        pm = PlanningMap(grid, self.planner.inflation_m)
        need = [r for r in P if self._needs_new_path(r, P[r], pm)]
        for r in set(self.tasks) - set(P):
            self.release(r)
        self.done = not self.frontiers and bool((grid.data == 0).any())  # not before a map
        if not self.frontiers:  # done: every robot stops (once); no map yet: wait
            stop = [r for r in P if r not in self._stopped] if self.done else []
            self._stopped.update(stop)
            for r in stop:
                self.tasks.pop(r, None)
            return {r: None for r in stop}
        self._stopped.clear()
        if not need:
            return {}
        out: dict[str, NDArray[np.float64] | None] = {}
        busy = {r: t.goal for r, t in self.tasks.items() if r not in need}
        candidates = [
            f.goal for f in self.frontiers
            if all(np.hypot(*(f.goal - g)) > self.frontier_gone_m for g in busy.values())
        ]  # fmt: skip
        goals = self.assigner.assign({r: P[r] for r in need}, candidates)
        for r in need:
            self.tasks.pop(r, None)
            goal = goals.get(r)
            path = None
            if goal is not None:
                others = [P[o][None, :2] for o in P if o != r]
                others += [t.path for o, t in self.tasks.items() if o != r]
                path = self.planner.plan(grid, P[r][:2], goal, others)
                if path is None:
                    self.unreachable += 1
                    # blocked by the map itself (not just by another robot for now)?
                    if self.planner.plan(grid, P[r][:2], goal) is None:
                        self._failed(goal)
                    log.debug("robot %s: no path to frontier %s", r, goal)
            if path is not None:
                self.tasks[r] = _Task(goal, path)
            out[r] = path
        return out

    def _needs_new_path(self, r: str, pose: NDArray[np.float64], pm: PlanningMap) -> bool:
        t = self.tasks.get(r)
        if t is None:
            return True
        if np.hypot(*(pose[:2] - t.goal)) < self.goal_reached_m:
            return True
        if not any(np.hypot(*(f.goal - t.goal)) < self.frontier_gone_m for f in self.frontiers):
            return True  # explored meanwhile, or no longer a frontier
        # the rest of the path, after the waypoint nearest the robot, must still be free
        k = int(np.argmin(np.hypot(*(t.path - pose[:2]).T)))
        return not pm.segment_free(t.path[min(k + 1, len(t.path) - 1) :])

    def _given_up(self, goal: NDArray[np.float64]) -> bool:
        return any(
            n >= self.max_failures and np.hypot(*(goal - g)) < self.frontier_gone_m
            for g, n in self._failures
        )

    def _failed(self, goal: NDArray[np.float64]) -> None:
        for k, (g, n) in enumerate(self._failures):
            if np.hypot(*(goal - g)) < self.frontier_gone_m:
                self._failures[k] = (g, n + 1)
                return
        self._failures.append((goal.copy(), 1))

    def restore_task(self, robot: str, path: ArrayLike) -> None:
        """After a restart: the robot is following `path` ((N, 2), map frame) to its end."""
        p = np.asarray(path, dtype=np.float64).reshape(-1, 2)
        self.tasks[robot] = _Task(p[-1].copy(), p)

    def release(self, robot: str) -> None:
        """Forget a robot (gone silent): its goal is free for the others."""
        self.tasks.pop(robot, None)
        self.assigner.release(robot)


def make_explorer(cfg: Config) -> ExplorationManager:
    """An `ExplorationManager` set up from `cfg.exploration`."""
    e = cfg.exploration
    return ExplorationManager(
        detector=FrontierDetector(e.frontier_radius_m, min_group_cells=e.min_frontier_cells),
        assigner=GoalAssigner(AssignmentWeights(e.w_distance, e.w_heading, e.w_previous)),
        planner=PathPlanner(e.inflation_m, e.robot_clearance_m, e.planning_time_s),
    )


def densify(path: NDArray[np.float64], spacing_m: float) -> NDArray[np.float64]:
    """Waypoints at most `spacing_m` apart along the polyline: a follower that turns
    toward the next waypoint early then cuts corners by little."""
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:], strict=True):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / spacing_m)))
        out.append(a + np.linspace(0.0, 1.0, n + 1)[1:, None] * (b - a))
    return np.vstack(out)
