"""Frontier goals for the robots (seed 002 §1.2, eq. 3).

Each robot k at pose x_k = [x, y, yaw] gets the frontier f minimizing
    w1 |x_k - f|_t + w2 |x_k - f|_theta + w3 |f - f_prev_k|_t
(distance, heading change to face f, distance from the robot's previous goal, which
anchors the goal and stops it switching between frontiers of similar cost). The
robots are assigned jointly (Hungarian method on the cost matrix), so no two robots
get the same goal: a goal given to one robot leaves the queue for the others. A
robot whose previous goal vanished (explored, or no longer a frontier) gets the best
remaining one; with more robots than frontiers, the ones left over get none (they
wait: exploration halts for them until a new map brings frontiers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from common.errors import ConfigError
from common.geometry import wrap_angle


@dataclass(frozen=True)
class AssignmentWeights:
    w_distance: float = 1.0  # w1, per m
    w_heading: float = 0.5  # w2, per rad
    w_previous: float = 0.5  # w3, per m from the previous goal

    def __post_init__(self) -> None:
        if min(self.w_distance, self.w_heading, self.w_previous) < 0:
            raise ConfigError("goal assignment weights must be >= 0")


UNREACHABLE_COST = 1e6  # a frontier a robot cannot reach: assigned only if nothing else is
FORBIDDEN_COST = 1e9  # a pair `assign` must not make: above any other, and then dropped


def assignment_costs(
    poses: NDArray[np.float64],
    frontiers: NDArray[np.float64],
    previous: list[NDArray[np.float64] | None],
    w: AssignmentWeights,
    distances: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """(robots, frontiers) matrix of eq. 3; `distances` (robots, frontiers), m, replaces
    the straight-line distance term (travel distances; inf = unreachable)."""
    d = frontiers[None, :, :] - poses[:, None, :2]
    dist = np.hypot(d[..., 0], d[..., 1]) if distances is None else distances
    heading = np.abs(wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - poses[:, None, 2]))
    prev = np.zeros_like(dist)
    for k, p in enumerate(previous):
        if p is not None:
            prev[k] = np.hypot(*(frontiers - np.asarray(p)[None, :2]).T)
    cost = w.w_distance * dist + w.w_heading * heading + w.w_previous * prev
    return np.where(np.isfinite(cost), cost, UNREACHABLE_COST)


def own_ground(
    everyone: NDArray[np.float64], mine: NDArray[np.float64], rows: list[int], cap_m: float
) -> NDArray[np.float64]:
    """(len(rows), frontiers) m by which each frontier is closer to robot `rows[k]`
    (its distances `mine[k]`) than to every other robot (`everyone`: all robots' travel
    distances, one row each), up to `cap_m`; 0 where another is as close. A side room
    a robot passes is its to take now, not left for a far one to come back for."""
    out = np.zeros_like(mine)
    if len(everyone) < 2:
        return out
    for k, i in enumerate(rows):
        others = np.delete(everyone, i, axis=0).min(axis=0)
        with np.errstate(invalid="ignore"):  # (inf - inf: reachable by none, 0)
            out[k] = np.nan_to_num(np.clip(others - mine[k], 0.0, cap_m))
    return out


def spaced(
    goals: dict[str, NDArray[np.float64] | None], way_m: dict[str, float], apart_m: float
) -> tuple[dict[str, NDArray[np.float64] | None], list[str]]:
    """Goals of one joint assignment with none within `apart_m` of another: the robot
    with the shorter way (`way_m`) keeps its goal. Returns the goals kept (None for the
    others) and the robots that lost theirs (to be assigned again)."""
    kept: dict[str, NDArray[np.float64] | None] = {r: None for r in goals}
    again: list[str] = []
    for r in sorted((r for r in goals if goals[r] is not None), key=lambda r: (way_m[r], r)):
        g = goals[r]
        assert g is not None
        if any(k is not None and np.hypot(*(g - k)) <= apart_m for k in kept.values()):
            again.append(r)
        else:
            kept[r] = g
    return kept, again


class GoalAssigner:
    def __init__(self, weights: AssignmentWeights | None = None) -> None:
        self.weights = weights or AssignmentWeights()
        self.goals: dict[str, NDArray[np.float64]] = {}  # current goal per robot

    def assign(
        self,
        poses: dict[str, ArrayLike],
        frontiers: list[ArrayLike],
        distances: dict[str, NDArray[np.float64]] | None = None,
        extra_costs: NDArray[np.float64] | None = None,
        forbidden: dict[str, NDArray[np.bool_]] | None = None,
    ) -> dict[str, NDArray[np.float64] | None]:
        """Goals [x, y] (or None: nothing left for it) for every robot in `poses`.

        `distances[robot]`: travel distance (m) to each frontier, replacing the straight
        line; `extra_costs`: per-frontier cost added for every robot (spreading);
        `forbidden[robot]`: frontiers that robot must not get (it gets none rather)."""
        robots = sorted(poses)
        if not robots:
            return {}
        if not frontiers:
            self.goals.clear()
            return {r: None for r in robots}
        P = np.array([np.asarray(poses[r], dtype=np.float64)[:3] for r in robots])
        F = np.array([np.asarray(f, dtype=np.float64)[:2] for f in frontiers])
        prev = [self.goals.get(r) for r in robots]
        D = None if distances is None else np.array([distances[r] for r in robots])
        cost = assignment_costs(P, F, prev, self.weights, D)
        if extra_costs is not None:
            cost = cost + np.asarray(extra_costs, dtype=np.float64)[None, :]
        banned = np.zeros(cost.shape, dtype=bool)
        if forbidden is not None:
            banned = np.array([forbidden[r] for r in robots], dtype=bool).reshape(cost.shape)
            cost = np.where(banned, FORBIDDEN_COST, cost)
        rows, cols = linear_sum_assignment(cost)
        out: dict[str, NDArray[np.float64] | None] = {r: None for r in robots}
        for i, j in zip(rows, cols, strict=True):
            if not banned[i, j]:
                out[robots[i]] = F[j].copy()
        self._remember(out)
        return out

    def nearest(
        self, poses: dict[str, ArrayLike], frontiers: list[ArrayLike]
    ) -> dict[str, NDArray[np.float64] | None]:
        """Uncoordinated baseline (explore_lite): each robot its own nearest frontier,
        whatever the others chose."""
        out: dict[str, NDArray[np.float64] | None] = {r: None for r in poses}
        if frontiers:
            F = np.array([np.asarray(f, dtype=np.float64)[:2] for f in frontiers])
            for r, p in poses.items():
                xy = np.asarray(p, dtype=np.float64)[:2]
                out[r] = F[int(np.argmin(np.hypot(*(F - xy).T)))].copy()
        self._remember(out)
        return out

    def _remember(self, goals: dict[str, NDArray[np.float64] | None]) -> None:
        for r, g in goals.items():
            if g is None:
                self.goals.pop(r, None)
            else:
                self.goals[r] = g

    def release(self, robot: str) -> None:
        """Forget a robot's goal (it went silent); its frontier is free for the others."""
        self.goals.pop(robot, None)
