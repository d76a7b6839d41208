"""Ties between places in a reduced pose graph: final constraints fused and folded,
odometry between places already joined left out."""

from __future__ import annotations

import numpy as np
from pose_graph_helpers import LAP, LOOP_COV, ODOM_COV, circle, fly_with_window, odometry_factors

from basestation.pose_graph import PoseGraph
from common.geometry import se2_between


def test_final_constraints_grow_with_the_places_not_with_the_revisits():
    graphs = {}
    for window in (None, 40):
        graph = PoseGraph(
            heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1
        )
        graph.add_robot("a", [0, 0, 0])
        truth = fly_with_window(graph, 6, window)
        graphs[window] = graph
    kept, final = graphs[None], graphs[40]
    n_loops = 5 * LAP // 5  # one every 5 nodes from lap 1 on

    def constraints(g: PoseGraph) -> int:
        return sum(r.kind == "constraint" and r.factor is not None for r in g._factors.values())

    # 5 laps of matches between the same places: final ones fold onto a lap's worth of pairs
    assert constraints(kept) > 0.8 * n_loops
    assert constraints(final) < 0.45 * n_loops  # 62 of 157
    assert final.reduction_stats()["fused_constraints"] > 0.5 * n_loops
    assert final.reduction_stats()["factor_records"] < kept.reduction_stats()["factor_records"]
    err = {w: np.linalg.norm(g.poses("a")[:, :2] - truth[:, :2], axis=1) for w, g in graphs.items()}
    assert err[40].max() < 0.2 and err[40].mean() < 1.2 * err[None].mean()


def test_past_the_tie_budget_a_final_constraint_is_folded_into_a_tie_next_to_it():
    """Matches whose far ends wander over 0.6 m land on several variables there: each
    would tie a new pair of places (iSAM2's fill-in grows with such ties). Past the
    budget they go into the ties already there, at no cost in accuracy."""
    graphs = {}
    for budget in (0.0, 0.2):  # 0: no cap
        graph = PoseGraph(
            heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1,
            tie_budget=budget,
        )  # fmt: skip
        graph.add_robot("a", [0, 0, 0])
        # final 5 nodes after it was added, before aliasing (10): moved onto the anchors
        truth = fly_with_window(graph, 6, 5, spread=4)
        graphs[budget] = graph
    plain, capped = graphs[0.0].reduction_stats(), graphs[0.2].reduction_stats()
    assert plain["folded_constraints"] == 0
    assert capped["folded_constraints"] > 20
    # (a match with no tie within FOLD_DISTANCE_M of its far end still ties a new pair)
    assert capped["final_ties"] < 0.6 * plain["final_ties"]  # 45 against 101
    assert capped["factors"] < plain["factors"]
    chain = graphs[0.2]._chains["a"]  # no factor is left on a variable that became an alias
    aliased = {chain.key_base + i for i in np.flatnonzero(chain.alias_key[: chain.size] >= 0)}
    assert not any(set(r.keys) & aliased for r in graphs[0.2]._factors.values())
    err = {b: np.linalg.norm(g.poses("a")[:, :2] - truth[:, :2], axis=1) for b, g in graphs.items()}
    assert err[0.2].max() < 0.2 and err[0.2].mean() < 1.2 * err[0.0].mean()


def fly_fast_revisits(graph: PoseGraph, laps: int, fast: int) -> np.ndarray:
    """Lap 0 at 0.2 m a node, then laps at ``fast`` x 0.2 m a node, each node after lap 0
    matched to lap 0 every other node; returns the true poses."""
    rng = np.random.default_rng(0)
    s = list(range(LAP)) + list(range(LAP, laps * LAP, fast))
    truth = [circle(k) for k in s]
    for i, p in enumerate(truth):
        d = None if i == 0 else se2_between(truth[i - 1], p) + rng.normal(0, [0.01, 0.01, 0.001])
        graph.add_node("a", i, d, None if i == 0 else ODOM_COV)
        if s[i] >= LAP and i % 2 == 0:
            T = se2_between(truth[s[i] % LAP], p) + rng.normal(0, [0.01, 0.01, 0.001])
            graph.add_constraint(("a", s[i] % LAP), ("a", i), T, LOOP_COV)
        graph.update()
    return np.array(truth)


def test_with_a_tie_budget_odometry_between_places_already_joined_is_left_out():
    """A faster revisit skips a variable between two of its nodes: their odometry would
    tie two places two hops apart anew. With a tie budget it is left out (the places
    stay joined through the variable between them), at little cost in accuracy."""
    graphs = {}
    for budget in (0.0, 0.5):
        graph = PoseGraph(
            heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1,
            tie_budget=budget,
        )  # fmt: skip
        graph.add_robot("a", [0, 0, 0])
        truth = fly_fast_revisits(graph, 8, fast=4)
        graphs[budget] = graph
    plain, capped = graphs[0.0], graphs[0.5]
    assert plain.reduction_stats()["dropped_odometry"] == 0
    assert capped.reduction_stats()["dropped_odometry"] > 50  # 86
    assert odometry_factors(capped) < 0.6 * odometry_factors(plain)  # 62 against 113
    assert capped.reduction_stats()["variables"] == plain.reduction_stats()["variables"]
    chain = capped._chains["a"]  # every odometry factor left is between two variables
    aliased = {chain.key_base + i for i in np.flatnonzero(chain.alias_key[: chain.size] >= 0)}
    assert not any(set(r.keys) & aliased for r in capped._factors.values())
    err = {b: np.linalg.norm(g.poses("a")[:, :2] - truth[:, :2], axis=1) for b, g in graphs.items()}
    assert np.isfinite(err[0.5]).all()
    assert err[0.5].max() < 0.15 and err[0.5].mean() < 1.2 * err[0.0].mean()  # 0.045 / 0.040


def test_a_long_final_constraint_is_folded_whatever_the_budget(monkeypatch):
    """Matches 2.0-2.6 m long (far ends wandering over 0.6 m): under a budget never
    reached, those longer than LONG_TIE_M still go into the ties already there (long
    ties make iSAM2's fill-in), at no cost in accuracy."""
    import basestation.pose_graph_reduction as reduction

    graphs = {}
    for long_m in (np.inf, reduction.LONG_TIE_M):
        monkeypatch.setattr(reduction, "LONG_TIE_M", long_m)
        graph = PoseGraph(
            heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1,
            tie_budget=100.0,
        )  # fmt: skip
        graph.add_robot("a", [0, 0, 0])
        truth = fly_with_window(graph, 6, 5, spread=4)
        graphs[long_m] = graph
    plain, folded = graphs[np.inf].reduction_stats(), graphs[reduction.LONG_TIE_M].reduction_stats()
    assert plain["folded_constraints"] == 0
    assert folded["folded_constraints"] > 40  # 66
    assert folded["final_ties"] < 0.75 * plain["final_ties"]  # 67 against 101
    err = {k: np.linalg.norm(g.poses("a")[:, :2] - truth[:, :2], axis=1) for k, g in graphs.items()}
    assert err[reduction.LONG_TIE_M].max() < 0.2
    assert err[reduction.LONG_TIE_M].mean() < 1.2 * err[np.inf].mean()
