"""Robots gone silent, and walls that come up across a robot's way.

An agent whose link to the base station is lost flies on along its path and hovers at
its end (docs/architecture.md, Liveliness). Its goal used to be released and its state
forgotten, so the next step sent another drone to the very spot it was heading for
(kinematic rooms15 with one link cut for 38 s: drones 0.02-0.45 m apart, 4 seeds of 4).
"""

from __future__ import annotations

import numpy as np

from basestation.exploration_setup import make_explorer
from basestation.path_planner import PlanningMap
from common.config import load_config
from common.map_io import GridMap

RES = 0.05


def corridor(length_cells: int = 400, known_cells: int = 220) -> GridMap:
    """A corridor 5 m wide along x, known free up to `known_cells`, unknown beyond."""
    data = np.full((120, length_cells), -1, np.int8)
    data[10:110, :known_cells] = 0
    data[:10, :known_cells] = 100
    data[110:, :known_cells] = 100
    data[:, :4] = 100
    return GridMap(data, RES, (0.0, 0.0, 0.0))


def test_a_silent_robots_way_and_goal_are_kept_from_the_others() -> None:
    grid = corridor()
    ex = make_explorer(load_config(), simulated=True)
    P = {"a": np.array([7.0, 3.0, 0.0]), "b": np.array([1.5, 3.0, 0.0])}
    ex.step(grid, P)
    goal_a, path_a = ex.tasks["a"].goal.copy(), ex.tasks["a"].path.copy()
    ex.release("a", P["a"])  # its link is lost where it was last heard of
    assert "a" not in ex.tasks and np.allclose(ex.silent["a"][-1], goal_a)
    out = ex.step(grid, {"b": P["b"]})
    pb = out.get("b")
    assert pb is None or np.hypot(*(pb[-1] - goal_a)) > 1.5
    if pb is not None:  # nowhere within the clearance of a's way
        pm = PlanningMap(grid, 0.0, [path_a], ex.planner.robot_clearance_m - 0.05)
        assert pm.segment_free(pb[2:])
    # heard again: its way is no longer held, and it gets a path of its own
    out = ex.step(grid, {"b": P["b"], "a": np.array([9.0, 3.0, 0.0])})
    assert "a" not in ex.silent and out.get("a") is not None


def test_a_robot_gone_for_good_frees_its_goal_at_once() -> None:
    grid = corridor()
    ex = make_explorer(load_config(), simulated=True)
    P = {"a": np.array([7.0, 3.0, 0.0]), "b": np.array([1.5, 3.0, 0.0])}
    ex.step(grid, P)
    ex.release("a")  # a new run of it: not flying on
    assert not ex.silent
    out = ex.step(grid, {"b": P["b"]})
    assert out.get("b") is not None


def test_a_silent_robot_already_on_anothers_way_gets_that_one_a_new_path() -> None:
    grid = corridor()
    ex = make_explorer(load_config(), simulated=True)
    ex.restore_task("b", np.array([[1.5, 3.0], [10.5, 3.0]]))
    ex.release("a", np.array([6.0, 3.0, 0.0]))  # hovering on b's way, silent
    out = ex.step(grid, {"b": np.array([1.5, 3.0, 0.0])})
    assert "b" in out  # re-planned (round it, or held)
    if out["b"] is not None:
        assert np.hypot(*(out["b"] - [6.0, 3.0]).T).min() >= ex.planner.robot_clearance_m - 0.05


def test_a_wall_across_the_leg_being_flown_gets_a_new_path() -> None:
    """The base station keeps the planner's legs (several m long); the rest of a path was
    checked only from its next waypoint on, so a wall seen across the leg the robot was
    on was left to its safety guard (held, 2 s, reported blocked)."""
    data = np.full((120, 400), -1, np.int8)
    data[10:110, :380] = 0
    data[:10, :] = 100
    data[110:, :] = 100
    ex = make_explorer(load_config(), simulated=True)
    ex.restore_task("a", np.array([[1.0, 3.0], [19.0, 3.0]]))
    open_grid = GridMap(data.copy(), RES, (0.0, 0.0, 0.0))
    assert ex.step(open_grid, {"a": np.array([1.5, 3.0, 0.0])}) == {}  # free: kept
    data[:, 150:156] = 100  # a wall across the corridor at x = 7.5 m
    out = ex.step(GridMap(data, RES, (0.0, 0.0, 0.0)), {"a": np.array([1.5, 3.0, 0.0])})
    assert "a" in out  # a new path (or a hold), not the old one through the wall
