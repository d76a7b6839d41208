"""A free robot nearer another robot's far goal takes it over (`goal_handover`)."""

from __future__ import annotations

import numpy as np
import pytest

from basestation.exploration import ExplorationManager, _Task
from basestation.frontiers import FrontierDetector
from basestation.goal_handover import handovers
from basestation.path_planner import PathPlanner
from common.map_io import GridMap


def _corridor() -> GridMap:
    """A 24 x 8 m hall known free from x = 3 to 21 m, unknown at both ends: one
    frontier at each end."""
    data = np.full((160, 480), -1, np.int8)
    data[:, 60:420] = 0
    data[[0, 1, -2, -1], :] = 100  # the corridor's side walls
    return GridMap(data, 0.05, (0.0, 0.0, 0.0))


@pytest.mark.parametrize("handover_m", [0.0, 2.0])
def test_a_free_robot_near_a_far_goal_takes_it_over(handover_m: float) -> None:
    g = _corridor()
    m = ExplorationManager(
        detector=FrontierDetector(0.3, min_group_cells=8),
        planner=PathPlanner(inflation_m=0.35, robot_clearance_m=1.0, time_budget_s=0.2),
        handover_m=handover_m,
    )
    assert len(m.detector.update(g)) == 2  # one frontier at each end
    east = max((f.goal for f in m._approachable(m.detector.update(g), g)), key=lambda q: q[0])
    # robot a has just set off east across the whole hall; b, in the east and out of
    # a's way, is free
    P = {"a": np.array([5.0, 2.0, 0.0]), "b": np.array([17.0, 7.0, 0.0])}
    m.tasks["a"] = _Task(east, np.array([[4.5, 2.0], east]))
    out = m.step(g, P)
    assert out.get("b") is not None  # b got a path ...
    goal_b = m.tasks["b"].goal
    if handover_m == 0.0:  # ... to the west end, past a flying the other way
        assert "a" not in out and goal_b[0] < 5.0
        np.testing.assert_allclose(m.tasks["a"].goal, east)
    else:  # ... to a's goal, 5 m from it, and a turns back for the west end, 3 m away
        np.testing.assert_allclose(goal_b, east)
        assert out.get("a") is not None and m.tasks["a"].goal[0] < 5.0
        assert np.hypot(*(out["b"][-1] - east)) < 1e-9


@pytest.mark.parametrize("unknown_factor", [1.0, 3.0])
def test_a_way_through_unknown_space_is_charged_before_a_goal_is_handed_over(
    unknown_factor: float,
) -> None:
    """a flies the last ~9 m east to its goal; b, free, is 4.5 m from it in a straight
    line, 2 m of that through a band of unknown (a building's unseen outside): charged
    3x, b is no longer nearer by the 2 m a handover needs."""
    g = _corridor()
    g.data[:, 360:400] = -1  # x = 18-20 m unknown across the hall
    m = ExplorationManager(
        planner=PathPlanner(inflation_m=0.35, robot_clearance_m=1.0, time_budget_s=0.2),
        handover_unknown=unknown_factor,
    )
    goal = np.array([21.5, 4.0])
    P = {"a": np.array([12.5, 4.0, 0.0]), "b": np.array([17.0, 4.0, 0.0])}
    m.tasks["a"] = _Task(goal, np.array([[12.5, 4.0], goal]))
    assert handovers(m, ["b"], g, P) == (["a"] if unknown_factor == 1.0 else [])
