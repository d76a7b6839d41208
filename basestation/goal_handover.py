"""Handing a goal over: a robot free for a new goal that is nearer another robot's goal
than that robot is takes part in the joint assignment with it (`ExplorationManager`).

Robots keep the goal they fly to until they reach it or it goes (eq. 3's `w3` is
against switching), so a robot sent far across the map keeps flying there even when
another robot, freed a step later, stands much nearer: rooms15 seed 0 (kinematic), a
drone sent 13.7 m east along the corridor past a drone that had just lost its goal
7 m from there; the one left behind found no way past the other's route and hovered
for 6 s while the team's coverage stood still. Such a flying robot is assigned
again in the same step as the free one, jointly (the Hungarian method, eq. 3 and the
tours): the free robot takes the far goal if that is cheaper for the team, and the
other the frontiers near it.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from basestation.path_planner import path_length
from basestation.travel_distance import travel_distances
from common.map_io import GridMap

if TYPE_CHECKING:
    from basestation.exploration import ExplorationManager

log = logging.getLogger("basestation.exploration")


def handovers(
    m: ExplorationManager, need: list[str], grid: GridMap, P: dict[str, NDArray[np.float64]]
) -> list[str]:
    """The robots flying to a frontier goal (not a support move) that one of `need`
    (robots about to be assigned goals in this step) can reach by travel on `grid`
    more than `m.handover_m` sooner than they will by the rest of their path: they are
    assigned again with `need`. None when not coordinated or `handover_m` is 0. Each m
    of that travel through unknown space counts `m.handover_unknown` times: counted as
    free, the unseen outside of a building made ways no robot could fly (random:6 seed
    1, a mission: 12.5 m through it to a room whose one door was 21.5 m round; the goal
    went back and forth between two robots while the room waited)."""
    if not (m.coordinated and m.handover_m > 0.0 and need):
        return []
    flying = sorted(o for o, t in m.tasks.items() if o in P and o not in need and not t.support)
    if not flying:
        return []
    goals = np.array([m.tasks[o].goal for o in flying])
    starts = np.array([P[r][:2] for r in need])
    c, k = m.planner.robot_radius_m, m.handover_unknown
    nearest = travel_distances(grid, starts, goals, c, k).min(axis=0)
    out = []
    for o, d in zip(flying, nearest, strict=True):
        left = path_length(m._remaining(o, P[o]))
        if d + m.handover_m < left:  # inf (no way there) never is
            log.debug("robot %s: %.1f m left to its goal, a free robot %.1f m", o, left, d)
            out.append(o)
    return out
