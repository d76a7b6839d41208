"""Paths in time: a robot's turn on the spot before it sets off, and goals of one joint
assignment kept apart (the rest of the time-aware checks: test_exploration_coordination.py)."""

from __future__ import annotations

import numpy as np

from basestation.exploration import ExplorationManager, _Task
from basestation.frontiers import Frontier
from basestation.goal_assigner import spaced
from basestation.path_schedule import nearest_leg, schedule_conflict, turn_delay_s
from common.map_io import GridMap

AHEAD = np.array([[0.0, 0.0], [10.0, 0.0]])  # along +x from the origin


def test_turn_delay_counts_only_the_turn_beyond_the_free_angle() -> None:
    free = np.radians(82.5)
    assert turn_delay_s(np.array([0.0, 0.0, 0.0]), AHEAD, free, 1.0) == 0.0
    assert turn_delay_s(np.array([0.0, 0.0, np.radians(80.0)]), AHEAD, free, 1.0) == 0.0
    back = turn_delay_s(np.array([0.0, 0.0, np.pi]), AHEAD, free, 1.0)
    assert back == np.pi - free  # facing away: 97.5 degrees at 1 rad/s
    assert turn_delay_s(np.array([0.0, 0.0, -np.pi]), AHEAD, free, 2.0) == back / 2.0
    assert turn_delay_s(np.array([0.0, 0.0, 1.0]), AHEAD[:1], free, 1.0) == 0.0  # no way


def test_a_leader_that_turns_first_is_caught_up_and_a_follower_that_does_is_not() -> None:
    mine = np.array([[0.0, 0.0], [15.0, 0.0]])
    leader = np.array([[2.5, 0.0], [20.0, 0.0]])  # 2.5 m ahead, same way
    args = (1.0, 15.0, 0.5, 1.0, 0.0)  # speed, horizon, clearance, keep, lag
    assert not schedule_conflict(mine, mine[0], [leader], *args)
    assert schedule_conflict(mine, mine[0], [leader], *args, delays_s=[2.0])
    assert not schedule_conflict(mine, mine[0], [leader], *args, delays_s=[1.0])
    follower = np.array([[-2.5, 0.0], [12.0, 0.0]])
    assert not schedule_conflict(mine, mine[0], [follower], *args)
    assert schedule_conflict(mine, mine[0], [follower], *args, delay_s=2.0)  # I turn first


def test_a_robot_that_turns_first_keeps_its_allowance_near_its_start() -> None:
    """A 2 m hop with another robot hovering 1.3 m from the start: no conflict facing the
    way; turning first (1.7 s), its points near the start had been judged in full."""
    path, other = np.array([[0.0, 0.0], [2.0, 0.0]]), np.array([0.0, 1.3])
    args = (1.0, 15.0, 1.0, 1.5, 0.6, [0.0])  # speed, horizon, clearance, keep, lag, waits
    for yaw in (0.0, np.pi):
        pose = np.array([0.0, 0.0, yaw])
        delay = turn_delay_s(pose, path, np.radians(82.5), 1.0)
        assert not schedule_conflict(path, pose, [other], *args, delay), yaw


def test_the_rest_of_a_path_keeps_the_corner_just_ahead() -> None:
    """2.5 m before an L path's corner, the robot is nearer the corner than the waypoint
    behind it: the rest had been cut from the corner on, a straight line through the
    wall (3.9 m instead of 5.5 m)."""
    m = ExplorationManager()
    path = np.array([[-7.0, 0.5], [-4.0, 0.5], [-4.0, 3.0], [-1.0, 3.0]])
    m.tasks["a"] = _Task(path[-1], path)
    np.testing.assert_allclose(m._remaining("a", np.array([-5.2, 0.5, 0.0])), [
        [-5.2, 0.5], [-4.0, 0.5], [-4.0, 3.0], [-1.0, 3.0]])  # fmt: skip
    np.testing.assert_allclose(m._remaining("a", np.array([-4.0, 0.5 + 1.4, 0.0])), [
        [-4.0, 1.9], [-4.0, 3.0], [-1.0, 3.0]])  # fmt: skip
    assert nearest_leg(path[:1], np.array([5.0, 5.0])) == 0  # (one waypoint: its own)


def test_the_manager_reads_the_turn_from_each_robots_heading() -> None:
    """b, 2.5 m ahead of a on a's way, sets off along it: in time if it faces that way,
    ~1.7 s late (plus the 1.2 s it may lag anyway) if it must first turn round."""
    m = ExplorationManager(speed_mps=1.0, horizon_s=15.0, conflict_margin=1.0)
    m.planner.robot_clearance_m = 1.0
    mine = np.array([[0.0, 0.0], [15.0, 0.0]])
    m.tasks["b"] = _Task(np.array([20.0, 0.0]), np.array([[2.5, 0.0], [20.0, 0.0]]))
    P = {"a": np.array([0.0, 0.0, 0.0]), "b": np.array([2.5, 0.0, 0.0])}
    assert not m._conflict("a", mine, P)
    P["b"] = np.array([2.5, 0.0, np.pi])
    assert m._conflict("a", mine, P)
    m.turn_rate_rps = 0.0  # not modelled
    assert not m._conflict("a", mine, P)


def test_of_two_goals_too_close_the_robot_with_the_longer_way_gives_its_up() -> None:
    goals = {"r": np.array([5.0, 5.0]), "s": np.array([5.0, 6.37]), "t": np.array([9.0, 1.0])}
    kept, again = spaced(goals, {"r": 3.0, "s": 3.2, "t": 9.0}, 1.5)
    assert again == ["s"] and kept["s"] is None
    assert np.allclose(kept["r"], goals["r"]) and np.allclose(kept["t"], goals["t"])
    kept, again = spaced(goals, {"r": 3.0, "s": 3.2, "t": 9.0}, 1.0)
    assert again == [] and all(kept[k] is not None for k in goals)


def test_one_joint_assignment_never_sends_two_robots_to_hover_side_by_side() -> None:
    """random:1, seed 6 (kinematic model): two robots were sent to frontiers 1.37 m
    apart; the one that would have got there last then conflicted with the other's
    hover, lost its goal to the busy radius of the other, and the team stalled. Now s
    never gets a2: without tours it gets c; with them c is on r's tour (a then c, 8.7 m,
    against 9.2 m for s), so s gets no goal and moves up behind."""
    g = GridMap(np.zeros((200, 200), np.int8), 0.05, (0.0, 0.0, 0.0))
    a, a2, c = np.array([5.0, 5.0]), np.array([5.0, 6.37]), np.array([9.0, 1.0])
    P = {"r": np.array([2.0, 5.0, 0.0]), "s": np.array([2.0, 7.0, 0.0])}
    for tours in (False, True):
        ex = ExplorationManager(w_spread=0.0, seen_cost_m=0.0, w_own=0.0, w_gain=0.0, tours=tours)
        ex.frontiers = [Frontier(f, f, 20) for f in (a, a2, c)]
        goals = ex._goals(P, g, P)
        assert np.allclose(goals["r"], a)
        assert goals["s"] is None if tours else np.allclose(goals["s"], c)
