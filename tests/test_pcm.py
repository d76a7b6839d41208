"""PCM outlier rejection on generated two-robot graphs: properties, not magic numbers."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from basestation.pcm import (
    DEFAULT_THRESHOLD_CHI2,
    IncrementalPcm,
    LoopMeasurement,
    _maximum_clique,
    _reversed,
    cycle_mahalanobis2,
    max_consistent_set,
    pairwise_consistent,
)
from common.errors import CollabSlamError
from common.geometry import se2_between, se2_compose, se2_inverse

STEP_SIGMAS = np.array([0.02, 0.02, math.radians(0.5)])  # odometry per step (m, m, rad)
LOOP_SIGMAS = np.array([0.03, 0.03, math.radians(0.5)])  # a verified match (m, m, rad)


def _adjoint(T: np.ndarray) -> np.ndarray:
    c, s = math.cos(T[2]), math.sin(T[2])
    return np.array([[c, -s, T[1]], [s, c, -T[0]], [0.0, 0.0, 1.0]])


class Robot:
    """A true trajectory and the drifting chain of noisy odometry estimated from it."""

    def __init__(self, start: np.ndarray, n: int, rng: np.random.Generator) -> None:
        steps = np.column_stack(
            [rng.uniform(0.3, 0.6, n - 1), rng.normal(0, 0.05, n - 1), rng.normal(0, 0.25, n - 1)]
        )
        self.truth = [start]
        for d in steps:
            self.truth.append(se2_compose(self.truth[-1], d))
        noisy = steps + rng.normal(0.0, 1.0, steps.shape) * STEP_SIGMAS
        self.estimate = [np.zeros(3)]  # the robot's own (drifting) frame
        for d in noisy:
            self.estimate.append(se2_compose(self.estimate[-1], d))

    def odometry(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """T_i_j of the estimate and its covariance (frame j), compounded step by step."""
        lo, hi = min(i, j), max(i, j)
        step_cov = np.diag(STEP_SIGMAS**2)
        cov = np.zeros((3, 3))
        for k in range(lo + 1, hi + 1):  # T_lo_k = T_lo_(k-1) * step_k
            step = se2_between(self.estimate[k - 1], self.estimate[k])
            A = _adjoint(se2_inverse(step))
            cov = A @ cov @ A.T + step_cov
        T = se2_between(self.estimate[lo], self.estimate[hi])
        if i > j:  # T_j_i -> T_i_j: covariance moves to the other end
            A = -_adjoint(T)
            T, cov = se2_inverse(T), A @ cov @ A.T
        return T, cov


def _measure(ra, i, rb, j, rng, wrong=False) -> tuple[np.ndarray, np.ndarray]:
    T = se2_between(ra.truth[i], rb.truth[j])
    if wrong:  # a false match: off by metres and tens of degrees
        off = rng.uniform(0.6, 2.0) * np.array([math.cos(a := rng.uniform(0, 6.3)), math.sin(a)])
        T = se2_compose(T, [off[0], off[1], rng.choice([-1, 1]) * rng.uniform(0.2, 0.8)])
    return se2_compose(T, rng.normal(0.0, 1.0, 3) * LOOP_SIGMAS), np.diag(LOOP_SIGMAS**2)


@pytest.fixture
def world():
    rng = np.random.default_rng(42)
    robots = {
        "a": Robot(np.array([0.0, 0.0, 0.0]), 40, rng),
        "b": Robot(np.array([1.0, 2.0, 1.0]), 40, rng),
    }

    def odometry(robot: str, i: int, j: int):
        return robots[robot].odometry(i, j)

    return robots, odometry, rng


def _loops(robots, rng, pairs, wrong, start_id=0, ra="a", rb="b"):
    out = []
    for k, (i, j) in enumerate(pairs):
        T, cov = _measure(robots[ra], i, robots[rb], j, rng, wrong=wrong)
        out.append(LoopMeasurement(start_id + k, ra, i, rb, j, T, cov))
    return out


def test_wrong_inter_robot_loops_are_excluded(world):
    robots, odometry, rng = world
    good = _loops(robots, rng, [(3, 5), (8, 10), (15, 12), (22, 30), (30, 33), (37, 20)], False)
    bad = _loops(robots, rng, [(5, 7), (18, 25), (33, 36)], True, start_id=100)
    mixed = [good[0], bad[0], good[1], good[2], bad[1], good[3], good[4], bad[2], good[5]]
    assert max_consistent_set(mixed, odometry) == {m.id for m in good}
    # the heuristic finds the same set here
    assert max_consistent_set(mixed, odometry, max_exact=0) == {m.id for m in good}


@pytest.mark.parametrize("max_exact", [40, 0])
def test_incremental_pcm_matches_the_batch_answer(world, max_exact):
    robots, odometry, rng = world
    good = _loops(robots, rng, [(3, 5), (8, 10), (15, 12), (22, 30), (30, 33), (37, 20)], False)
    bad = _loops(robots, rng, [(5, 7), (18, 25), (33, 36)], True, start_id=100)
    mixed = [good[0], bad[0], good[1], good[2], bad[1], good[3], good[4], bad[2], good[5]]

    def batch(robot, ii, jj):
        out = [
            odometry(robot, int(i), int(j)) if i != j else (np.zeros(3), np.zeros((3, 3)))
            for i, j in zip(ii, jj, strict=True)
        ]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out])

    pcm = IncrementalPcm(max_exact=max_exact)
    vec = IncrementalPcm(max_exact=max_exact)
    for m in mixed:
        got = pcm.add(m if m.id % 2 else _reversed(m), odometry)  # either orientation
        assert vec.add(m if m.id % 2 else _reversed(m), odometry, batch) == got
    np.testing.assert_allclose(vec._d2, pcm._d2, rtol=1e-9)
    assert got == pcm.accepted == {m.id for m in good}
    # loops of one robot, both paths agree too
    loops = IncrementalPcm()
    loops_vec = IncrementalPcm()
    for k, (i, j) in enumerate([(2, 30), (31, 5), (10, 38), (36, 12)]):
        T, cov = _measure(robots["a"], i, robots["a"], j, rng, wrong=k == 2)
        m = LoopMeasurement(500 + k, "a", i, "a", j, T, cov)
        assert loops_vec.add(m, odometry, batch) == loops.add(m, odometry)
    np.testing.assert_allclose(loops_vec._d2, loops._d2, rtol=1e-9)
    with pytest.raises(CollabSlamError):
        pcm.add(LoopMeasurement(999, "a", 1, "a", 30, np.zeros(3), np.eye(3)), odometry)


def test_a_consistent_pair_of_outliers_loses_to_the_majority(world):
    """Perceptual aliasing: two wrong matches that agree with each other (robot b seen as
    if shifted by the same rigid motion) must lose to the larger group of good ones."""
    robots, odometry, rng = world
    good = _loops(robots, rng, [(3, 5), (15, 12), (30, 33), (37, 20)], False)
    D = np.array([1.2, -0.4, 0.3])
    aliased = []
    for k, (i, j) in enumerate([(10, 14), (26, 28)]):
        T = se2_between(robots["a"].truth[i], se2_compose(D, robots["b"].truth[j]))
        aliased.append(LoopMeasurement(200 + k, "a", i, "b", j, T, np.diag(LOOP_SIGMAS**2)))
    assert pairwise_consistent(aliased[0], aliased[1], odometry)
    assert max_consistent_set(aliased + good, odometry) == {m.id for m in good}


def test_pairwise_consistency_of_good_and_bad(world):
    robots, odometry, rng = world
    g1, g2 = _loops(robots, rng, [(4, 6), (30, 25)], False)
    (b1,) = _loops(robots, rng, [(10, 10)], True, start_id=10)
    assert pairwise_consistent(g1, g2, odometry)
    assert not pairwise_consistent(g1, b1, odometry)
    assert not pairwise_consistent(b1, g2, odometry)
    # symmetric in its arguments
    assert cycle_mahalanobis2(g1, b1, odometry) == pytest.approx(
        cycle_mahalanobis2(b1, g1, odometry), rel=0.2
    )


def test_orientation_of_a_measurement_does_not_matter(world):
    robots, odometry, rng = world
    g1, g2 = _loops(robots, rng, [(4, 6), (30, 25)], False)
    T_b_a = se2_inverse(g2.T_a_b)
    A = -_adjoint(g2.T_a_b)
    flipped = LoopMeasurement(
        g2.id, "b", g2.index_b, "a", g2.index_a, T_b_a, A @ g2.covariance @ A.T
    )
    d_same = cycle_mahalanobis2(g1, g2, odometry)
    assert cycle_mahalanobis2(g1, flipped, odometry) == pytest.approx(d_same, rel=1e-6)
    assert d_same < DEFAULT_THRESHOLD_CHI2


def test_wrong_intra_robot_loops_are_excluded(world):
    robots, odometry, rng = world
    pairs_good = [(2, 20), (5, 25), (9, 31), (12, 35), (25, 39), (0, 38)]
    good = _loops(robots, rng, pairs_good, False, ra="a", rb="a")
    bad = _loops(robots, rng, [(3, 30), (10, 22), (15, 37)], True, start_id=50, ra="a", rb="a")
    # one good loop stored the other way round (newer node first)
    g = good[2]
    A = -_adjoint(g.T_a_b)
    good[2] = LoopMeasurement(
        g.id, "a", g.index_b, "a", g.index_a, se2_inverse(g.T_a_b), A @ g.covariance @ A.T
    )
    assert max_consistent_set(bad + good, odometry) == {m.id for m in good}


def test_groups_are_independent(world):
    robots, odometry, rng = world
    inter = _loops(robots, rng, [(3, 5), (8, 10), (22, 30)], False)
    inter_bad = _loops(robots, rng, [(18, 25)], True, start_id=10)
    intra = _loops(robots, rng, [(2, 20), (5, 25)], False, start_id=20, ra="b", rb="b")
    single = _loops(robots, rng, [(1, 33)], True, start_id=30, ra="a", rb="a")
    got = max_consistent_set(inter + inter_bad + intra + single, odometry)
    # a lone measurement is trivially consistent, even a wrong one: PCM cannot judge it
    assert got == {0, 1, 2, 20, 21, 30}


def test_single_and_empty():
    def odometry(robot, i, j):
        raise AssertionError("a single measurement needs no odometry")

    m = LoopMeasurement(7, "a", 1, "b", 2, np.array([1.0, 0.0, 0.1]), np.eye(3) * 0.01)
    assert max_consistent_set([m], odometry) == {7}
    assert max_consistent_set([], odometry) == set()


def test_duplicate_ids_and_mismatched_robots_raise(world):
    robots, odometry, rng = world
    g1, g2 = _loops(robots, rng, [(4, 6), (30, 25)], False)
    with pytest.raises(CollabSlamError):
        max_consistent_set(
            [g1, LoopMeasurement(g1.id, "a", 7, "b", 8, g2.T_a_b, g2.covariance)], odometry
        )
    intra = LoopMeasurement(9, "a", 1, "a", 20, g2.T_a_b, g2.covariance)
    with pytest.raises(CollabSlamError):
        pairwise_consistent(g1, intra, odometry)


def test_maximum_clique_matches_brute_force():
    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 9, 12):
        for density in (0.2, 0.5, 0.8):
            upper = np.triu(rng.random((n, n)) < density, 1)
            adj = upper | upper.T
            d2 = rng.random((n, n))
            d2 = d2 + d2.T
            best = max(
                (
                    len(c)
                    for r in range(1, n + 1)
                    for c in itertools.combinations(range(n), r)
                    if all(adj[i, j] for i, j in itertools.combinations(c, 2))
                ),
                default=0,
            )
            clique = _maximum_clique(adj, d2)
            assert len(clique) == best
            assert all(adj[i, j] for i, j in itertools.combinations(clique, 2))


def test_maximum_clique_with_exponentially_many_ties_falls_back_to_the_heuristic():
    """Pairs of matches that contradict each other, every other pair consistent (a
    repetitive corridor: at each place one right match and one a period off): 2^20
    maximum cliques, all collected before (~10 s for 40 matches, 31 s for the 40th
    match of a real corridor, on the base station's main thread). Past its step budget
    the search takes PCM's heuristic, which finds one of them."""
    n = 40
    part = np.arange(n) // 2
    adj = part[:, None] != part[None, :]
    d2 = np.ones((n, n))
    for steps in (1000, None):
        clique = _maximum_clique(adj, d2, steps) if steps else _maximum_clique(adj, d2)
        assert len(clique) == 20 and len(set(part[clique])) == 20


def test_incremental_pcm_keeps_a_bounded_window(world):
    """A pair closing many loops: PCM keeps its last `window` matches and their
    window x window consistency matrix (it grew with the square of all matches);
    within the window the answer is the batch one over the same matches, and a
    match that left the window is counted as settled."""
    robots, odometry, rng = world
    pairs = [(i, (7 * i) % 40) for i in range(2, 38)]
    good = _loops(robots, rng, pairs, False)
    bad = _loops(robots, rng, [(5, 7), (18, 25), (33, 36), (11, 2)], True, start_id=100)
    stream = good[:9] + [bad[0]] + good[9:20] + [bad[1], bad[2]] + good[20:] + [bad[3]]
    window = 8
    pcm = IncrementalPcm(window=window)
    for k, m in enumerate(stream, start=1):
        accepted = pcm.add(m, odometry)
        kept = pcm.measurements
        assert len(kept) == min(k, window) and pcm._d2.shape == (len(kept), len(kept))
        assert pcm.settled == k - len(kept)
        assert [x.id for x in kept] == [x.id for x in stream[k - len(kept) : k]]
        assert accepted <= pcm.ids
        assert accepted == max_consistent_set(kept, odometry)  # exact below max_exact
        if m.id >= 100:
            assert m.id not in accepted  # a wrong match in a window of good ones
    assert len(pcm.accepted) == window - 1  # the last wrong one is out
    with pytest.raises(CollabSlamError):
        IncrementalPcm(window=0)


@pytest.mark.parametrize("yaw", [0.0, 1e-12, 3e-9, 1e-6, 9e-5, 1.1e-4, 0.3, -2.0, 3.14159])
def test_se2_log_is_finite_and_exact_for_any_small_rotation(yaw: float) -> None:
    """_log(T) = [a x + h y, -h x + a y, w] with h = w / 2, a = h cot(h): for small
    angles against the series of h cot(h) (exact in float64 there), for large ones
    against gtsam's Logmap."""
    import gtsam

    from basestation.pcm import _log

    T = np.array([0.7, -0.4, yaw])
    xi = _log(T)
    if abs(yaw) < 1e-3:
        h = 0.5 * yaw
        a = 1.0 - h * h / 3.0 - h**4 / 45.0
        expected = np.array([a * 0.7 + h * -0.4, -h * 0.7 + a * -0.4, yaw])
    else:
        expected = np.asarray(gtsam.Pose2.Logmap(gtsam.Pose2(*T)))
    np.testing.assert_allclose(xi, expected, rtol=1e-14, atol=1e-15)
