"""Support moves: a robot left without a frontier of its own moves up behind the others
(`ExplorationManager.step`), so that it waits near where the map is growing instead of
where it happened to stop, ready for the frontiers that open up there."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from basestation.path_planner import path_length
from basestation.path_schedule import points_along
from basestation.travel_distance import travel_distances
from common.map_io import GridMap

if TYPE_CHECKING:
    from basestation.exploration import ExplorationManager


def support_move(
    m: ExplorationManager, r: str, grid: GridMap, P: dict[str, NDArray[np.float64]]
) -> NDArray[np.float64] | None:
    """Robot r's path toward the nearest frontier (taken by another robot, or one it
    could not plan to) that stops where it keeps twice the robot clearance from every
    other robot's goal and, flown in time, from the others (`m._conflict`); None if no
    such path is at least `m.support_min_m` long. Of the three nearest frontiers by
    travel, the first with a path that is no long way round another robot."""
    goals = np.array([f.goal for f in m.frontiers])
    dist = travel_distances(grid, P[r][None, :2], goals, m.planner.robot_radius_m)[0]
    discs = m._discs(r, P)
    others = [t.goal for o, t in m.tasks.items() if o != r]
    keep = 2.0 * m.planner.robot_clearance_m
    for j in np.argsort(dist)[:3]:
        if not np.isfinite(dist[j]):
            break
        path = m.planner.plan(grid, P[r][:2], goals[j], discs)
        if path is None or (len(P) > 1 and m._too_long(path, dist[j])):
            continue  # none, or only the long way round another robot
        length = path_length(path)
        for cut in np.arange(length - keep, m.support_min_m - 1e-9, -0.5):
            prefix = points_along(path, np.linspace(0.0, cut, max(2, int(cut / 0.25) + 1)))
            end = prefix[-1]
            if any(np.hypot(*(end - g)) < keep for g in others):
                continue
            if not m._conflict(r, prefix, P):
                return prefix
    return None
