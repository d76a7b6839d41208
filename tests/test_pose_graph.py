"""Tests for basestation.pose_graph (iSAM2 back end) and basestation.batch_solver."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from basestation.batch_solver import batch_optimize
from basestation.pose_graph import ROBOT_KEY_ALPHABET, PoseGraph
from benchmarks.backend import split_g2o
from common.config import Config
from common.errors import CollabSlamError
from common.g2o_io import read_g2o
from common.geometry import se2_between, se2_compose, wrap_angle

ODO_COV = np.diag([0.05**2, 0.05**2, 0.01**2])  # m^2, m^2, rad^2
LC_COV = np.diag([0.1**2, 0.1**2, 0.02**2])


def assert_pose_close(got: NDArray, want: NDArray, tol_xy: float, tol_yaw: float) -> None:
    got, want = np.atleast_2d(got), np.atleast_2d(want)
    assert np.abs(got[:, :2] - want[:, :2]).max() <= tol_xy, (got, want)
    assert np.abs(wrap_angle(got[:, 2] - want[:, 2])).max() <= tol_yaw, (got, want)


def compose_chain(start: NDArray, deltas: list[NDArray]) -> NDArray:
    poses = [np.asarray(start, dtype=float)]
    for d in deltas:
        poses.append(se2_compose(poses[-1], d))
    return np.array(poses)


def square_deltas(side: int = 5) -> list[NDArray]:
    """A closed 4*side-step square of 1 m steps, turning left at each corner."""
    return [
        np.array([1.0, 0.0, np.pi / 2 if k % side == 0 else 0.0]) for k in range(1, 4 * side + 1)
    ]


def build_chain(graph: PoseGraph, robot: str, start: NDArray | None, deltas: list[NDArray]) -> None:
    graph.add_robot(robot, start)
    graph.add_node(robot, 0, None, None)
    for k, d in enumerate(deltas, start=1):
        graph.add_node(robot, k, d, ODO_COV)


def test_odometry_chain_gives_composed_poses() -> None:
    rng = np.random.default_rng(1)
    deltas = [
        np.array([rng.uniform(0, 1), rng.uniform(-0.2, 0.2), rng.uniform(-0.5, 0.5)])
        for _ in range(30)
    ]
    start = np.array([2.0, -1.0, 0.3])
    graph = PoseGraph()
    build_chain(graph, "a", start, deltas)
    assert_pose_close(graph.poses("a"), compose_chain(start, deltas), 1e-9, 1e-9)  # pending
    stats = graph.update()
    assert stats.num_new_nodes == 31 and stats.robots_with_new_nodes == {"a"}
    assert_pose_close(graph.poses("a"), compose_chain(start, deltas), 1e-6, 1e-6)
    assert graph.num_nodes() == graph.num_nodes("a") == 31
    assert graph.latest_index("a") == 30 and graph.robots() == ["a"]
    cov = graph.marginal_covariance("a", 30)
    assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert graph.marginal_covariance("a", 30)[0, 0] > graph.marginal_covariance("a", 1)[0, 0]


def test_known_starts_keep_each_chain_at_its_prior() -> None:
    starts = {"a": np.array([0.0, 0.0, 0.0]), "b": np.array([10.0, 5.0, np.pi / 2])}
    deltas = square_deltas()
    graph = PoseGraph()
    for robot, start in starts.items():
        build_chain(graph, robot, start, deltas)
    graph.update()
    for robot, start in starts.items():
        assert_pose_close(graph.pose(robot, 0), start, 1e-6, 1e-6)
        assert_pose_close(graph.poses(robot), compose_chain(start, deltas), 1e-6, 1e-6)


def test_correct_loop_closure_reduces_drift() -> None:
    deltas = square_deltas()
    truth = compose_chain(np.zeros(3), deltas)
    biased = [d + np.array([0.0, 0.0, 0.03]) for d in deltas]  # yaw drifts 0.03 rad/step
    graph = PoseGraph()
    build_chain(graph, "a", np.zeros(3), biased)
    graph.update()
    last = len(deltas)
    yaw_before = abs(wrap_angle(graph.pose("a", last)[2] - truth[last, 2]))
    err_before = np.linalg.norm(graph.poses("a")[:, :2] - truth[:, :2], axis=1).max()
    tight = np.diag([0.02**2, 0.02**2, 0.002**2])  # a precise scan match
    graph.add_constraint(("a", last), ("a", 0), np.zeros(3), tight, robust=None)
    stats = graph.update(extra_iterations=5)
    assert stats.changed_robots == {"a"}
    yaw_after = abs(wrap_angle(graph.pose("a", last)[2] - truth[last, 2]))
    err_after = np.linalg.norm(graph.poses("a")[:, :2] - truth[:, :2], axis=1).max()
    assert yaw_before > 0.5
    assert yaw_after < 0.1 * yaw_before
    assert err_after < 0.25 * err_before


@pytest.mark.parametrize("kernel", ["huber", "cauchy"])
def test_robust_kernel_limits_a_wrong_loop_closure(kernel: str) -> None:
    deltas = square_deltas()
    truth = compose_chain(np.zeros(3), deltas)
    wrong = np.array([3.0, 1.0, 0.5])  # node 10 is really at [5, 5, pi]
    errors = {}
    for robust in (None, kernel):
        graph = PoseGraph()
        build_chain(graph, "a", np.zeros(3), deltas)
        graph.update()
        graph.add_constraint(("a", 0), ("a", 10), wrong, LC_COV, robust=robust)
        graph.update(extra_iterations=10)
        errors[robust] = np.linalg.norm(graph.poses("a")[:, :2] - truth[:, :2], axis=1).max()
    assert errors[None] > 1.0
    assert errors[kernel] < 0.1 * errors[None]


def test_removing_a_constraint_restores_the_estimate() -> None:
    deltas = [d + np.array([0.0, 0.0, 0.02]) for d in square_deltas()]
    graph = PoseGraph()
    build_chain(graph, "a", np.zeros(3), deltas)
    graph.update()
    before = graph.poses("a")
    fid = graph.add_constraint(("a", 20), ("a", 0), np.zeros(3), LC_COV, robust=None)
    graph.update(extra_iterations=5)
    assert np.abs(graph.poses("a") - before).max() > 0.5
    slots = graph.factor_slots()  # prior, 20 odometry factors, the loop closure
    assert slots == 22
    graph.remove_constraint(fid)
    stats = graph.update(extra_iterations=5)
    assert stats.num_removed_factors == 1
    assert graph.factor_slots() == slots  # iSAM2 keeps the removed factor's slot
    assert_pose_close(graph.poses("a"), before, 1e-3, 1e-4)
    with pytest.raises(CollabSlamError):
        graph.remove_constraint(fid)
    # a constraint removed before it ever reached iSAM2 is simply dropped
    pending = graph.add_constraint(("a", 20), ("a", 0), np.zeros(3), LC_COV)
    graph.remove_constraint(pending)
    assert graph.update().num_new_factors == 0
    # ... also when it waits next to a new node and another constraint: those two go in
    # (the update's factor graph, built as the factors came, is built again without it)
    graph.add_node("a", 21, np.array([1.0, 0.0, 0.0]), ODO_COV)
    kept = graph.add_constraint(("a", 20), ("a", 21), np.array([1.0, 0, 0]), LC_COV, robust=None)
    dropped = graph.add_constraint(("a", 20), ("a", 0), np.zeros(3), LC_COV)
    graph.remove_constraint(dropped)
    stats = graph.update(extra_iterations=5)
    assert (stats.num_new_factors, stats.num_new_nodes) == (2, 1)  # odometry and kept
    assert_pose_close(graph.poses("a")[:21], before, 1e-3, 1e-4)  # no loop closed
    graph.remove_constraint(kept)  # its iSAM2 slot was read from this update
    assert graph.update().num_removed_factors == 1


@pytest.mark.parametrize("first_start", [np.array([1.0, 2.0, 0.5]), None])
@pytest.mark.parametrize(("robust", "skip"), [("huber", 1), (None, 1), ("huber", 10)])
def test_floating_chain_merges_after_one_inter_robot_constraint(
    first_start: NDArray | None, robust: str | None, skip: int
) -> None:
    graph = PoseGraph(relinearize_skip=skip)
    build_chain(graph, "a", first_start, [np.array([1.0, 0.0, 0.2])] * 14)
    build_chain(graph, "b", None, [np.array([1.0, 0.0, -0.15])] * 14)
    graph.update()
    chain_b = graph.poses("b")
    assert_pose_close(chain_b[0], np.zeros(3), 1e-9, 1e-9)  # floating: its own frame
    T_a_b = np.array([-20.0, 30.0, 2.5])
    fid = graph.add_constraint(("a", 7), ("b", 3), T_a_b, LC_COV, robust=robust)
    stats = graph.update()
    assert "b" in stats.changed_robots
    assert_pose_close(se2_between(graph.pose("a", 7), graph.pose("b", 3)), T_a_b, 1e-6, 1e-6)
    if first_start is not None:
        assert_pose_close(graph.pose("a", 0), first_start, 1e-6, 1e-6)
    # chain b moved rigidly: its internal relative poses are unchanged
    b = graph.poses("b")
    assert_pose_close(
        se2_between(b[:-1], b[1:]), se2_between(chain_b[:-1], chain_b[1:]), 1e-6, 1e-6
    )
    # removing the only link makes b float again (re-gauged, still solvable)
    graph.remove_constraint(fid)
    graph.update()
    graph.add_node("b", 15, np.array([1.0, 0.0, 0.0]), ODO_COV)
    graph.update()
    assert_pose_close(graph.pose("b", 0), b[0], 1e-6, 1e-6)


def test_a_floating_map_moves_rigidly_half_a_turn() -> None:
    """Before a join the floating map is moved where the matches put it (Gauss-Newton
    from half a turn off can settle a long chain in a bent minimum): every node moves by
    the same rigid motion, relative poses stay; a map with a known start does not move."""
    graph = PoseGraph()
    build_chain(graph, "a", np.zeros(3), [np.array([1.0, 0.0, 0.1])] * 30)
    build_chain(graph, "b", None, [np.array([1.0, 0.0, -0.12])] * 60)
    graph.update()
    before = graph.poses("b")
    T = np.array([-25.0, 40.0, 3.1])
    assert graph.move_floating("b", T)
    after = graph.poses("b")
    assert_pose_close(after, se2_compose(T, before), 1e-4, 1e-5)
    assert not graph.move_floating("a", T)
    assert_pose_close(
        graph.poses("a")[-1],
        compose_chain(np.zeros(3), [np.array([1.0, 0.0, 0.1])] * 30)[-1],
        1e-6,
        1e-6,
    )


def test_new_floating_chain_joins_in_the_same_update() -> None:
    graph = PoseGraph()
    build_chain(graph, "a", np.zeros(3), [np.array([1.0, 0.0, 0.1])] * 5)
    graph.update()
    build_chain(graph, "b", None, [np.array([0.5, 0.0, -0.3])] * 5)
    T_a_b = np.array([3.0, -4.0, -2.0])
    graph.add_constraint(("a", 5), ("b", 2), T_a_b, LC_COV)
    graph.update()
    assert_pose_close(se2_between(graph.pose("a", 5), graph.pose("b", 2)), T_a_b, 1e-6, 1e-6)
    assert_pose_close(graph.pose("a", 0), np.zeros(3), 1e-6, 1e-6)


def test_invalid_input_raises() -> None:
    graph = PoseGraph()
    build_chain(graph, "a", np.zeros(3), [np.array([1.0, 0.0, 0.0])] * 3)
    bad_covs = [
        np.diag([1.0, 1.0, -1.0]),
        np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
        np.diag([1.0, np.nan, 1.0]),
        np.diag([1.0, np.inf, 1.0]),
        np.eye(2),
        np.zeros((3, 3)),
        np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),  # 2x2 minor < 0
        np.array([[1.0, 0.9, 0.9], [0.9, 1.0, -0.9], [0.9, -0.9, 1.0]]),  # only det < 0
    ]
    for cov in bad_covs:
        with pytest.raises(CollabSlamError):
            graph.add_node("a", 4, np.array([1.0, 0.0, 0.0]), cov)
        with pytest.raises(CollabSlamError):
            graph.add_constraint(("a", 0), ("a", 3), np.zeros(3), cov)
    with pytest.raises(CollabSlamError, match="expected node 4"):
        graph.add_node("a", 5, np.array([1.0, 0.0, 0.0]), ODO_COV)
    with pytest.raises(CollabSlamError):
        graph.add_node("a", 4, np.array([1.0, np.inf, 0.0]), ODO_COV)
    with pytest.raises(CollabSlamError):
        graph.add_node("zz", 0, None, None)
    with pytest.raises(CollabSlamError):
        graph.add_constraint(("a", 0), ("a", 9), np.zeros(3), LC_COV)
    with pytest.raises(CollabSlamError):
        graph.add_constraint(("a", 0), ("a", 1), np.zeros(3), LC_COV, robust="tukey")
    with pytest.raises(CollabSlamError):
        graph.add_robot("a", None)
    with pytest.raises(CollabSlamError):
        graph.marginal_covariance("a", 0)  # not optimized yet
    graph.add_node("a", 4, np.array([1.0, 0.0, 0.0]), ODO_COV)  # state is still usable
    graph.update()
    assert graph.num_nodes("a") == 5


def test_robot_alphabet_is_bounded() -> None:
    graph = PoseGraph()
    for n in range(len(ROBOT_KEY_ALPHABET)):
        graph.add_robot(f"r{n}", None)
    with pytest.raises(CollabSlamError, match="at most"):
        graph.add_robot("one_too_many", None)


def test_chains_past_the_lowercase_letters_keep_their_poses() -> None:
    """Keys sort by character and 'A' < 'a': the 27th chain's rows came first in the
    estimate, and (unreduced) every robot's poses were another's (r0 read 2600 m)."""
    graph = PoseGraph()
    for k in range(28):
        graph.add_robot(f"r{k}", np.array([100.0 * k, 0.0, 0.0]))
        graph.add_node(f"r{k}", 0, None, None)
        graph.add_node(f"r{k}", 1, [1.0, 0.0, 0.0], np.eye(3) * 1e-4)
    graph.update()
    for k in (0, 1, 25, 26, 27):
        np.testing.assert_allclose(graph.poses(f"r{k}")[:, 0], [100.0 * k, 100.0 * k + 1])
        assert graph.pose(f"r{k}", 0)[0] == pytest.approx(100.0 * k)


def _feed_m3500(graph: PoseGraph, m3500: Path, n_nodes: int, n_robots: int) -> int:
    """Feed an M3500 prefix node by node, cut into one chain per robot (the bench's
    split, robot 0 at the file's first vertex, the others floating until an edge
    links them), one update per node. Returns the number of inter-robot constraints."""
    feed = split_g2o(read_g2o(m3500), n_nodes,
                     [f"r{k}" for k in range(n_robots)], known_starts=False)  # fmt: skip
    for robot, start in feed.starts.items():
        graph.add_robot(robot, start)
    inter_robot = 0
    for node in feed.nodes:
        graph.add_node(node.robot_id, node.index, node.delta, node.covariance)
        for c in node.constraints:
            graph.add_constraint(c.key_a, c.key_b, c.T_a_b, c.covariance, robust=None)
            inter_robot += c.key_a[0] != c.key_b[0]
        graph.update()
    return inter_robot


@pytest.mark.parametrize("n_robots", [1, 3])
def test_incremental_m3500_prefix_matches_batch(n_robots: int, shared_data: Path) -> None:
    graph = PoseGraph()
    inter_robot = _feed_m3500(graph, shared_data / "g2o/M3500.g2o", n_nodes=900, n_robots=n_robots)
    assert graph.num_nodes() == 900
    assert (inter_robot > 0) == (n_robots > 1)
    batch = batch_optimize(graph, start="current")
    assert batch.chi2 <= graph.chi2() <= 1.02 * batch.chi2 + 1e-6
    for robot, poses in batch.poses.items():
        assert_pose_close(graph.poses(robot), poses, 0.05, 0.01)
    if n_robots == 1:  # from odometry, LM lands in the same minimum
        assert batch_optimize(graph, start="guess").chi2 == pytest.approx(batch.chi2, rel=1e-3)


def test_base_station_settings_match_batch_and_reorder(shared_data: Path) -> None:
    """The shipped iSAM2 settings (relinearize_skip, adaptive re-ordering, no change
    tracking) stay as accurate as batch LM; a low reorder threshold really re-orders."""
    b = Config().basestation
    assert not b.track_changes
    b.adaptive_reorder_threshold = 1.05  # re-order often on a short prefix
    graph = PoseGraph.from_config(b)
    feed = split_g2o(read_g2o(shared_data / "g2o/M3500.g2o"), 600)
    for robot, start in feed.starts.items():
        graph.add_robot(robot, start)
    reorders = 0
    for node in feed.nodes:
        graph.add_node(node.robot_id, node.index, node.delta, node.covariance)
        for c in node.constraints:
            graph.add_constraint(c.key_a, c.key_b, c.T_a_b, c.covariance, robust=None)
        stats = graph.update()
        assert stats.changed_robots is None
        reorders += stats.batch_reordered
    assert reorders > 0
    batch = batch_optimize(graph, start="guess")
    assert batch.chi2 <= graph.chi2() * (1 + 1e-9) and graph.chi2() <= 1.01 * batch.chi2
    for robot, poses in batch.poses.items():
        assert_pose_close(graph.poses(robot), poses, 0.05, 0.01)


def test_factorization_is_checked() -> None:
    with pytest.raises(CollabSlamError, match="factorization"):
        PoseGraph(factorization="LU")


def test_extra_iterations_relinearize_even_between_skips() -> None:
    deltas = [d + np.array([0.0, 0.0, 0.03]) for d in square_deltas()]
    tight = np.diag([0.02**2, 0.02**2, 0.002**2])
    chi2 = {}
    for skip in (1, 10):
        graph = PoseGraph(relinearize_skip=skip)
        build_chain(graph, "a", np.zeros(3), deltas)
        graph.update()
        graph.add_constraint(("a", 20), ("a", 0), np.zeros(3), tight, robust=None)
        graph.update(extra_iterations=5)
        chi2[skip] = graph.chi2()
    assert chi2[10] == pytest.approx(chi2[1], rel=1e-6)


def test_lazy_estimate_matches_tracked_estimate() -> None:
    deltas = [d + np.array([0.0, 0.0, 0.03]) for d in square_deltas()]
    graphs = {track: PoseGraph(track_changes=track) for track in (True, False)}
    for track, graph in graphs.items():
        build_chain(graph, "a", np.zeros(3), deltas)
        graph.update()
        graph.add_constraint(("a", 20), ("a", 0), np.zeros(3), LC_COV)
        stats = graph.update()
        assert (stats.changed_robots is None) == (not track)
        graph.add_node("a", 21, deltas[0], ODO_COV)
        graph.update()
    lazy, tracked = graphs[False], graphs[True]
    for i in (0, 7, 20, 21):  # single poses straight from iSAM2, before any full estimate
        assert_pose_close(lazy.pose("a", i), tracked.pose("a", i), 1e-9, 1e-9)
    assert_pose_close(lazy.poses("a"), tracked.poses("a"), 1e-9, 1e-9)


def test_a_degenerate_but_valid_odometry_covariance_does_not_stop_the_graph() -> None:
    """Variances of 100 m^2 along and 1e-6 across and in yaw (a corridor's, within what
    the protocol takes) made iSAM2's Cholesky fail after 14 keyframes: the base station
    stopped. The graph now goes on with QR, every factor and node kept."""
    g = PoseGraph()
    g.add_robot("r0", np.zeros(3))
    g.add_node("r0", 0, None, None)
    g.add_robot("r1", np.array([0.0, 5.0, 0.0]))
    g.add_node("r1", 0, None, None)
    cov = np.diag([100.0, 1e-6, 1e-6])
    expected = np.zeros(3)
    for k in range(1, 60):
        g.add_node("r0", k, [0.3, 0.0, 0.05], cov)
        g.add_node("r1", k, [0.3, 0.0, 0.0], np.diag([1e-4, 1e-4, 1e-6]))
        g.update()
        expected = se2_compose(expected, [0.3, 0.0, 0.05])
    assert g._isam.params().getFactorization() == "QR" and g.num_rebuilds == 1
    assert np.allclose(g.poses("r0")[-1], expected, atol=1e-6)
    assert np.allclose(g.poses("r1")[-1], [59 * 0.3, 5.0, 0.0], atol=1e-6)
    g.add_constraint(("r0", 10), ("r1", 10), se2_between(g.pose("r0", 10), g.pose("r1", 10)),
                     np.diag([1e-4, 1e-4, 1e-6]))  # fmt: skip
    g.update()  # and takes more
    assert np.allclose(g.poses("r0")[-1], expected, atol=1e-4)
