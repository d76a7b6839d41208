"""Multi-robot exploration on the global map (seed 002 §1.2): frontiers -> goals -> paths.

`ExplorationManager.step` takes the latest global grid (and the boxes the map changed
in), every robot's pose in `map` and returns a new path in `map` for each robot that
needs one: it has none, reached its goal, its goal is no longer a frontier, the map
or another robot now blocks its path, or a free robot is nearer its goal
(`goal_handover`). Frontier goals (`FrontierDetector`) are moved out of the inflation
(`PathPlanner.approachable`), assigned jointly (eq. 3, `GoalAssigner`) and planned with
RRT* (`PathPlanner`) around the other robots and
their paths, unless that makes a long detour (the robot waits or goes elsewhere). A
frontier the map itself kept a robot from reaching `max_failures` times is given up, and
all that are left when no robot could move for a few steps (`frontier_give_up`).
When no frontier is left (those of the exploration grid, then those of the published
map: `step`), `done` is True until a new map brings more; a robot that goes silent is
`release`d. Pure logic over numpy arrays: the base station node feeds it and sends
the paths in each robot's `odom` frame (`common.geometry.map_to_odom`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from basestation.frontier_give_up import FrontierGiveUp
from basestation.frontiers import Box, Frontier, FrontierDetector
from basestation.goal_assigner import AssignmentWeights, GoalAssigner, spaced
from basestation.goal_costs import frontier_costs
from basestation.goal_handover import handovers
from basestation.path_planner import PathPlanner, PlanningMap, path_length, unknown_length
from basestation.path_schedule import (
    comes_near,
    nearest_leg,
    points_along,
    schedule_conflict,
    turn_delay_s,
)
from basestation.support_moves import support_move
from basestation.travel_distance import planning_order, travel_distances
from common.map_io import GridMap

log = logging.getLogger(__name__)


@dataclass
class _Task:
    goal: NDArray[np.float64]
    path: NDArray[np.float64]  # (N, 2) map frame
    support: bool = False  # no frontier of its own: closing in on another robot's


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
    give_up: FrontierGiveUp = field(default_factory=FrontierGiveUp)
    coordinated: bool = True  # false: the greedy baseline (nearest frontier, no sharing rule)
    alternatives: int = 2  # other frontiers tried when other robots block the best one
    w_spread: float = 1.0  # cost per m a frontier lies inside spread_radius_m of a busy goal
    spread_radius_m: float = 5.0  # m
    speed_mps: float = 1.0  # cruise speed the robots fly their paths at (conflict checks)
    horizon_s: float = 15.0  # s ahead that paths are checked against each other
    # times robot_clearance_m: paths keep 1.5 m, the 1 m target plus the ~0.5 m a drone at
    # cruise speed needs to stop (v^2 / 2a) when a hold or a new path reaches it (1.3: two
    # drones 0.73 m apart when one held at a junction another was crossing, random:1)
    conflict_margin: float = 1.5
    # s, the others are also checked this far behind (and ahead of) their schedule: one
    # speeding up from a hover is 0.5 s late; one that stops is caught by the follower's
    # own neighbour guard (news ~0.3 s old), not by the next step (1.2 s before the guard)
    lag_s: float = 0.6
    # a robot facing away from its way turns on the spot first (the agents' follower flies
    # while it turns only up to 60-105 degrees off the nose): held in the schedules until
    # its way is this far off the nose, turning at this yaw rate (rad/s; 0: not modelled)
    turn_free_deg: float = 82.5
    turn_rate_rps: float = 1.0
    # m a robot that loses its path in a step may still fly on it while it stops (v^2 / 2a
    # at cruise speed): others planned in that step see it there, not where it was
    stop_distance_m: float = 0.5
    w_gain: float = 0.25  # m of travel per m^2 of unknown in view short of gain_full_m2
    gain_full_m2: float = 25.0  # m^2: about a half disc of gain_radius_m, a room's door
    gain_near_m: float = 5.0  # m of travel: nearer, less (a pocket is taken in passing)
    gain_radius_m: float = 4.0  # m: how far a look from a frontier counts (unknown_in_view)
    w_own: float = 0.5  # cost per m a frontier is closer to a robot than to all others
    own_cap_m: float = 10.0  # m, up to this much
    tours: bool = True  # goals only from the robot's share of the min-max tours (frontier_tours)
    support_min_m: float = 1.0  # m, shortest move worth sending an idle robot
    handover_m: float = 2.0  # m: a robot this much nearer another's goal competes for it
    handover_unknown: float = 3.0  # ... by travel charging unknown space this many times
    busy_radius_factor: float = 2.0  # frontiers within this x clearance of a busy goal: taken
    goal_shift_m: float = 1.0  # m a frontier goal may move to get out of the inflation
    # A path around other robots (their discs, or their routes) longer than this factor
    # times the path without them, plus the slack, is refused: wait or go elsewhere.
    detour_factor: float = 1.5
    detour_slack_m: float = 3.0  # m
    detours_refused: int = 0
    guess_m: float = 1.0  # m more through unknown space than the way without the others
    near_frontier_m: float = 1.5  # m of travel: a frontier this close to a robot ...
    near_frontier_cost_m: float = 5.0  # ... costs this much more (m of travel) for it
    seen_range_m: float = 6.0  # m: another robot's path sees frontiers this far ...
    seen_fov_deg: float = 270.0  # ... in this field of view around its flight direction ...
    seen_cost_m: float = 5.0  # ... and those cost this much more (0: off)
    strict_detector: FrontierDetector = field(default_factory=FrontierDetector)
    cleanup: bool = False  # the frontiers are those of the strict map (see `step`)
    # robots gone silent (liveliness lost) that may fly on: the rest of their path from
    # where they were last heard of, ending where they will hover (`release`)
    silent: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    _stopped: set[str] = field(default_factory=set)
    _unplanned: set[str] = field(default_factory=set)  # this step's robots still to plan
    _stopping: dict[str, NDArray[np.float64]] = field(default_factory=dict)  # see `_conflict`

    def step(
        self,
        grid: GridMap,
        poses: dict[str, ArrayLike],
        touched: list[Box] | None = None,
        blocked: set[str] | frozenset[str] = frozenset(),
        strict: GridMap | None = None,
    ) -> dict[str, NDArray[np.float64] | None]:
        """New paths (map frame, (N, 2)) for the robots that need one; None tells a
        robot to stop (nothing left for it). Robots not in the result keep theirs.
        `blocked`: robots whose own safety guard holds them (they get a new path).

        `grid` calls a cell free once it was seen free more often than hit (one look);
        `strict`, if given, is the map as published, whose free cells were seen free
        several times (four with the default map_server thresholds). Once `grid` has no
        frontier left, the frontiers of `strict` are cleaned up before exploration is
        `done`: areas only glimpsed (behind a drone's blind sector at the start, through
        a door in passing) are looked at again. Each such frontier is visited once: one
        still there when a robot reaches it is given up."""
        self.frontiers = [
            f for f in self._approachable(self.detector.update(grid, touched), grid)
            if not self.give_up.given_up(f.goal)
        ]  # fmt: skip
        self.cleanup = not self.frontiers and strict is not None
        if self.cleanup:  # what the published map still lacks (see `strict`)
            assert strict is not None
            self.frontiers = [
                f for f in self._approachable(self.strict_detector.update(strict), grid)
                if not self.give_up.given_up(f.goal)
            ]  # fmt: skip
        P = {r: np.asarray(p, dtype=np.float64)[:3] for r, p in poses.items()}
        for r in set(self.silent) & set(P):  # heard again
            del self.silent[r]
        self._note_stopping(P)
        pm = PlanningMap(grid, self.planner.inflation_m)
        need = [r for r in P if r in blocked or self._needs_new_path(r, P, pm)]
        if self.cleanup:  # the ones just given up by the robots standing at them
            self.frontiers = [f for f in self.frontiers if not self.give_up.given_up(f.goal)]
        for r in set(self.tasks) - set(P):
            self.release(r)
        self.done = not self.frontiers and bool((grid.data == 0).any())  # not before a map
        if not self.frontiers:  # done: every robot stops (once); no map yet: wait
            # ... a robot on its way first finishes the leg it is on: where its path ends
            # was checked against the others, a point in the middle of it was not; one
            # that stops hovers where it is, so the others' legs are judged again
            stop: list[str] = []
            while self.done:
                more = [
                    r for r in sorted(P)
                    if r not in self._stopped and (r in blocked or not self._finishing(r, P))
                ]  # fmt: skip
                if not more:
                    break
                self._stopped.update(more)
                for r in more:
                    self.tasks.pop(r, None)
                stop += more
            return {r: None for r in stop}
        self._stopped.clear()
        need += handovers(self, need, grid, P)  # a far goal another robot is nearer now
        if not need:
            return {}
        for r in need:
            self.tasks.pop(r, None)
        goals = self._goals({r: P[r] for r in need}, grid, P)
        need = planning_order(need, goals, grid, P, self.planner.robot_radius_m, self.coordinated)
        self._unplanned = set(need)
        out = {}
        for r in need:
            self._unplanned.discard(r)
            out[r] = self._plan(r, goals.get(r), grid, P)
        if self.coordinated and any(p is not None for p in out.values()):
            # robots planned before another got its path saw that one as standing still:
            # now it is on its way (judged in time), the way may be open
            for r in [r for r in need if out[r] is None]:
                out[r] = self._plan(r, self._goals({r: P[r]}, grid, P).get(r), grid, P)
        if self.coordinated:  # robots left without a frontier move up behind the others
            for r in [r for r in need if out[r] is None]:
                out[r] = support_move(self, r, grid, P)
                if out[r] is not None:
                    self.tasks[r] = _Task(out[r][-1], out[r], support=True)
            self._recheck(out, grid, P)
        moving = bool(self.tasks) or any(p is not None for p in out.values())
        self.give_up.note_progress(moving, [f.goal for f in self.frontiers], bool(self.silent))
        for r, path in out.items():
            task = self.tasks.get(r)
            log.debug(
                "robot %s at %s: %s",
                r,
                np.round(P[r][:2], 2),
                "stop" if path is None or task is None
                else f"{path_length(path):.1f} m to {np.round(task.goal, 2)}"
                + (" (support)" if task.support else ""),
            )  # fmt: skip
        return out

    def _note_stopping(self, P: dict[str, NDArray[np.float64]]) -> None:
        """Where each robot flying now would stop if it lost its path in this step."""
        s = np.linspace(0.0, self.stop_distance_m, 3)
        self._stopping = {
            r: points_along(self._remaining(r, P[r]), s) for r in self.tasks if r in P
        }

    def _recheck(
        self,
        out: dict[str, NDArray[np.float64] | None],
        grid: GridMap,
        P: dict[str, NDArray[np.float64]],
    ) -> None:
        """Re-plan (into `out`) every robot whose path now conflicts with the others: one
        that holds, or took a new way, may be in the way of a robot planned around it
        earlier, in an earlier step or in this one before it (at the start of a rooms15
        run a drone flew 0.91 m past one that was to have left and then held). Until
        none changes: a re-planned robot that now holds may be in another's way."""
        for _ in range(len(P)):
            changed = False
            for r in [r for r in P if r in self.tasks]:
                if self._conflict(r, self._remaining(r, P[r]), P):
                    self.tasks.pop(r)
                    out[r] = self._plan(r, self._goals({r: P[r]}, grid, P).get(r), grid, P)
                    changed = True
            if not changed:
                return

    def _approachable(self, found: list[Frontier], grid: GridMap) -> list[Frontier]:
        """Frontiers with their goal moved out of the no-collision zone (up to
        `goal_shift_m`): a frontier cell beside a wall or a door jamb lies inside the
        inflation, where no path may end. Those that cannot be moved are left out."""
        if not found:
            return found
        goals = self.planner.approachable(grid, [f.goal for f in found], self.goal_shift_m)
        return [
            f if np.array_equal(g, f.goal) else replace(f, goal=g)
            for f, g in zip(found, goals, strict=True)
            if np.isfinite(g).all()
        ]

    def _plan(
        self,
        r: str,
        goal: NDArray[np.float64] | None,
        grid: GridMap,
        P: dict[str, NDArray[np.float64]],
    ) -> NDArray[np.float64] | None:
        """A path for robot r to `goal`, or (coordinated) to the next best frontier when
        other robots block it; None if there is none. Coordinated: first a path around
        the other robots' discs only, kept if, flown at cruise speed against their
        remaining paths, it never comes within the clearance x margin of any of them
        (time-aware, so a robot may follow another through a door); otherwise a path
        that avoids their remaining paths by the clearance and passes that check too
        (bshape seed 8: a way round another's route ended 0.85 m from where it hovered)."""
        tried: list[NDArray[np.float64]] = []
        while goal is not None:
            path = self._path_among_others(r, goal, grid, P)
            if path is not None:
                self.tasks[r] = _Task(goal, path)
                return path
            self.unreachable += 1
            # blocked by the map itself (not just by another robot for now)?
            if self.planner.plan(grid, P[r][:2], goal) is None:
                self.give_up.failed(goal)
            log.debug("robot %s: no path to frontier %s", r, goal)
            tried.append(goal)
            if not self.coordinated or len(tried) > self.alternatives:
                return None
            goal = self._goals({r: P[r]}, grid, P, exclude=tried).get(r)
        return None

    def _path_among_others(
        self,
        r: str,
        goal: NDArray[np.float64],
        grid: GridMap,
        P: dict[str, NDArray[np.float64]],
    ) -> NDArray[np.float64] | None:
        """Robot r's path to `goal` around the other robots (`_plan`), or None. A path
        the others make more than `detour_factor` x (+ `detour_slack_m`) as long as the
        way without them, or send through more unknown space (`_detour`), is refused
        (`detours_refused`): one standing in a door, or
        another's route through it, would send r the long way round, when it could
        wait a moment or take another frontier. Not when a robot in the way has no
        goal of its own (it would not move on)."""
        start = P[r][:2]
        discs = self._discs(r, P)
        path = self.planner.plan(grid, start, goal, discs)
        if path is None or not self.coordinated or len(P) < 2:
            return path
        if self._conflict(r, path, P):
            routes = [self._remaining(o, P[o]) for o in self.tasks if o != r and o in P]
            around = self.planner.plan(grid, start, goal, discs + routes) if routes else None
            if around is not None and self._detour(grid, around, path):
                self.detours_refused += 1
                return None
            return None if around is None or self._conflict(r, around, P) else around
        if not self._too_long(path, float(np.hypot(*(goal - start)))) and not self._detour(
            grid, path, None
        ):  # no detour at all: no need to know the way without the others
            return path
        alone = self.planner.plan(grid, start, goal, list(self.silent.values()))
        if alone is None or not self._detour(grid, path, alone):
            return path  # the map itself makes the way that long
        in_way = [o for o in P if o != r and not self.planner.clear_of(grid, alone, [P[o][:2]])]
        if (not in_way or not discs) and not self._conflict(r, alone, P):
            return alone  # the others were not in the way after all (or RRT* went round)
        if not all(
            o in self._unplanned or (o in self.tasks and not self.tasks[o].support) for o in in_way
        ):  # one in the way stays there (no goal of its own): go round; one that gets
            return path  # its path later in this step is not judged yet: wait for it
        self.detours_refused += 1
        return None

    def _finishing(self, r: str, P: dict[str, NDArray[np.float64]]) -> bool:
        """Whether robot r is still on its way to its goal, on a path that keeps clear of
        the others (at the end, a support leg has nothing to finish: 8 drones' idle legs
        of 22-26 m had held a mission's end from 21 s to 44 s)."""
        t = self.tasks.get(r)
        return (t is not None and not t.support
                and bool(np.hypot(*(P[r][:2] - t.goal)) >= self.goal_reached_m)
                and not self._conflict(r, self._remaining(r, P[r]), P))  # fmt: skip

    def _discs(self, r: str, P: dict[str, NDArray[np.float64]]) -> list[NDArray[np.float64]]:
        """Where the other robots are, as discs to plan around: (coordinated) only those
        with no path to fly; one on its way is judged by `_conflict`, in time, so that
        a robot may follow another through the door it is leaving by."""
        return [
            P[o][None, :2] for o in P
            if o != r and not (self.coordinated and o in self.tasks)
        ] + list(self.silent.values())  # fmt: skip

    def _detour(
        self, grid: GridMap, path: NDArray[np.float64], way: NDArray[np.float64] | None
    ) -> bool:
        """Whether `path` is a detour from `way` (None: from nowhere): `_too_long`, or through
        more than `guess_m` more of unknown space (a way round the others, seen through
        a door, that may not be there)."""
        more = unknown_length(grid, path) - (0.0 if way is None else unknown_length(grid, way))
        return (way is not None and self._too_long(path, path_length(way))) or more > self.guess_m

    def _too_long(self, path: NDArray[np.float64], reference_m: float) -> bool:
        """Longer than `detour_factor` x `reference_m` + `detour_slack_m`."""
        return path_length(path) > self.detour_factor * reference_m + self.detour_slack_m

    def _conflict(
        self, r: str, path: NDArray[np.float64], P: dict[str, NDArray[np.float64]]
    ) -> bool:
        """Whether robot r flying `path` would come too close to another robot flying the
        rest of its own path (or hovering), in time (`schedule_conflict`): within the
        robot clearance x `conflict_margin`, over `horizon_s`, the others also `lag_s`
        behind and ahead of their schedule. One flying at the start of this step that
        lost its path in it is flown on for `stop_distance_m` (docs: Exploration)."""
        names = [o for o in P if o != r]
        others = [
            self._remaining(o, P[o]) if o in self.tasks else self._stopping.get(o, P[o][:2])
            for o in names
        ]
        free, rate = np.radians(self.turn_free_deg), self.turn_rate_rps  # turns on the spot
        delays = [
            turn_delay_s(P[o], q, free, rate) if q.ndim == 2 else 0.0
            for o, q in zip(names, others, strict=True)
        ]
        c = self.planner.robot_clearance_m
        return schedule_conflict(
            path, P[r], others, self.speed_mps, self.horizon_s, c, c * self.conflict_margin,
            self.lag_s, delays, turn_delay_s(P[r], path, free, rate),
        )  # fmt: skip

    def _goals(
        self,
        poses: dict[str, NDArray[np.float64]],
        grid: GridMap,
        P: dict[str, NDArray[np.float64]],
        exclude: list[NDArray[np.float64]] | None = None,
        taken: list[NDArray[np.float64]] | None = None,
    ) -> dict[str, NDArray[np.float64] | None]:
        """Goals for the robots in `poses` (eq. 3, jointly; P: every robot's pose), no
        two closer than the robots keep apart (clearance x `conflict_margin`): of two
        such, the robot with the longer way is assigned again, with the other's goal
        `taken` (busy). random:1 seed 6 (kinematic): goals 1.37 m apart; the robot that
        would get there last conflicted with the other's hover, lost its goal to the
        busy radius, and the team stalled for good."""
        if not self.coordinated:
            return self.assigner.nearest(poses, [f.goal for f in self.frontiers])
        flying = [r for r, t in self.tasks.items() if r not in poses and not t.support]
        busy = [self.tasks[r].goal for r in flying] + [w[-1] for w in self.silent.values()]
        busy += taken or []
        # a frontier this close to another robot's goal is that robot's to see
        near = self.busy_radius_factor * self.planner.robot_clearance_m
        candidates = [
            f.goal for f in self.frontiers
            if all(np.hypot(*(f.goal - g)) > near for g in busy)
            and all(np.hypot(*(f.goal - g)) > self.frontier_gone_m for g in exclude or [])
        ]  # fmt: skip
        if not candidates:
            return self.assigner.assign(poses, [])
        F = np.array(candidates)
        robots = sorted(poses)
        names = sorted(P)  # every robot from where it will be (a flying one: its goal)
        at = [self.tasks[o].goal if o in self.tasks and o not in poses else P[o][:2] for o in names]
        sources = np.vstack([np.array(at), F]) if self.tours else np.array(at)
        D_both = travel_distances(grid, sources, F, self.planner.robot_radius_m)
        D_all = D_both[: len(names)]
        between = D_both[len(names) :] if self.tours else None
        rows = [names.index(r) for r in robots]
        left = [
            path_length(self._remaining(o, P[o])) if o in self.tasks and o not in poses else 0.0
            for o in names
        ]  # fmt: skip
        D, spread, others = frontier_costs(
            self, grid, F, D_all, rows, busy, flying, P, between, np.array(left)
        )  # fmt: skip
        out = self.assigner.assign(
            poses, candidates, dict(zip(robots, D, strict=True)), spread,
            None if others is None else dict(zip(robots, others, strict=True)),
        )  # fmt: skip
        way = {
            r: D_all[names.index(r), np.argmin(np.hypot(*(F - g).T))]
            for r, g in out.items() if g is not None
        }  # fmt: skip
        kept, again = spaced(out, way, self.planner.robot_clearance_m * self.conflict_margin)
        if again:
            mine = [g for g in kept.values() if g is not None]
            kept.update(self._goals({r: P[r] for r in again}, grid, P, exclude, busy + mine))
        return kept

    def _remaining(self, robot: str, pose: NDArray[np.float64]) -> NDArray[np.float64]:
        """The part of a robot's path still ahead of it, from where it is now: on from the
        leg nearest it (the nearest waypoint's had skipped a corner just ahead)."""
        path = self.tasks[robot].path
        return np.vstack([pose[None, :2], path[nearest_leg(path, pose[:2]) + 1 :]])

    def _needs_new_path(self, r: str, P: dict[str, NDArray[np.float64]], pm: PlanningMap) -> bool:
        t = self.tasks.get(r)
        if t is None or t.support:  # supporting: look for a frontier of its own again
            return True
        pose = P[r]
        if np.hypot(*(pose[:2] - t.goal)) < self.goal_reached_m:
            if any(np.hypot(*(f.goal - t.goal)) < self.frontier_gone_m for f in self.frontiers):
                # looked at from where it is and still there: in the cleanup it stays as
                # it is; otherwise given up once robots stood at it `max_failures` steps,
                # as explore_lite blacklists a goal it makes no progress on (random:2
                # seed 2, greedy: one drone hovered 0.2 m from the frontier all three
                # chose, the other two held behind it, and nothing moved for 400 s)
                self.give_up.failed(t.goal, self.give_up.max_failures if self.cleanup else 1)
            return True
        if not any(np.hypot(*(f.goal - t.goal)) < self.frontier_gone_m for f in self.frontiers):
            return True  # explored meanwhile, or no longer a frontier
        rest = self._remaining(r, pose)
        if self._conflict(r, rest, P):  # another robot would come too close
            log.debug("robot %s: its path now comes too close to another robot", r)
            return True
        clear, escape = self.planner.robot_clearance_m, self.planner.start_escape_m
        if comes_near(rest, list(self.silent.values()), clear, escape):
            return True  # across a silent robot's way
        # the rest of the path must still be free: after the next waypoint of all else,
        # up to it of walls (a robot leaving one's inflation flies inside it there)
        if len(rest) > 1 and path_length(rest[:2]) > 0.25:
            ahead = np.vstack([points_along(rest[:2], np.array([0.25])), rest[1:2]])
            if not pm.walls_free(ahead):
                return True
        return not pm.segment_free(rest[1:] if len(rest) > 1 else rest)

    def restore_task(self, robot: str, path: ArrayLike) -> None:
        """After a restart: the robot is following `path` ((N, 2), map frame) to its end."""
        p = np.asarray(path, dtype=np.float64).reshape(-1, 2)
        self.tasks[robot] = _Task(p[-1].copy(), p)

    def release(self, robot: str, pose: ArrayLike | None = None, stopped: bool = False) -> None:
        """Forget a robot's goal. `pose`: it went silent there (its link lost) and may fly
        on: the rest of its path and its end, where it will hover, are kept clear of the
        others (`silent`, as discs in their plans) until it is heard again (its agent
        `stopped`: where it hovers); else (a new run of it) its goal is free at once."""
        task = self.tasks.pop(robot, None)
        self.silent.pop(robot, None)
        if pose is not None:
            p = np.asarray(pose, dtype=np.float64)[None, :2]
            rest = task.path[nearest_leg(task.path, p[0]) + 1 :] if task and not stopped else p[:0]
            self.silent[robot] = np.vstack([p, rest])
            (log.debug if stopped else log.warning)("robot %s %s at %s: its way (%.1f m) kept "
                "clear", robot, "stopped" if stopped else "silent", np.round(p[0], 2),
                path_length(self.silent[robot]))  # fmt: skip
        self.assigner.release(robot)
