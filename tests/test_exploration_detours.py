"""Detours around other robots through unknown space (`ExplorationManager._detour`)."""

from __future__ import annotations

import numpy as np
import pytest

from basestation.exploration import ExplorationManager, _Task
from basestation.path_planner import PathPlanner, unknown_length
from common.map_io import GridMap


def _door_and_unknown_floor() -> GridMap:
    """12 x 10 m inside outer walls; a wall at y = 5 m with a 1.2 m door at x = 2-3.2 m;
    a 3 x 4 m patch round x = 6-9 m, y = 3-7 m never seen (unknown), where the wall may
    or may not go on."""
    data = np.zeros((200, 240), np.int8)
    data[[0, -1], :] = data[:, [0, -1]] = 100
    data[100:102, :] = 100
    data[100:102, 40:64] = 0
    data[60:140, 120:180] = -1
    return GridMap(data, 0.05, (0.0, 0.0, 0.0))


@pytest.mark.parametrize("guess_m", [1.0, np.inf])
def test_a_way_round_another_robot_through_unknown_space_is_refused(guess_m: float) -> None:
    """b comes head-on through the door: a's way round b's route goes through the unseen
    patch, a guess about the wall that is not much longer. Refused (a waits, or takes
    another frontier) unless the guess is allowed."""
    g = _door_and_unknown_floor()
    m = ExplorationManager(planner=PathPlanner(0.35, 1.0, 0.2), guess_m=guess_m)
    goal = np.array([4.0, 8.0])
    P = {"a": np.array([2.6, 1.3, np.pi / 2]), "b": np.array([2.6, 7.0, -np.pi / 2])}
    m.tasks["b"] = _Task(np.array([2.6, 3.8]), np.array([[2.6, 7.0], [2.6, 3.8]]))
    alone = m.planner.plan(g, P["a"][:2], goal)
    assert alone is not None and unknown_length(g, alone) == 0.0  # through the door
    path = m._plan("a", goal, g, P)
    if np.isfinite(guess_m):
        assert path is None and m.detours_refused >= 1
        assert not m.give_up.failures  # the map does not block the goal: not given up
    else:
        assert path is not None and unknown_length(g, path) > 1.0
        assert m.detours_refused == 0
