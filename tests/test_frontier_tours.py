"""Min-max frontier tours (basestation/frontier_tours.py) and their goal cost term."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from basestation.exploration import ExplorationManager, _Task
from basestation.frontier_tours import minmax_tours
from basestation.frontiers import Frontier
from basestation.goal_costs import tour_shares
from common.map_io import GridMap


def _dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.hypot(*(a[:, None, :] - b[None, :, :]).transpose(2, 0, 1))


def _tour_length(S: np.ndarray, C: np.ndarray, r: int, tour: list[int]) -> float:
    if not tour:
        return 0.0
    return float(S[r, tour[0]] + sum(C[a, b] for a, b in itertools.pairwise(tour)))


def _brute_force(S: np.ndarray, C: np.ndarray) -> float:
    R, N = S.shape
    best = np.inf
    for owner in itertools.product(range(R), repeat=N):
        worst = 0.0
        for r in range(R):
            mine = [j for j in range(N) if owner[j] == r]
            if mine:
                worst = max(
                    worst, min(_tour_length(S, C, r, list(p)) for p in itertools.permutations(mine))
                )
        best = min(best, worst)
    return best


@pytest.mark.parametrize("seed", range(6))
def test_small_instances_reach_the_optimum(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R, N = (2, 6) if seed % 2 else (3, 5)
    robots, frontiers = rng.uniform(0, 20, (R, 2)), rng.uniform(0, 20, (N, 2))
    S, C = _dist(robots, frontiers), _dist(frontiers, frontiers)
    tours, lengths = minmax_tours(np.zeros(R), S, C)
    assert sorted(sum(tours, [])) == list(range(N))  # every frontier once
    for r, t in enumerate(tours):
        assert lengths[r] == pytest.approx(_tour_length(S, C, r, t))
    assert lengths.max() <= _brute_force(S, C) * 1.05 + 1e-9


def test_two_rooms_two_robots_one_room_each() -> None:
    """Frontiers in a row along a corridor and two robots at one end: a nearest-first
    rule sends both the same way; the tours split the row between them."""
    frontiers = np.array([[x, 0.0] for x in (2.0, 4.0, 6.0, 8.0)] + [[-x, 0.0] for x in (2.0, 4.0)])
    robots = np.array([[0.0, 0.5], [0.0, -0.5]])
    tours, lengths = minmax_tours(
        np.zeros(2), _dist(robots, frontiers), _dist(frontiers, frontiers)
    )
    east, west = {0, 1, 2, 3}, {4, 5}
    assert {frozenset(t) for t in tours} == {frozenset(east), frozenset(west)}
    assert lengths.max() == pytest.approx(np.hypot(2.0, 0.5) + 6.0)  # east, in order


def test_a_robot_still_on_its_way_gets_less() -> None:
    frontiers = np.array([[float(x), 0.0] for x in range(1, 7)])
    robots = np.zeros((2, 2))
    S, C = _dist(robots, frontiers), _dist(frontiers, frontiers)
    tours, _ = minmax_tours(np.array([0.0, 0.0]), S, C)
    busy, _ = minmax_tours(np.array([0.0, 5.0]), S, C)
    assert len(busy[1]) < max(len(t) for t in tours) or not busy[1]
    assert sorted(sum(busy, [])) == list(range(6))


def test_unreachable_pairs_and_empty_inputs() -> None:
    S = np.array([[1.0, np.inf], [np.inf, 1.0]])
    C = np.array([[0.0, np.inf], [np.inf, 0.0]])
    tours, lengths = minmax_tours(np.zeros(2), S, C)
    assert tours == [[0], [1]] and np.all(np.isfinite(lengths))
    assert minmax_tours(np.zeros(2), np.zeros((2, 0)), np.zeros((0, 0)))[0] == [[], []]
    assert minmax_tours(np.zeros(0), np.zeros((0, 3)), np.zeros((3, 3)))[0] == []


def test_tour_shares_marks_each_frontier_for_one_robot() -> None:
    frontiers = np.array([[2.0, 0.0], [4.0, 0.0], [-2.0, 0.0], [-4.0, 0.0]])
    robots = np.array([[1.0, 0.0], [-1.0, 0.0]])
    D, C = _dist(robots, frontiers), _dist(frontiers, frontiers)
    on = tour_shares(np.zeros(2), D, C)
    assert on.sum(axis=0).tolist() == [1, 1, 1, 1]
    assert on[0].tolist() == [True, True, False, False]
    # the robot on the east still has 20 m to fly: the west one takes everything
    assert tour_shares(np.array([20.0, 0.0]), D, C)[1].all()


def test_a_robot_takes_no_frontier_from_another_robots_tour() -> None:
    """One frontier B, 3 m past the goal o is about to reach (1.5 m on) and 7 m from r:
    it is on o's tour, so r gets no goal (it moves up behind the others) instead of
    flying 7 m to a frontier o will see first; without tours r takes it."""
    g = GridMap(np.zeros((240, 240), np.int8), 0.05, (0.0, 0.0, 0.0))
    b = np.array([5.0, 2.0])
    P = {"o": np.array([0.5, 2.0, 0.0]), "r": np.array([5.0, 9.0, 0.0])}
    goals = []
    for tours in (True, False):
        ex = ExplorationManager(w_spread=0.0, seen_cost_m=0.0, tours=tours)
        ex.frontiers = [Frontier(b, b, 20)]
        ex.tasks["o"] = _Task(np.array([2.0, 2.0]), np.array([[0.5, 2.0], [2.0, 2.0]]))
        goals.append(ex._goals({"r": P["r"]}, g, P)["r"])
    assert goals[0] is None
    assert goals[1] is not None and np.allclose(goals[1], b)
