"""Goal assignment (seed 002 eq. 3)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from basestation.goal_assigner import (
    AssignmentWeights,
    GoalAssigner,
    assignment_costs,
    own_ground,
)
from common.errors import ConfigError


def test_joint_assignment_minimizes_the_summed_cost() -> None:
    ga = GoalAssigner()
    goals = ga.assign({"a": [0, 0, 0], "b": [10, 0, np.pi]}, [[12, 0], [-2, 0], [5, 8]])
    # 2 m behind each robot (2 + 0.5 pi each) beats 12 m ahead of it, and [5, 8]
    np.testing.assert_allclose(goals["a"], [-2, 0])
    np.testing.assert_allclose(goals["b"], [12, 0])


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 5),
    st.integers(0, 8),
    st.integers(0, 10_000),
)
def test_two_robots_never_get_the_same_goal(n_robots: int, n_frontiers: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    poses = {f"r{k}": [*rng.uniform(-10, 10, 2), rng.uniform(-3, 3)] for k in range(n_robots)}
    frontiers = [rng.uniform(-10, 10, 2) for _ in range(n_frontiers)]
    goals = GoalAssigner().assign(poses, frontiers)
    given_goals = [tuple(g) for g in goals.values() if g is not None]
    assert len(given_goals) == len(set(given_goals)) == min(n_robots, n_frontiers)


def test_previous_goal_anchors_against_switching() -> None:
    w = AssignmentWeights(w_distance=1.0, w_heading=0.0, w_previous=1.0)
    ga = GoalAssigner(w)
    ga.assign({"a": [0, 0, 0]}, [[5, 0], [-5.5, 0]])
    # the robot drifted a little towards the other frontier: it keeps its goal
    goals = ga.assign({"a": [-0.4, 0, 0]}, [[5, 0], [-5.5, 0]])
    np.testing.assert_allclose(goals["a"], [5, 0])


def test_a_forbidden_frontier_is_never_given_even_when_nothing_else_is_left() -> None:
    ga = GoalAssigner()
    poses = {"a": [0, 0, 0], "b": [10, 0, np.pi]}
    frontiers = [[1, 0], [9, 0]]
    goals = ga.assign(
        poses, frontiers, forbidden={"a": np.array([True, False]), "b": np.zeros(2, bool)}
    )
    # a may not take [1, 0], its nearest: it takes [9, 0], and b the one left
    np.testing.assert_allclose(goals["a"], [9, 0])
    np.testing.assert_allclose(goals["b"], [1, 0])
    goals = ga.assign(
        poses, frontiers[:1], forbidden={"a": np.array([True]), "b": np.array([True])}
    )
    assert goals == {"a": None, "b": None}
    assert ga.goals == {}  # nothing given, nothing remembered


def test_vanished_goal_gets_a_pending_one_and_no_frontier_halts() -> None:
    ga = GoalAssigner()
    ga.assign({"a": [0, 0, 0]}, [[3, 0], [0, 7]])
    goals = ga.assign({"a": [1, 0, 0]}, [[0, 7]])  # [3, 0] was explored
    np.testing.assert_allclose(goals["a"], [0, 7])
    assert ga.assign({"a": [1, 0, 0]}, []) == {"a": None}
    assert ga.goals == {}


def test_costs_and_bad_weights() -> None:
    c = assignment_costs(
        np.array([[0.0, 0.0, 0.0]]),
        np.array([[0.0, 2.0]]),
        [np.array([0.0, 5.0])],
        AssignmentWeights(1.0, 2.0, 3.0),
    )
    assert c[0, 0] == pytest.approx(2.0 + 2.0 * np.pi / 2 + 3.0 * 3.0)
    with pytest.raises(ConfigError):
        AssignmentWeights(w_heading=-1.0)


def test_own_ground_is_the_lead_over_the_nearest_other_robot_capped() -> None:
    inf = np.inf
    everyone = np.array([[2.0, 6.0, 30.0, inf], [5.0, 4.0, 40.0, 3.0], [9.0, 1.0, inf, inf]])
    gain = own_ground(everyone, everyone[[0, 1]], [0, 1], cap_m=10.0)
    assert np.allclose(gain[0], [3.0, 0.0, 10.0, 0.0])  # leads by 3; behind; capped; none
    assert np.allclose(gain[1], [0.0, 0.0, 0.0, 10.0])  # only robot 1 reaches the last one
    assert not own_ground(everyone[:1], everyone[:1], [0], 10.0).any()  # alone: no others
