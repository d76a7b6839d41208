"""A frontier that stays where a robot stands is given up, as explore_lite blacklists a
goal it makes no progress on: it does not hold the robot there for the whole mission."""

from __future__ import annotations

import numpy as np
import pytest

from basestation.exploration import ExplorationManager
from basestation.frontier_give_up import FrontierGiveUp
from basestation.frontiers import FrontierDetector
from basestation.path_planner import PathPlanner
from common.map_io import GridMap


def _room_with_an_unknown_pocket() -> GridMap:
    """10 x 10 m known free inside walls, a 1 m unknown pocket in the middle: a frontier
    round it that the (unchanging) map never clears."""
    data = np.zeros((200, 200), np.int8)
    data[[0, -1], :] = data[:, [0, -1]] = 100
    data[90:110, 90:110] = -1
    return GridMap(data, 0.05, (0.0, 0.0, 0.0))


@pytest.mark.parametrize("coordinated", [False, True])
def test_a_frontier_still_there_when_robots_stand_at_it_is_given_up(coordinated: bool) -> None:
    grid = _room_with_an_unknown_pocket()
    mgr = ExplorationManager(
        detector=FrontierDetector(radius_m=0.3, min_group_cells=8),
        planner=PathPlanner(inflation_m=0.25, robot_clearance_m=0.8, time_budget_s=0.05),
        give_up=FrontierGiveUp(max_failures=4),
        coordinated=coordinated,
    )
    pose = np.array([2.0, 2.0, 0.0])
    arrivals: dict[tuple[float, float], int] = {}
    for _ in range(60):
        paths = mgr.step(grid, {"r0": pose})
        if mgr.done:
            break
        path = paths.get("r0")
        if path is not None:
            pose = np.array([*path[-1], 0.0])  # flown there at once; the map stays as it is
            key = (round(float(path[-1][0]), 1), round(float(path[-1][1]), 1))
            arrivals[key] = arrivals.get(key, 0) + 1
    assert mgr.done, f"{len(mgr.frontiers)} frontiers left, goals {arrivals}"
    assert arrivals and max(arrivals.values()) <= 4 + 1  # each given up after 4 steps at it
