"""A reduced pose graph lets go of ties between places past a degree, at its rebuilds."""

from __future__ import annotations

import numpy as np
import pytest
from pose_graph_helpers import fly_with_window
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from basestation.pose_graph import PoseGraph
from basestation.pose_graph_sparsify import Tie, ties_to_drop
from common.config import load_config
from common.errors import ConfigError


def _components(n: int, ties: list[Tie]) -> np.ndarray:
    a = [t.a for t in ties]
    b = [t.b for t in ties]
    m = coo_matrix((np.ones(len(ties)), (a, b)), shape=(n, n))
    return connected_components(m, directed=False)[1]


@pytest.mark.parametrize("seed", range(20))
def test_what_is_left_out_keeps_every_pair_joined_and_the_degree_bounded(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 60))
    xy = rng.uniform(0, 10, (n, 2))
    ties = []
    for fid in range(int(rng.integers(0, 4 * n))):
        a, b = rng.choice(n, 2, replace=False)
        length = float(np.hypot(*(xy[a] - xy[b])))
        ties.append(Tie(fid, int(a), int(b), length, bool(rng.random() < 0.8)))
    degree = int(rng.integers(1, 6))
    drop = ties_to_drop(ties, degree)
    kept = [t for t in ties if t.fid not in set(drop)]
    assert drop == sorted(drop)
    assert all(t.optional for t in ties if t.fid in set(drop))  # fixed ties always stay
    # the optional ties alone join the same variables as before (a spanning forest stays)
    optional = [t for t in ties if t.optional]
    np.testing.assert_array_equal(
        _components(n, optional), _components(n, [t for t in kept if t.optional])
    )
    # a tie left out had an end that already had `degree` ties kept
    count = np.bincount([t.a for t in kept] + [t.b for t in kept], minlength=n)
    for t in ties:
        if t.fid in set(drop):
            assert max(count[t.a], count[t.b]) >= degree
    assert ties_to_drop(ties, 0) == []


def test_shortest_ties_are_kept_first():
    # a triangle and a pendant: the forest takes the two short sides, the long one goes
    ties = [Tie(0, 0, 1, 1.0, True), Tie(1, 1, 2, 1.0, True), Tie(2, 0, 2, 3.0, True)]
    assert ties_to_drop(ties, 1) == [2]
    assert ties_to_drop(ties, 2) == []  # every end has fewer than 2 kept: all stay
    # fixed ties count toward the degree, but the optional ones alone keep the forest
    assert ties_to_drop([Tie(9, 0, 1, 0.5, False), *ties], 1) == [2]
    assert ties_to_drop([*ties, Tie(9, 0, 2, 0.5, False), Tie(8, 1, 2, 0.5, False)], 2) == [2]


def test_a_rebuild_leaves_ties_past_the_degree_out_of_isam2_and_keeps_the_estimate():
    """Matches whose far ends wander over 0.6 m tie each place to several others: with a
    degree of 2 each rebuild leaves the longest of them out of iSAM2 (dormant: still in
    the records, so the reduction makes the same places); the graph stays one piece and
    the trajectory about as accurate."""
    graphs = {}
    for degree in (0, 2):
        graph = PoseGraph(
            heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1,
            reduce_after_nodes=200, rebuild_nodes=100, tie_degree=degree,
        )  # fmt: skip
        graph.add_robot("a", [0, 0, 0])
        truth = fly_with_window(graph, 6, 5, spread=4)
        graph.update()
        graph.rebuild()
        graphs[degree] = graph
    plain, sparse = graphs[0], graphs[2]
    assert plain.num_dormant == 0 and sparse.num_rebuilds >= 5
    assert sparse.num_dormant > 20
    dormant = [r for r in sparse._factors.values() if r.dormant]
    assert len(dormant) == sparse.num_dormant
    assert all(r.isam_index is None and r.kind in ("odometry", "constraint") for r in dormant)
    in_isam = sparse._isam.getFactorsUnsafe().nrFactors()
    assert in_isam == plain._isam.getFactorsUnsafe().nrFactors() - sparse.num_dormant
    assert sparse.factor_slots() == in_isam
    variables = {d: g.reduction_stats()["variables"] for d, g in graphs.items()}
    assert abs(variables[2] - variables[0]) <= 0.05 * variables[0]
    err = {d: np.linalg.norm(g.poses("a")[:, :2] - truth[:, :2], axis=1) for d, g in graphs.items()}
    assert np.isfinite(err[2]).all()
    assert err[2].max() < 0.25 and err[2].mean() < 1.3 * err[0].mean()
    # a dormant tie that takes in a new measurement is back in iSAM2 at the next update
    record = dormant[0]
    fid = next(f for f, r in sparse._factors.items() if r is record)
    sparse._replace_factor(fid, record.factor)
    sparse.update()
    assert not record.dormant and record.isam_index is not None


def test_the_degree_comes_from_the_config_and_a_negative_one_is_refused():
    cfg = load_config(None, {"basestation.reduce_tie_degree": 4})
    assert PoseGraph.from_config(cfg.basestation)._tie_degree == 4
    assert load_config(None, {}).basestation.reduce_tie_degree == 3
    with pytest.raises(ConfigError, match="reduce_tie_degree"):
        load_config(None, {"basestation.reduce_tie_degree": -1})
