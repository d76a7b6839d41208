"""Reduced pose graph: keyframes over mapped ground become aliases of old variables."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from pose_graph_helpers import (
    LAP,
    LOOP_COV,
    ODOM_COV,
    circle,
    fly_laps,
    fly_with_window,
    odometry_factors,
    variables,
)

from basestation.between_measurements import fuse, moved_measurement
from basestation.loop_closure_manager import invert_with_covariance
from basestation.pose_graph import PoseGraph
from basestation.pose_graph_reduction import LINK_KEYFRAMES
from basestation.pose_graph_state import pose2
from common.errors import CollabSlamError
from common.geometry import se2_between, se2_compose


def test_revisits_add_no_variables_and_poses_stay_accurate():
    full = PoseGraph(heads_last=True)
    full.add_robot("a", [0, 0, 0])
    truth = fly_laps(full, 6)
    reduced = PoseGraph(heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1)
    reduced.add_robot("a", [0, 0, 0])
    assert np.array_equal(fly_laps(reduced, 6), truth)
    # 6 laps of 157 nodes: all iSAM2 holds is about half a lap's worth of variables
    assert variables(full) == 6 * LAP
    assert variables(reduced) < 0.6 * LAP and odometry_factors(reduced) < 0.6 * LAP
    assert reduced.num_nodes("a") == 6 * LAP
    poses = reduced.poses("a")
    assert poses.shape == (6 * LAP, 3)
    err_full = np.linalg.norm(full.poses("a")[:, :2] - truth[:, :2], axis=1)
    err_red = np.linalg.norm(poses[:, :2] - truth[:, :2], axis=1)
    # rigid 0.5 m clusters cost some accuracy (1.47x the mean error here, 0.3 m: 1.09x)
    assert err_red.max() < 0.15
    assert err_red.mean() < 1.6 * err_full.mean()
    # single-pose queries agree with the full extraction, aliases included
    for i in (0, 3, LAP + 7, 5 * LAP + 11, 6 * LAP - 1):
        np.testing.assert_allclose(reduced.pose("a", i), poses[i], atol=1e-9)


def test_variables_stop_growing_once_the_ground_is_mapped():
    graph = PoseGraph(heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    fly_laps(graph, 3)
    after_3 = (variables(graph), odometry_factors(graph))
    more = PoseGraph(heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1)
    more.add_robot("a", [0, 0, 0])
    fly_laps(more, 8)
    after_8 = (variables(more), odometry_factors(more))
    assert after_8[0] <= after_3[0] + 2 and after_8[1] <= after_3[1] + 2
    assert more.num_aliased > 7 * LAP


def test_constraint_marks_are_kept_only_where_the_pass_still_looks():
    graph = PoseGraph(heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    fly_laps(graph, 3)  # a loop closure every 5 nodes from lap 1 on: ~63 constrained nodes
    chain = graph._chains["a"]
    assert chain.reduce_next > 3 * LAP - 20
    assert chain.constrained and min(chain.constrained) >= chain.reduce_next - LINK_KEYFRAMES
    assert len(chain.constrained) <= 2 * (LINK_KEYFRAMES + 10) // 5 + 2


def test_the_reduction_waits_for_its_node_count():
    graph = PoseGraph(
        heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_after_nodes=2 * LAP
    )
    graph.add_robot("a", [0, 0, 0])
    rng = np.random.default_rng(3)
    for i in range(3 * LAP):
        d = None if i == 0 else se2_between(circle(i - 1), circle(i)) + rng.normal(0, 0.005, 3)
        graph.add_node("a", i, d, None if i == 0 else ODOM_COV)
        graph.update()
        if i == 2 * LAP - 2:
            assert graph.num_aliased == 0 and not graph.reduction_stats()["reducing"]
    # then every settled node is looked at, the oldest ones too
    assert graph.reduction_stats()["reducing"]
    assert np.count_nonzero(graph._chains["a"].alias_key[:LAP] >= 0) > LAP // 2


def side_by_side(constraints: int) -> tuple[PoseGraph, list[int]]:
    """Robots a and b flying side by side, 0.1 m apart, in steps of 0.5 m (so no node
    has a variable of its own robot within the 0.3 m of the reduction), the first
    ``constraints`` node pairs tied by an inter-robot constraint."""
    graph = PoseGraph(reduce_distance_m=0.3, reduce_lag=5, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    graph.add_robot("b", [0, 0.1, 0])
    ids = []
    for i in range(40):
        for rid in ("a", "b"):
            d = None if i == 0 else [0.5, 0.0, 0.0]
            graph.add_node(rid, i, d, None if i == 0 else ODOM_COV)
        if i < constraints:
            ids.append(graph.add_constraint(("a", i), ("b", i), [0.0, 0.1, 0.0], LOOP_COV))
        graph.update()
    return graph, ids


def test_a_robot_over_anothers_ground_is_folded_onto_its_variables():
    graph, ids = side_by_side(constraints=8)  # tied at the start only: the rest follows
    aliases = {r: graph._chains[r].alias_key[:40] for r in "ab"}
    across = sum(np.count_nonzero(k >= 0) for k in aliases.values())
    # every settled node after the first few is an alias of the other robot's variable
    assert across > 25
    for r, other in (("a", "b"), ("b", "a")):
        keys = aliases[r][aliases[r] >= 0]
        assert np.all(keys >> 56 == ord(graph._chains[other].char))
    assert variables(graph) < 40 + 15  # about one robot's worth, not two
    for i in (10, 25, 33, 39):
        np.testing.assert_allclose(graph.pose("b", i) - graph.pose("a", i), [0, 0.1, 0], atol=1e-3)
    # the aliases tie the two for good: one map even without a constraint between them
    for fid in ids:
        graph.remove_constraint(fid)
    graph.update()
    assert graph.components() == [["a", "b"]]
    np.testing.assert_allclose(graph.pose("b", 25) - graph.pose("a", 25), [0, 0.1, 0], atol=1e-3)


def test_a_pair_with_few_constraints_keeps_its_own_variables():
    graph, _ = side_by_side(constraints=4)  # fewer than ACROSS_MIN_CONSTRAINTS
    assert graph.num_aliased == 0 and variables(graph) == 80
    np.testing.assert_allclose(graph.pose("b", 20) - graph.pose("a", 20), [0, 0.1, 0], atol=1e-3)


def test_a_registered_revisit_is_aliased_onto_the_nearest_variable_however_far_in_the_graph():
    """A slow lap (0.2 m steps), then a fast one (1 m steps) with a loop closure every
    8 nodes: a fast node's graph neighbours are a metre away, the old variable beside
    it is many factors away, yet it becomes an alias of that one."""
    rng = np.random.default_rng(5)
    graph = PoseGraph(reduce_distance_m=0.3, reduce_lag=5, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    slow = [circle(i) for i in range(LAP)]
    fast = [circle(i) for i in range(0, LAP, 5)]
    truth = slow + fast
    for i, p in enumerate(truth):
        d = None if i == 0 else se2_between(truth[i - 1], p) + rng.normal(0, [0.005, 0.005, 5e-4])
        graph.add_node("a", i, d, None if i == 0 else ODOM_COV)
        if i >= LAP and (i - LAP) % 8 == 0:
            j = 5 * (i - LAP)  # the slow node at the same place
            graph.add_constraint(("a", j), ("a", i), se2_between(slow[j], p), LOOP_COV)
        graph.update()
    chain = graph._chains["a"]
    settled = range(LAP + 1, len(truth) - 5)
    aliased = [i for i in settled if chain.alias_key[i] >= 0]
    assert len(aliased) >= 0.8 * len(settled)  # two factors away: only beside a closure
    assert all(chain.alias_key[i] & ((1 << 56) - 1) < LAP for i in aliased)  # slow lap's
    err = np.linalg.norm(graph.poses("a")[:, :2] - np.array(truth)[:, :2], axis=1)
    assert err.max() < 0.1


def test_passes_wait_for_a_batch_of_settled_nodes():
    graph = PoseGraph(reduce_distance_m=0.5, reduce_lag=5, reduce_batch_nodes=30)
    graph.add_robot("a", [0, 0, 0])
    aliased = []
    for i in range(80):
        graph.add_node("a", i, None if i == 0 else [0.1, 0, 0], None if i == 0 else ODOM_COV)
        graph.update()
        aliased.append(graph.num_aliased)
    # nothing until 30 settled nodes wait (node 35 committed), then in steps
    assert aliased[33] == 0 and aliased[36] > 15
    assert len(set(aliased)) <= 4


def test_newest_nodes_first_node_and_gps_robots_stay_variables():
    graph = PoseGraph(reduce_distance_m=5.0, reduce_lag=10, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    graph.add_robot("g", [0, 0, 0], start_sigmas=[10.0, 10.0, 1.0])
    graph.add_gps_fix("g", 100.0, [0.0, 0.0], [1.0, 1.0, 1.0])  # waits after the nodes
    for i in range(40):
        for rid in ("a", "g"):
            d = None if i == 0 else np.array([0.05, 0.0, 0.0])
            graph.add_node(rid, i, d, None if i == 0 else ODOM_COV, stamp=float(i))
        graph.update()
    a, g = graph._chains["a"], graph._chains["g"]
    assert a.alias_key[0] < 0 and np.all(a.alias_key[40 - 10 : 40] < 0)
    assert np.count_nonzero(a.alias_key[:40] >= 0) > 20
    assert len(g.alias_key) == 0 or np.all(g.alias_key < 0)


def test_constraints_on_aliased_nodes_are_moved_onto_their_variables():
    graph = PoseGraph(reduce_distance_m=0.5, reduce_lag=5, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    truth = [np.array([0.1 * i, 0.0, 0.0]) for i in range(60)]
    bias = np.array([0.1, 0.0, 0.0])  # odometry overshoots: the chain drifts forward
    for i in range(60):
        d = None if i == 0 else se2_between(truth[i - 1], truth[i]) + 0.01 * bias
        graph.add_node("a", i, d, None if i == 0 else ODOM_COV)
        graph.update()
    aliased = [i for i in range(1, 50) if graph._chains["a"].alias_key[i] >= 0]
    assert len(aliased) > 30
    k = aliased[-1]
    before = graph.pose("a", 59)
    # a loop closure from the newest node back to an aliased one pulls the head back
    fid = graph.add_constraint(("a", k), ("a", 59), se2_between(truth[k], truth[59]), LOOP_COV)
    graph.update()
    graph.update(extra_iterations=3)
    after = graph.pose("a", 59)
    measured = se2_between(graph.pose("a", k), after)
    np.testing.assert_allclose(measured[:2], se2_between(truth[k], truth[59])[:2], atol=0.02)
    assert not np.allclose(before, after)
    graph.remove_constraint(fid)
    graph.update(extra_iterations=3)
    cov = graph.marginal_covariance("a", k)
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)


def test_a_constraint_inside_one_cluster_is_kept_but_inert():
    graph = PoseGraph(reduce_distance_m=1.0, reduce_lag=3, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    for i in range(12):
        graph.add_node("a", i, None if i == 0 else [0.05, 0, 0], None if i == 0 else ODOM_COV)
        graph.update()
    chain = graph._chains["a"]
    pair = [i for i in range(1, 9) if chain.alias_key[i] >= 0][:2]
    assert len(pair) == 2 and chain.alias_key[pair[0]] == chain.alias_key[pair[1]]
    fid = graph.add_constraint(("a", pair[0]), ("a", pair[1]), [0.05, 0, 0], LOOP_COV)
    assert graph._factors[fid].factor is None
    graph.update()
    graph.remove_constraint(fid)
    graph.update()
    with pytest.raises(Exception, match="no active constraint"):
        graph.remove_constraint(fid)


@pytest.mark.parametrize("side", [0, 1])
def test_moving_a_factor_end_keeps_its_error(side):
    rng = np.random.default_rng(side)
    for _ in range(20):
        anchor, other, offset, z = (rng.normal(0, [2, 2, 1.5]) for _ in range(4))
        node = se2_compose(anchor, offset)
        cov = np.diag(rng.uniform(0.01, 0.1, 3))
        noise = gtsam.noiseModel.Gaussian.Covariance(cov)
        K_a, K_b, K_n = 1, 2, 3
        values = gtsam.Values()
        for key, p in ((K_a, node), (K_b, other), (K_n, anchor)):
            values.insert(key, pose2(p))
        keys = (K_a, K_b) if side == 0 else (K_b, K_a)
        original = gtsam.BetweenFactorPose2(*keys, pose2(z), noise)
        z2, cov2 = moved_measurement(z, cov, side, offset)
        moved_keys = (K_n, K_b) if side == 0 else (K_b, K_n)
        moved = gtsam.BetweenFactorPose2(
            *moved_keys, pose2(z2), gtsam.noiseModel.Gaussian.Covariance(cov2)
        )
        assert moved.error(values) == pytest.approx(original.error(values), rel=1e-6, abs=1e-9)


def test_fusing_two_measurements():
    z = np.array([1.0, 0.5, 0.3])
    cov = np.diag([0.01, 0.02, 0.001])
    zf, covf = fuse(z, cov, z, cov)
    np.testing.assert_allclose(zf, z, atol=1e-12)
    np.testing.assert_allclose(covf, cov / 2, atol=1e-12)
    z2 = z + np.array([0.1, 0.0, 0.0])
    zf, _ = fuse(z, cov, z2, 1e6 * cov)  # a vague second one barely moves it
    np.testing.assert_allclose(zf, z, atol=1e-6)
    zf, _ = fuse(z, 1e6 * cov, z2, cov)  # a vague first one: the second wins
    np.testing.assert_allclose(zf[:2], z2[:2], atol=1e-4)


def test_a_late_gps_fix_on_reduced_nodes_is_dropped():
    graph = PoseGraph(reduce_distance_m=0.5, reduce_lag=5, reduce_batch_nodes=1)
    graph.add_robot("a", [0, 0, 0])
    for i in range(40):
        d = None if i == 0 else [0.1, 0.0, 0.0]
        graph.add_node("a", i, d, None if i == 0 else ODOM_COV, stamp=float(i))
        graph.update()
    chain = graph._chains["a"]
    assert chain.alias_key[10] >= 0 or chain.alias_key[11] >= 0
    graph.add_gps_fix("a", 10.5, [1.05, 0.0], [1.0, 1.0, 1.0])  # long after its nodes
    graph.flush_gps()
    graph.update()
    assert graph.gps_stats()["gps_dropped_reduced"] == 1
    assert graph.gps_stats()["gps_factors"] == 0
    np.testing.assert_allclose(graph.pose("a", 39)[:2], [3.9, 0.0], atol=1e-6)


def test_final_constraints_between_the_same_two_nodes_are_one_factor():
    """Gaussian constraints (no kernel) fused exactly enough: same optimum, one factor."""
    truth = [np.array([0.5 * i, 0.0, 0.0]) for i in range(10)]
    measured = ([4.5, 0.0, 0.0], [4.52, -0.01, 0.003], [4.49, 0.02, -0.002])
    graphs = []
    for finalize in (False, True):
        graph = PoseGraph(reduce_distance_m=0.3, reduce_after_nodes=1000)  # none aliased
        graph.add_robot("a", truth[0])
        for i in range(10):
            d = None if i == 0 else [0.51, 0.0, 0.001]  # drifting odometry
            graph.add_node("a", i, d, None if i == 0 else ODOM_COV)
        ids = [graph.add_constraint(("a", 0), ("a", 9), z, LOOP_COV, robust=None) for z in measured]
        # the same relation measured the other way round (node 0 seen from node 9)
        z, cov = invert_with_covariance(np.array([4.51, 0.01, 0.002]), LOOP_COV)
        ids.append(graph.add_constraint(("a", 9), ("a", 0), z, cov, robust=None))
        graph.update()
        if finalize:
            for fid in ids:
                graph.finalize_constraint(fid)
            graph.update(extra_iterations=3)
            with pytest.raises(CollabSlamError):
                graph.remove_constraint(ids[1])  # fused into the first: no longer its own
        graphs.append(graph)
    plain, fused = graphs
    loops = [r for r in fused._factors.values() if r.kind == "constraint"]
    assert len(loops) == 1 and fused.reduction_stats()["fused_constraints"] == 3
    np.testing.assert_allclose(fused.poses("a"), plain.poses("a"), atol=2e-4)


def test_a_constraint_is_finalized_once():
    graph = PoseGraph(reduce_distance_m=0.5)
    graph.add_robot("a", [0, 0, 0])
    for i in range(3):
        graph.add_node("a", i, None if i == 0 else [1.0, 0, 0], None if i == 0 else ODOM_COV)
    fid = graph.add_constraint(("a", 0), ("a", 2), [2.0, 0, 0], LOOP_COV)
    graph.update()
    graph.finalize_constraint(fid)
    with pytest.raises(CollabSlamError):
        graph.finalize_constraint(fid)
    with pytest.raises(CollabSlamError):
        graph.finalize_constraint(10_000)


def test_fused_robust_constraints_weigh_what_they_did_apart():
    """Huber constraints far outside their kernel's quadratic zone: n fused ones (width
    k sqrt(n)) pull exactly as the n separate ones did, not sqrt(n) times less."""
    graphs = []
    for finalize in (False, True):
        graph = PoseGraph(reduce_distance_m=0.3, reduce_after_nodes=1000)
        graph.add_robot("a", [0, 0, 0])
        for i in range(10):
            d = None if i == 0 else [0.5, 0.0, 0.02]  # 0.5 rad of drift by node 9
            graph.add_node("a", i, d, None if i == 0 else ODOM_COV)
        z = [4.5, 0.0, 0.0]
        ids = [graph.add_constraint(("a", 0), ("a", 9), z, LOOP_COV) for _ in range(4)]
        graph.update(extra_iterations=5)
        if finalize:
            for fid in ids:
                graph.finalize_constraint(fid)
            graph.update(extra_iterations=10)
            assert sum(r.kind == "constraint" for r in graph._factors.values()) == 1
        graphs.append(graph)
    np.testing.assert_allclose(graphs[1].poses("a"), graphs[0].poses("a"), atol=1e-4)


def test_a_fresh_isam2_now_and_then_holds_the_same_graph():
    """``rebuild_nodes``: once reducing, every so many nodes iSAM2 is built anew from the
    same factors at the current estimate; the factors keep their ids (a constraint can
    still be removed) and get new slots, none left empty."""
    graphs = {}
    for every in (0, 100):
        graph = PoseGraph(
            heads_last=True, reduce_distance_m=0.5, reduce_lag=10, reduce_batch_nodes=1,
            reduce_after_nodes=200, rebuild_nodes=every,
        )  # fmt: skip
        graph.add_robot("a", [0, 0, 0])
        truth = fly_with_window(graph, 4, 40)
        graphs[every] = graph
    plain, rebuilt = graphs[0], graphs[100]
    assert plain.num_rebuilds == 0 and rebuilt.num_rebuilds >= 3  # 628 nodes, from 200 on
    err = {k: np.linalg.norm(g.poses("a")[:, :2] - truth[:, :2], axis=1) for k, g in graphs.items()}
    assert err[100].max() < 0.2 and err[100].mean() < 1.2 * err[0].mean()
    n = 4 * LAP
    fid = rebuilt.add_constraint(("a", 3), ("a", n - 1), se2_between(truth[3], truth[-1]), LOOP_COV)
    rebuilt.update()
    rebuilt.rebuild()
    live = [r for r in rebuilt._factors.values() if r.isam_index is not None]
    assert rebuilt.factor_slots() == len(live) == len({r.isam_index for r in live})
    before = rebuilt.poses("a")
    rebuilt.remove_constraint(fid)  # by its slot in the new iSAM2
    rebuilt.update()
    assert fid not in rebuilt._factors
    assert rebuilt._isam.getFactorsUnsafe().nrFactors() == len(live) - 1
    assert np.abs(rebuilt.poses("a")[:, :2] - before[:, :2]).max() < 0.05
    rebuilt.add_constraint(("a", 5), ("a", n - 2), se2_between(truth[5], truth[-2]), LOOP_COV)
    with pytest.raises(CollabSlamError):
        rebuilt.rebuild()  # a factor is pending: between updates only
