"""LoopClosureManager on generated two-robot graphs: PCM in front of iSAM2.

Two robots fly the same 5 m square (1 m steps) from different, unknown-to-each-
other starts. Verified matches arrive one by one; wrong ones must stay out of the
graph (or leave it once the majority disagrees), right ones must join the maps.
"""

from __future__ import annotations

import numpy as np
import pytest

from basestation.loop_closure_manager import LoopClosureManager, invert_with_covariance
from basestation.pose_graph import PoseGraph
from common.config import ConstraintConfig
from common.geometry import se2_between, se2_compose, wrap_angle

ODO_COV = np.diag([0.02**2, 0.02**2, 0.005**2])
LC_COV = np.diag([0.03**2, 0.03**2, 0.01**2])
START_B = np.array([0.4, -0.3, 0.2])  # truth; robot b's chain floats in its own frame


def _square(n_laps: int = 1) -> list[np.ndarray]:
    return [
        np.array([1.0, 0.0, np.pi / 2 if k % 5 == 0 else 0.0]) for k in range(1, 20 * n_laps + 1)
    ]


def _truth(start: np.ndarray, deltas: list[np.ndarray]) -> np.ndarray:
    P = [start]
    for d in deltas:
        P.append(se2_compose(P[-1], d))
    return np.array(P)


def _setup(
    rng: np.random.Generator,
    cfg: ConstraintConfig | None = None,
    third: bool = False,
    third_known: bool = True,
    graph: PoseGraph | None = None,
):
    """Robots a (known start) and b (floating); with `third`, c too (known start: on
    a's map, unless not `third_known`), flying the square from 1 m to the side of b's
    start."""
    deltas = _square()
    truth = {"a": _truth(np.zeros(3), deltas), "b": _truth(START_B, deltas)}
    starts = [("a", np.zeros(3)), ("b", None)]
    if third:
        truth["c"] = _truth(START_B + [1.0, 0.0, 0.0], deltas)
        starts.append(("c", truth["c"][0] if third_known else None))
    graph = graph or PoseGraph()
    for rid, start in starts:
        graph.add_robot(rid, start)
        graph.add_node(rid, 0, None, None)
        for k, d in enumerate(deltas, start=1):
            noisy = d + rng.normal(0.0, 1.0, 3) * np.sqrt(np.diag(ODO_COV))
            graph.add_node(rid, k, noisy, ODO_COV)
    graph.update()

    def chain_cov(robot: str, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        # n steps of odometry, plus the heading uncertainty swept over n metres
        n = np.abs(np.asarray(j) - np.asarray(i))[:, None, None]
        return n * ODO_COV + n**2 * ODO_COV[2, 2] * np.diag([1.0, 1.0, 0.0])

    # 1 m between nodes, not ~0.3 m: each match counts toward a merge (the stretch rule
    # has its own test)
    cfg = cfg or ConstraintConfig()
    cfg.merge_stretch_keyframes = 1
    manager = LoopClosureManager(graph, cfg, chain_cov)
    return graph, manager, truth


def _true_T(truth, a, b):
    return se2_between(truth[a[0]][a[1]], truth[b[0]][b[1]])


def _max_error(graph: PoseGraph, truth) -> float:
    return max(
        float(np.linalg.norm(graph.poses(r)[:, :2] - truth[r][:, :2], axis=1).max()) for r in truth
    )


def test_wrong_inter_robot_match_in_a_two_robot_square_is_rejected() -> None:
    rng = np.random.default_rng(3)
    graph, manager, truth = _setup(rng)
    wrong = se2_compose(_true_T(truth, ("a", 10), ("b", 10)), [1.5, -1.0, 0.6])
    manager.add(("a", 10), ("b", 10), wrong, LC_COV, "inter")
    graph.update()
    assert not graph.is_anchored("b"), "one match alone must not join two maps"
    for i, j in [(2, 2), (7, 8), (15, 14), (18, 18)]:
        manager.add(("a", i), ("b", j), _true_T(truth, ("a", i), ("b", j)), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert manager.counts() == {
        "loop_closures": 0,
        "inter_robot_constraints": 4,
        "rejected_by_pcm": 1,
    }
    assert _max_error(graph, truth) < 0.3  # both chains drift by ~0.15 m


def _one_wrong_loop(error: list[float]):
    """Two robots' chains (`_setup`) and robot a's loop 0 -> 20 offered with `error`."""
    graph, manager, truth = _setup(np.random.default_rng(5))
    wrong = se2_compose(_true_T(truth, ("a", 0), ("a", 20)), error)
    manager.add(("a", 0), ("a", 20), wrong, LC_COV, "loop")
    graph.update(extra_iterations=5)
    return graph, manager, truth


def test_a_wrong_loop_closure_leaves_the_graph_when_right_ones_disagree() -> None:
    # wrong by 0.36 m: within what 20 keyframes of odometry allow, so accepted alone
    graph, manager, truth = _one_wrong_loop([0.3, 0.2, -0.03])
    assert manager.counts()["loop_closures"] == 1
    distorted = _max_error(graph, {"a": truth["a"]})
    for i, j in [(1, 19), (2, 18), (3, 17)]:
        manager.add(("a", i), ("a", j), _true_T(truth, ("a", i), ("a", j)), LC_COV, "loop")
    graph.update(extra_iterations=5)
    counts = manager.counts()
    assert counts["loop_closures"] == 3 and counts["rejected_by_pcm"] == 1
    assert _max_error(graph, {"a": truth["a"]}) < 0.15 < distorted


def test_a_lone_match_that_disagrees_with_the_estimate_waits_for_another() -> None:
    """PCM tests matches against each other only: the first of a group would enter
    untested. On one map it must agree with the estimate (here: a loop 2.2 m and 29 deg
    off what 20 keyframes of odometry allow; an inter-robot match 22 m off)."""
    graph, manager, truth = _one_wrong_loop([2.0, 1.0, -0.5])
    assert manager.counts()["loop_closures"] == 0
    assert _max_error(graph, {"a": truth["a"]}) < 0.3  # odometry drift only
    manager.add(("a", 1), ("a", 19), _true_T(truth, ("a", 1), ("a", 19)), LC_COV, "loop")
    graph.update(extra_iterations=5)
    assert manager.counts()["loop_closures"] == 1  # a right one agrees: in
    for i, j in [(2, 18), (3, 17)]:
        manager.add(("a", i), ("a", j), _true_T(truth, ("a", i), ("a", j)), LC_COV, "loop")
    graph.update(extra_iterations=5)
    assert manager.counts() == {
        "loop_closures": 3,
        "inter_robot_constraints": 0,
        "rejected_by_pcm": 1,
    }
    # b joins a's map; then a far-off match between them arrives first of its kind
    for i, j in [(5, 4), (12, 12), (17, 16)]:
        manager.add(("a", i), ("b", j), _true_T(truth, ("a", i), ("b", j)), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    far = manager.counts()["inter_robot_constraints"]
    manager.groups.pop(("a", "b"))  # as if those had left the PCM window long ago
    manager.add(("a", 2), ("b", 18), np.array([0.5, 0.2, 0.3]), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert manager.counts()["inter_robot_constraints"] == far


def test_orientation_of_a_match_is_normalized() -> None:
    T = np.array([1.0, -2.0, 0.7])
    cov = np.diag([0.01, 0.04, 0.001])
    T_inv, cov_inv = invert_with_covariance(T, cov)
    back, cov_back = invert_with_covariance(T_inv, cov_inv)
    np.testing.assert_allclose(back, T, atol=1e-12)
    np.testing.assert_allclose(cov_back, cov, atol=1e-12)
    assert abs(wrap_angle(T_inv[2] + T[2])) < 1e-12


@pytest.mark.parametrize("kernel", ["huber", "cauchy", "none"])
def test_consistent_matches_join_the_floating_robot(kernel: str) -> None:
    rng = np.random.default_rng(11)
    cfg = ConstraintConfig(robust_kernel=kernel)
    graph, manager, truth = _setup(rng, cfg)
    for i, j in [(5, 4), (12, 12), (17, 16)]:
        # given from b's side: the manager orders every pair the same way
        manager.add(("b", j), ("a", i), _true_T(truth, ("b", j), ("a", i)), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert len(graph.components()) == 1
    assert _max_error(graph, truth) < 0.3  # both chains drift by ~0.15 m


def test_agreeing_matches_from_one_spot_do_not_join_two_maps() -> None:
    """Look-alike places: matches seen from within a metre of each other agree with
    each other whatever they say; they must not fuse two maps on their own."""
    rng = np.random.default_rng(2)
    graph, manager, truth = _setup(rng)
    wrong = np.array([1.5, -1.0, 0.6])  # the same wrong offset every time
    for j in (8, 9, 9):  # nodes of b 1 m apart at most
        T = se2_compose(_true_T(truth, ("a", j), ("b", j)), wrong)
        manager.add(("a", j), ("b", j), T, LC_COV, "inter")
    graph.update()
    assert not graph.is_anchored("b")
    assert manager.counts()["inter_robot_constraints"] == 0


def test_matches_seen_from_one_spot_of_either_robot_do_not_join_two_maps() -> None:
    """ACES: a robot turning on one spot matched a corridor another one drove along,
    9 matches from 7 m of the mover's path, all agreeing, 180 degrees wrong. Each
    robot's side must be spread: one place of a seen from b's 1 m apart nodes, then
    from a's nodes 5 m apart."""
    rng = np.random.default_rng(7)
    graph, manager, truth = _setup(rng)
    for j in (6, 8, 10, 12):  # b's nodes up to 6 m apart, a's node 9 every time
        manager.add(("a", 9), ("b", j), _true_T(truth, ("a", 9), ("b", j)), LC_COV, "inter")
    graph.update()
    assert not graph.is_anchored("b")
    assert manager.counts()["inter_robot_constraints"] == 0
    for i in (12, 14):  # then from a's places 3 and 5 m on
        manager.add(("a", i), ("b", i), _true_T(truth, ("a", i), ("b", i)), LC_COV, "inter")
        graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert _max_error(graph, truth) < 0.3


def test_a_merge_waits_while_other_matches_say_otherwise() -> None:
    """ACES corridors: 3 agreeing wrong matches and 1 right one (3 of 4 offered) joined
    two maps wrongly. The agreeing set must outnumber the rest by
    `min_consistent_to_merge`; right matches arriving later then join them right."""
    rng = np.random.default_rng(9)
    graph, manager, truth = _setup(rng)
    # b placed elsewhere, consistently (a corridor seen the other way round)
    wrong_b = _truth(np.array([4.6, 4.1, np.pi]), _square())
    for j, right in ((6, True), (4, False), (8, False), (14, True), (12, False)):
        T = _true_T(truth, ("a", j), ("b", j)) if right else se2_between(truth["a"][j], wrong_b[j])
        manager.add(("a", j), ("b", j), T, LC_COV, "inter")
    graph.update()
    assert not graph.is_anchored("b")
    for j in (16, 18, 2, 10):  # right ones: 6 against 3
        manager.add(("a", j), ("b", j), _true_T(truth, ("a", j), ("b", j)), LC_COV, "inter")
        graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert _max_error(graph, truth) < 0.3


def test_a_match_far_from_where_the_rest_put_the_robot_stays_out_of_a_join() -> None:
    """ACES: PCM tests matches through the chains' covariance, which grows with the
    distance between matched nodes, so a wrong match far along the chain can agree with
    every right one. Here the chains are taken as very uncertain (PCM accepts a match
    7 m off); the join leaves it out, and it stays out when more matches come."""
    rng = np.random.default_rng(4)
    graph, manager, truth = _setup(rng)
    manager.chain_covariance = lambda robot, i, j: (
        np.abs(np.asarray(j) - np.asarray(i))[:, None, None] * np.diag([4.0, 4.0, 0.01])
    )
    wrong = se2_compose(_true_T(truth, ("a", 18), ("b", 18)), [7.0, 0.0, 0.0])
    manager.add(("a", 18), ("b", 18), wrong, LC_COV, "inter")
    for j in (2, 5, 8, 11):
        manager.add(("a", j), ("b", j), _true_T(truth, ("a", j), ("b", j)), LC_COV, "inter")
    (group,) = manager.groups.values()
    assert len(group.pcm.accepted) == 5  # PCM alone takes the wrong one too
    manager.add(("a", 14), ("b", 14), _true_T(truth, ("a", 14), ("b", 14)), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert 0 not in manager.accepted and len(manager.accepted) == 5
    assert _max_error(graph, truth) < 0.3


def test_another_pairs_matches_far_from_where_a_join_puts_them_stay_out() -> None:
    """ACES: two wrong matches between the second and third segments agreed with each
    other (PCM tests nothing else) and entered the graph when a join put both segments
    on one map, 22 m off. They are checked against where the join put the robots."""
    rng = np.random.default_rng(9)
    graph, manager, truth = _setup(rng, third=True, third_known=False)  # b, c floating
    D = np.array([8.0, 3.0, 0.4])  # c seen 8.5 m off by b, twice, consistently
    for j in (5, 9):
        T = se2_between(truth["b"][j], se2_compose(D, truth["c"][j]))
        manager.add(("b", j), ("c", j), T, LC_COV, "inter")
    for j in (3, 10, 16):  # right matches with a join c's map
        manager.add(("a", j), ("c", j), _true_T(truth, ("a", j), ("c", j)), LC_COV, "inter")
        graph.update(extra_iterations=5)
    assert graph.is_anchored("c")
    for j in (2, 8, 14):  # right matches with a join b's map
        manager.add(("a", j), ("b", j), _true_T(truth, ("a", j), ("b", j)), LC_COV, "inter")
        graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert not {0, 1} & manager.accepted
    assert _max_error(graph, truth) < 0.3


def test_matches_from_one_stretch_of_a_chain_count_once_toward_a_merge() -> None:
    """Whole-map searches a few keyframes apart match overlapping stretches of scans:
    four agreeing matches from two stretches do not join two maps, a third one does."""
    rng = np.random.default_rng(9)
    graph, manager, truth = _setup(rng)
    manager.cfg.merge_stretch_keyframes = 5
    for j in (2, 4, 6, 8):  # stretches from 2 and from 8
        manager.add(("a", j), ("b", j), _true_T(truth, ("a", j), ("b", j)), LC_COV, "inter")
        graph.update()
    assert not graph.is_anchored("b")
    manager.add(("a", 14), ("b", 14), _true_T(truth, ("a", 14), ("b", 14)), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert _max_error(graph, truth) < 0.3


def test_more_matches_are_looked_for_where_most_matches_agree() -> None:
    """Two maps not joined yet (3 right matches against 2 wrong, agreeing ones): the
    match new candidates are searched around is the newest right one, not the newest."""
    rng = np.random.default_rng(9)
    graph, manager, truth = _setup(rng)
    wrong_b = _truth(np.array([4.6, 4.1, np.pi]), _square())
    for j, right in ((8, False), (6, True), (14, True), (4, True), (12, False)):
        T = _true_T(truth, ("a", j), ("b", j)) if right else se2_between(truth["a"][j], wrong_b[j])
        manager.add(("a", j), ("b", j), T, LC_COV, "inter")
    graph.update()
    assert not graph.is_anchored("b")  # 3 against 2
    (lead,) = manager.pending_links()
    assert (lead.robot_a, lead.index_a, lead.robot_b, lead.index_b) == ("a", 4, "b", 4)


@pytest.mark.parametrize("c_right", [True, False])
def test_matches_with_two_robots_of_one_map_count_together_when_they_agree(c_right: bool) -> None:
    """b sees a three times from within a metre (not enough alone: look-alike places),
    then c, on a's map, twice from 5 m on. If c's matches put b where a's do, together
    they are spread enough to join b's map; if they put it 1.5 m elsewhere, not."""
    rng = np.random.default_rng(5)
    graph, manager, truth = _setup(rng, third=True)
    for j in (8, 9, 9):
        manager.add(("a", j), ("b", j), _true_T(truth, ("a", j), ("b", j)), LC_COV, "inter")
    graph.update()
    assert not graph.is_anchored("b")
    for j in (13, 14):
        T = _true_T(truth, ("c", j), ("b", j))
        manager.add(("c", j), ("b", j), T if c_right else T + [1.5, 0.0, 0.0], LC_COV, "inter")
        graph.update(extra_iterations=5)
    assert graph.is_anchored("b") == c_right
    if c_right:  # joined by the a-b matches (c's enter with the group's next match)
        assert manager.counts()["inter_robot_constraints"] >= 3
        assert _max_error(graph, truth) < 0.3


def test_matches_with_other_robots_of_the_map_count_from_enough_stretches_only() -> None:
    """As above with c right, but counting stretches of 5 nodes along b's chain: b's
    matches at 8, 9, 9, 13 and 14 come from two stretches and do not join its map; one
    more of c from 19, a third stretch, does."""
    rng = np.random.default_rng(5)
    graph, manager, truth = _setup(rng, third=True)
    manager.cfg.merge_stretch_keyframes = 5
    for j in (8, 9, 9):
        manager.add(("a", j), ("b", j), _true_T(truth, ("a", j), ("b", j)), LC_COV, "inter")
    for j in (13, 14):
        manager.add(("c", j), ("b", j), _true_T(truth, ("c", j), ("b", j)), LC_COV, "inter")
        graph.update(extra_iterations=5)
    assert not graph.is_anchored("b")
    manager.add(("c", 19), ("b", 19), _true_T(truth, ("c", 19), ("b", 19)), LC_COV, "inter")
    manager.add(("a", 10), ("b", 10), _true_T(truth, ("a", 10), ("b", 10)), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert graph.is_anchored("b")
    assert _max_error(graph, truth) < 0.3


def test_matches_leaving_the_pcm_window_keep_their_state() -> None:
    """With a PCM window of 3, the manager keeps records of the last 3 matches of a
    pair only; accepted matches that left it stay in the graph (and in the counts),
    a rejected one stays out."""
    rng = np.random.default_rng(7)
    graph, manager, truth = _setup(rng, ConstraintConfig(pcm_window=3))
    pairs = [(2, 2), (7, 8), (10, 10), (15, 14), (18, 18), (4, 4), (12, 12)]
    for n, (i, j) in enumerate(pairs, start=1):
        T = _true_T(truth, ("a", i), ("b", j))
        if n == 4:  # a wrong one in the middle of the stream
            T = se2_compose(T, [1.5, -1.0, 0.6])
        manager.add(("a", i), ("b", j), T, LC_COV, "inter")
        graph.update(extra_iterations=2)
        group = manager.groups[("a", "b")]
        assert len(group.measurements) == len(group.pcm.measurements) == min(n, 3)
        assert set(group.in_graph) <= set(group.measurements)
    assert group.pcm.settled == len(pairs) - 3
    constraints = sum(1 for f in graph._factors.values() if f.kind == "constraint")
    assert constraints == len(pairs) - 1  # the settled accepted ones are still there
    assert manager.counts() == {
        "loop_closures": 0,
        "inter_robot_constraints": len(pairs) - 1,
        "rejected_by_pcm": 1,
    }
    assert graph.is_anchored("b") and _max_error(graph, truth) < 0.3


def test_matches_leaving_the_pcm_window_are_fused_between_the_same_places() -> None:
    """A reducing graph: matches that left the window are final, and those between the
    same two nodes become one factor (the accepted count stays what it was)."""
    rng = np.random.default_rng(8)
    reducing = PoseGraph(reduce_distance_m=0.3, reduce_after_nodes=10**6)  # no aliases
    graph, manager, truth = _setup(rng, ConstraintConfig(pcm_window=3), graph=reducing)
    pairs = [(2, 2), (7, 8), (10, 10)] + [(15, 14)] * 6
    for i, j in pairs:
        T = se2_compose(_true_T(truth, ("a", i), ("b", j)), rng.normal(0, 0.01, 3))
        manager.add(("a", i), ("b", j), T, LC_COV, "inter")
        graph.update(extra_iterations=2)
    constraints = [f for f in graph._factors.values() if f.kind == "constraint"]
    # 3 final at distinct places, the 3 final (15, 14) ones as one, the last 3 (window)
    assert len(constraints) == 3 + 1 + 3
    assert graph.reduction_stats()["fused_constraints"] == 2
    assert manager.counts()["inter_robot_constraints"] == len(pairs)
    assert graph.is_anchored("b") and _max_error(graph, truth) < 0.3


def test_a_tie_covers_candidates_between_the_same_two_stretches_only() -> None:
    """`covered`: a candidate whose ends are both within `inter_redundant_keyframes` of
    an accepted inter-robot constraint's (either order of the robots) is redundant; a
    later pass over the same place, or a tie PCM has kept out, covers nothing."""
    graph, manager, truth = _setup(np.random.default_rng(3))
    wrong = se2_compose(_true_T(truth, ("a", 10), ("b", 10)), [1.5, -1.0, 0.6])
    manager.add(("a", 10), ("b", 10), wrong, LC_COV, "inter")
    for i, j in [(2, 2), (7, 8), (15, 14), (18, 18)]:
        manager.add(("a", i), ("b", j), _true_T(truth, ("a", i), ("b", j)), LC_COV, "inter")
    graph.update(extra_iterations=5)
    assert graph.is_anchored("b") and 10 not in set(manager.links[("a", "b")].view()[:, 2].tolist())
    manager.cfg.inter_redundant_keyframes = 2
    assert manager.covered(("a", 4), ("b", 3))  # 2 and 1 keyframes from the (2, 2) tie
    assert manager.covered(("b", 16), ("a", 13))  # robots the other way round
    assert not manager.covered(("a", 11), ("b", 11))  # near the wrong match only
    assert not manager.covered(("a", 3), ("b", 14))  # one end far from any tie
    assert not manager.covered(("a", 22), ("b", 2))  # a's next lap over the same place
    manager.cfg.inter_redundant_keyframes = 0
    assert not manager.covered(("a", 2), ("b", 2))  # off


@pytest.mark.parametrize("offset_m", [0.0, 1.2])
def test_matches_between_robots_with_known_starts_must_fit_the_estimate(offset_m: float) -> None:
    """Two robots with known starts (both on `map`) are two components until their first
    match, and were joined like two maps, by PCM and the merge rules alone. In a corridor
    whose look repeats every 1.2 m (within the verifier's window), three matches one
    period off, 15 m apart, agree with each other and went in: robot b bent ~1.25 m.
    The firm start priors make the estimate sure of their relative pose: a match that
    does not fit it stays out; right ones go in."""
    odo = np.diag([0.02**2, 0.02**2, 0.003**2])
    rng = np.random.default_rng(1)
    n = 81  # 40 m of corridor, 0.5 m keyframes
    truth = {r: np.array([[0.5 * i, y, 0.0] for i in range(n)]) for r, y in (("a", 0), ("b", 0.4))}
    g = PoseGraph()
    for r in ("a", "b"):
        g.add_robot(r, truth[r][0])
        g.add_node(r, 0, None, None)
        for i in range(1, n):
            d = se2_between(truth[r][i - 1], truth[r][i]) + rng.normal(0, np.sqrt(np.diag(odo)))
            g.add_node(r, i, d, odo)
    g.update()

    def error() -> float:  # of robot b (odometry drift alone: ~1.2 m at the end)
        return float(np.hypot(*(g.poses("b")[:, :2] - truth["b"][:, :2]).T).max())

    drift = error()

    def chain_cov(robot, i, j):
        k = np.abs(np.asarray(j) - np.asarray(i))[:, None, None]
        return k * odo + (0.5 * k) ** 2 * odo[2, 2] * np.diag([1.0, 1.0, 0.0])

    lcm = LoopClosureManager(g, ConstraintConfig(), chain_cov)
    for i in (10, 40, 70):
        T = se2_compose(se2_between(truth["a"][i], truth["b"][i]), [offset_m, 0.0, 0.0])
        lcm.add(("a", i), ("b", i), T, np.diag([0.03**2, 0.03**2, 0.01**2]), "inter")
        g.update(extra_iterations=5)
    assert len(lcm.accepted) == (3 if offset_m == 0.0 else 0)
    if offset_m:  # the graph as it was
        assert error() == pytest.approx(drift, abs=1e-6)
    else:  # b where a's matches put it
        rel = se2_between(g.pose("a", 70), g.pose("b", 70))
        assert np.allclose(rel[:2], [0.0, 0.4], atol=0.05)


@pytest.mark.parametrize("prior", [(0.01, 0.01, 0.001), (0.2, 0.2, 0.035)])
def test_starts_measured_by_hand_take_right_matches_with_their_sigmas(
    prior: tuple[float, float, float], caplog: pytest.LogCaptureFixture
) -> None:
    """Known starts 0.2 m and 2 deg off (a fleet.json measured by hand): with the default
    firm start prior (`basestation.prior_sigma_*`, 0.01 m / 0.001 rad) the right matches
    disagree with them and stay out, with a warning that says what to set; with sigmas
    as large as the error they go in."""
    odo = np.diag([0.002**2, 0.002**2, 0.001**2])  # the agent's: 0.2 m keyframes
    rng = np.random.default_rng(1)
    n = 201  # 40 m of corridor
    truth = {r: np.array([[0.2 * i, y, 0.0] for i in range(n)]) for r, y in (("a", 0), ("b", 0.4))}
    g = PoseGraph(prior_sigmas=prior)
    for r in ("a", "b"):
        off = [0.2, 0.0, np.radians(2.0)] if r == "b" else [0.0, 0.0, 0.0]
        g.add_robot(r, se2_compose(truth[r][0], off))
        g.add_node(r, 0, None, None)
        for i in range(1, n):
            d = se2_between(truth[r][i - 1], truth[r][i]) + rng.normal(0, np.sqrt(np.diag(odo)))
            g.add_node(r, i, d, odo)
    g.update()

    def chain_cov(robot, i, j):
        k = np.abs(np.asarray(j) - np.asarray(i))[:, None, None]
        return k * odo + (0.2 * k) ** 2 * odo[2, 2] * np.diag([1.0, 1.0, 0.0])

    lcm = LoopClosureManager(g, ConstraintConfig(), chain_cov)
    with caplog.at_level("WARNING"):
        for i in (25, 60, 100, 140, 180):
            T = se2_between(truth["a"][i], truth["b"][i])
            lcm.add(("a", i), ("b", i), T, np.diag([0.03**2, 0.03**2, 0.01**2]), "inter")
            g.update(extra_iterations=5)
    firm = prior[0] < 0.1
    assert len(lcm.accepted) == (0 if firm else 5)
    assert ("prior_sigma_xy_m" in caplog.text) == firm
