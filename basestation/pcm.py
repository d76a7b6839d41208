"""Pairwise Consistent Measurement set maximization (Mangelson et al., ICRA 2018).

Outlier rejection for loop closures and inter-robot constraints before they reach the
pose graph. Two measurements between the same pair of robots (or two loops of one
robot) are *pairwise consistent* when the cycle they close with the robots' own
odometry returns to the start: for m1 = T(a_i1, b_j1) and m2 = T(a_i2, b_j2),

    C = m1 * odo_b(j1 -> j2) * m2^-1 * odo_a(i2 -> i1)  ~  identity,

tested as the Mahalanobis distance of Log(C) under the first-order covariance of the
four pieces against a chi-square bound with 3 dof. The accepted set is the largest
group of measurements that are all pairwise consistent: a maximum clique of the
consistency graph (exact up to `max_exact` measurements, a greedy heuristic above).
Groups of different robot pairs do not constrain each other and are solved apart.

Conventions (same as `basestation.pose_graph`): poses [x, y, yaw] (m, m, rad), T_a_b
maps frame b into frame a; every covariance is 3x3 over [x, y, yaw] in the tangent
space of the pose it belongs to (right perturbation T * Exp(xi), gtsam's Pose2), so
the covariance of T_a_b is expressed in frame b.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from common.errors import CollabSlamError
from common.geometry import se2_compose, se2_inverse, wrap_angle

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
# odometry(robot, i, j) -> (T_i_j [x, y, yaw], its 3x3 covariance in frame j)
Odometry = Callable[[str, int, int], tuple[np.ndarray, np.ndarray]]
# the same for index arrays I, J (n,) -> (n, 3) poses, (n, 3, 3) covariances
BatchOdometry = Callable[[str, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

DEFAULT_THRESHOLD_CHI2 = float(chi2.ppf(0.99, 3))  # ~11.34
MAX_CLIQUE_STEPS = 20_000  # branch-and-bound expansions before the heuristic (~1 s)


class _OutOfBudget(Exception):
    pass


@dataclass(frozen=True)
class LoopMeasurement:
    """A candidate constraint: node `index_b` of `robot_b` seen from node `index_a` of
    `robot_a` at `T_a_b` [x, y, yaw], with its 3x3 `covariance` (frame b). `id` is the
    caller's handle, unique within one call of `max_consistent_set`."""

    id: int
    robot_a: str
    index_a: int
    robot_b: str
    index_b: int
    T_a_b: np.ndarray
    covariance: np.ndarray


def _adjoint(T: FloatArray) -> FloatArray:
    """SE(2) adjoints (..., 3, 3) of T = [x, y, yaw] (..., 3): Exp(Ad_T xi) = T Exp(xi) T^-1."""
    T = np.asarray(T, dtype=np.float64)
    c, s = np.cos(T[..., 2]), np.sin(T[..., 2])
    A = np.zeros(T.shape[:-1] + (3, 3))
    A[..., 0, 0], A[..., 0, 1], A[..., 0, 2] = c, -s, T[..., 1]
    A[..., 1, 0], A[..., 1, 1], A[..., 1, 2] = s, c, -T[..., 0]
    A[..., 2, 2] = 1.0
    return A


def _log(T: FloatArray) -> FloatArray:
    """SE(2) logarithms [v_x, v_y, omega] (..., 3) of T (..., 3) (gtsam's Pose2::Logmap)."""
    T = np.asarray(T, dtype=np.float64)
    w = wrap_angle(T[..., 2])
    # half * cot(half) as half / tan(half): no cancellation for small angles (the form
    # with 1 - cos(w) lost its digits there, and divided by zero below ~1e-8 rad: an
    # infinite chi2 that rejected a perfect match)
    small = np.abs(w) < 1e-10
    half = 0.5 * w
    hs = np.where(small, 1.0, half)
    a = np.where(small, 1.0, hs / np.tan(hs))
    x, y = T[..., 0], T[..., 1]
    return np.stack([a * x + half * y, -half * x + a * y, w], axis=-1)


def _sandwich(J: FloatArray, C: FloatArray) -> FloatArray:
    """J C J^T over stacks of 3x3 matrices."""
    return np.einsum("...ij,...jk,...lk->...il", J, C, J)


def _cycle_d2(
    T1: FloatArray,
    C1: FloatArray,
    T2: FloatArray,
    C2: FloatArray,
    Ob: FloatArray,
    Cob: FloatArray,
    Oa: FloatArray,
    Coa: FloatArray,
) -> FloatArray:
    """Mahalanobis^2 (P,) of the cycles T1 * Ob * T2^-1 * Oa (stacks of P poses and
    3x3 covariances). A right perturbation xi of the k-th factor moves the cycle by
    Ad_{(factors after k)^-1} xi, and xi(T^-1) = -Ad_T xi(T)."""
    after2 = se2_compose(se2_inverse(T2), Oa)
    after1 = se2_compose(Ob, after2)
    e = _log(se2_compose(T1, after1))
    J1 = _adjoint(se2_inverse(after1))
    J2 = _adjoint(se2_inverse(after2))
    J3 = -_adjoint(se2_inverse(Oa)) @ _adjoint(T2)
    cov = _sandwich(J1, C1) + _sandwich(J2, Cob) + _sandwich(J3, C2) + Coa
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    try:
        sol = np.linalg.solve(cov, e[..., None])[..., 0]
    except np.linalg.LinAlgError as exc:
        raise CollabSlamError("singular covariance of a consistency cycle") from exc
    return np.einsum("...i,...i->...", e, sol)


def _reversed(m: LoopMeasurement) -> LoopMeasurement:
    """The same measurement seen from the other end: T_b_a, covariance in frame a."""
    J = -_adjoint(m.T_a_b)
    cov = J @ np.asarray(m.covariance, dtype=np.float64) @ J.T
    return LoopMeasurement(
        m.id, m.robot_b, m.index_b, m.robot_a, m.index_a, se2_inverse(m.T_a_b), cov
    )


def _odometry(odometry: Odometry, robot: str, i: int, j: int) -> tuple[FloatArray, FloatArray]:
    if i == j:
        return np.zeros(3), np.zeros((3, 3))
    T, cov = odometry(robot, i, j)
    return np.asarray(T, dtype=np.float64).reshape(3), np.asarray(cov, dtype=np.float64)


def _aligned(m1: LoopMeasurement, m2: LoopMeasurement) -> LoopMeasurement:
    """m2 oriented like m1 (robot_a with robot_a); for two loops of one robot, the
    orientation whose cycle runs over the shorter stretches of odometry."""
    if m1.robot_a != m1.robot_b:
        if (m2.robot_a, m2.robot_b) == (m1.robot_a, m1.robot_b):
            return m2
        if (m2.robot_a, m2.robot_b) == (m1.robot_b, m1.robot_a):
            return _reversed(m2)
        raise CollabSlamError(
            f"measurements {m1.id} and {m2.id} do not connect the same pair of robots"
        )
    if not m2.robot_a == m2.robot_b == m1.robot_a:
        raise CollabSlamError(f"measurements {m1.id} and {m2.id} are not loops of one robot")
    straight = abs(m1.index_a - m2.index_a) + abs(m1.index_b - m2.index_b)
    crossed = abs(m1.index_a - m2.index_b) + abs(m1.index_b - m2.index_a)
    return _reversed(m2) if crossed < straight else m2


def _pairs_d2(
    pairs: list[tuple[LoopMeasurement, LoopMeasurement]], odometry: Odometry
) -> FloatArray:
    """Mahalanobis^2 of the cycle of every pair (m1, m2), m2 aligned to m1 here."""
    n = len(pairs)
    T1, T2, Ob, Oa = (np.empty((n, 3)) for _ in range(4))
    C1, C2, Cob, Coa = (np.empty((n, 3, 3)) for _ in range(4))
    for k, (m1, m2) in enumerate(pairs):
        m2 = _aligned(m1, m2)
        T1[k], C1[k] = m1.T_a_b, m1.covariance
        T2[k], C2[k] = m2.T_a_b, m2.covariance
        Ob[k], Cob[k] = _odometry(odometry, m1.robot_b, m1.index_b, m2.index_b)
        Oa[k], Coa[k] = _odometry(odometry, m1.robot_a, m2.index_a, m1.index_a)
    return _cycle_d2(T1, C1, T2, C2, Ob, Cob, Oa, Coa)


def cycle_mahalanobis2(m1: LoopMeasurement, m2: LoopMeasurement, odometry: Odometry) -> float:
    """Squared Mahalanobis distance of the cycle m1 * odo_b * m2^-1 * odo_a from identity
    (module doc); `odometry(robot, i, j)` gives T_i_j along the robot's chain and its
    covariance (frame j). Raises CollabSlamError if m1, m2 link different robots."""
    return float(_pairs_d2([(m1, m2)], odometry)[0])


def pairwise_consistent(
    m1: LoopMeasurement,
    m2: LoopMeasurement,
    odometry: Odometry,
    threshold_chi2: float = DEFAULT_THRESHOLD_CHI2,
) -> bool:
    """Whether m1 and m2 close a cycle near identity: Mahalanobis^2 <= threshold_chi2
    (chi-square, 3 dof). See `cycle_mahalanobis2`."""
    return cycle_mahalanobis2(m1, m2, odometry) <= threshold_chi2


def _group_key(m: LoopMeasurement) -> tuple[str, str]:
    return (min(m.robot_a, m.robot_b), max(m.robot_a, m.robot_b))


def max_consistent_set(
    measurements: list[LoopMeasurement],
    odometry: Odometry,
    threshold_chi2: float = DEFAULT_THRESHOLD_CHI2,
    max_exact: int = 40,
) -> set[int]:
    """Ids of the largest pairwise-consistent subset of each group of measurements
    (one group per unordered pair of robots, intra-robot loops a group per robot).

    A maximum clique of the consistency graph: exact for groups of up to `max_exact`
    measurements, a greedy heuristic above. Ties between cliques of equal size go to
    the one with the smallest summed Mahalanobis^2. A group of one is trivially
    consistent. Calls `odometry` O(n^2) times per group of n.
    """
    ids = [m.id for m in measurements]
    if len(set(ids)) != len(ids):
        raise CollabSlamError("measurement ids must be unique")
    groups: dict[tuple[str, str], list[LoopMeasurement]] = defaultdict(list)
    for m in measurements:
        key = _group_key(m)
        # one orientation per robot pair (robot_a = the first of the key)
        groups[key].append(m if m.robot_a == key[0] else _reversed(m))
    accepted: set[int] = set()
    for key, group in groups.items():
        n = len(group)
        d2 = np.zeros((n, n))
        iu, ju = np.triu_indices(n, 1)
        if len(iu):
            d2[iu, ju] = _pairs_d2(
                [(group[i], group[j]) for i, j in zip(iu, ju, strict=True)], odometry
            )
            d2[ju, iu] = d2[iu, ju]
        adj = d2 <= threshold_chi2
        np.fill_diagonal(adj, False)
        if n <= max_exact:
            clique = _maximum_clique(adj, d2)
        else:
            clique = _greedy_clique(adj, d2)
        logger.debug("PCM %s: %d of %d consistent", key, len(clique), n)
        accepted.update(group[i].id for i in clique)
    return accepted


def _clique_cost(clique: list[int], d2: FloatArray) -> float:
    idx = np.asarray(clique, dtype=np.int64)
    return float(d2[np.ix_(idx, idx)].sum())


def _maximum_clique(
    adj: NDArray[np.bool_], d2: FloatArray, max_steps: int = MAX_CLIQUE_STEPS
) -> list[int]:
    """Every maximum clique by branch and bound on bitsets (Carraghan-Pardalos with a
    greedy-colouring bound, Tomita); the one with the smallest summed d2 wins. Their
    number can grow exponentially (a repetitive corridor: matches at one place that
    contradict each other, places far apart that agree with anything; 31 s for one
    match of 40 on the main thread): past `max_steps` expansions, PCM's heuristic."""
    n = len(adj)
    if n == 0:
        return []
    nbr = [sum(1 << int(j) for j in np.flatnonzero(adj[i])) for i in range(n)]
    best: list[list[int]] = [[0]]
    budget = [max_steps]

    def colour_bound(cand: int) -> list[tuple[int, int]]:
        """Vertices of `cand` with their greedy colour number (ascending)."""
        order: list[tuple[int, int]] = []
        colour = 0
        rest = cand
        while rest:
            colour += 1
            avail = rest
            while avail:
                v = (avail & -avail).bit_length() - 1
                avail &= ~(1 << v) & ~nbr[v]
                rest &= ~(1 << v)
                order.append((v, colour))
        return order

    def expand(clique: list[int], cand: int) -> None:
        budget[0] -= 1
        if budget[0] < 0:
            raise _OutOfBudget
        order = colour_bound(cand)
        for v, colour in reversed(order):
            if len(clique) + colour < len(best[0]):
                return
            new = clique + [v]
            sub = cand & nbr[v]
            if sub:
                expand(new, sub)
            elif len(new) > len(best[0]):
                best[:] = [new]
            elif len(new) == len(best[0]):
                best.append(new)
            cand &= ~(1 << v)

    try:
        expand([], (1 << n) - 1)
    except _OutOfBudget:
        return _greedy_clique(adj, d2)
    return sorted(min(best, key=lambda c: _clique_cost(c, d2)))


def _greedy_clique(adj: NDArray[np.bool_], d2: FloatArray) -> list[int]:
    """PCM's heuristic (Pattabiraman et al. 2015): from every vertex, grow a clique by
    adding the candidate of highest degree; keep the largest (then cheapest)."""
    n = len(adj)
    degree = adj.sum(axis=1)
    best: list[int] = []
    for start in np.argsort(-degree, kind="stable"):
        if degree[start] + 1 < len(best):
            break
        clique = _grow_clique(adj, int(start), degree)
        if len(clique) > len(best) or (
            len(clique) == len(best) and _clique_cost(clique, d2) < _clique_cost(best, d2)
        ):
            best = clique
    return sorted(best) if n else []


class IncrementalPcm:
    """PCM for one group (one robot pair, or one robot's loops) as measurements arrive.

    Each new measurement is tested against the group's previous ones once, when it
    arrives (O(n) odometry queries, not O(n^2) per arrival); the consistency matrix is
    kept. The accepted set is then updated: exactly (maximum clique) while the group
    has at most `max_exact` measurements; above that, the new measurement joins the
    current clique when consistent with all of it, and otherwise the best clique
    grown greedily from it replaces the current one only if it is larger. This is the
    incremental use of PCM in multi-robot systems (DOOR-SLAM, Kimera-Multi).

    Sliding window: only the `window` most recent measurements of the group are kept
    (with their consistency matrix, window x window float64, ~80 kB at 100); a new one
    is tested against them only, so memory and each arrival's cost stay bounded
    however many loops a pair closes (the whole matrix grew with the square of the
    matches). A measurement leaving the window keeps its last state for good: accepted
    ones stay in the graph (the caller's factors), rejected ones stay out.
    `settled` counts the measurements that left.
    """

    def __init__(
        self, threshold_chi2: float = DEFAULT_THRESHOLD_CHI2, max_exact: int = 40,
        window: int = 100,
    ) -> None:  # fmt: skip
        if window < 1:
            raise CollabSlamError(f"PCM window must be >= 1, got {window}")
        self.threshold_chi2 = float(threshold_chi2)
        self.max_exact = int(max_exact)
        self.window = int(window)
        self.measurements: list[LoopMeasurement] = []  # the window, oldest first
        self._d2 = np.zeros((0, 0))
        self._clique: list[int] = []  # indices into self.measurements
        self.settled = 0  # measurements that left the window

    def add(
        self, m: LoopMeasurement, odometry: Odometry, batch_odometry: BatchOdometry | None = None
    ) -> set[int]:
        """Add `m` (oriented like the group's first measurement or not); returns the
        ids of the accepted (pairwise-consistent) measurements in the window. With
        `batch_odometry` the tests against the window run vectorized."""
        if self.measurements:
            first = self.measurements[0]
            if _group_key(m) != _group_key(first):
                raise CollabSlamError(f"measurement {m.id} belongs to another group")
            if m.robot_a != first.robot_a:
                m = _reversed(m)
        if len(self.measurements) >= self.window:  # the oldest leaves, its state final
            del self.measurements[0]
            self._d2 = self._d2[1:, 1:]
            self._clique = [i - 1 for i in self._clique if i > 0]
            self.settled += 1
        n = len(self.measurements)
        if n == 0:
            row = np.zeros(0)
        elif batch_odometry is not None:
            row = _window_d2(self.measurements, m, batch_odometry)
        else:
            row = _pairs_d2([(old, m) for old in self.measurements], odometry)
        d2 = np.zeros((n + 1, n + 1))
        d2[:n, :n] = self._d2
        d2[n, :n] = d2[:n, n] = row
        self._d2 = d2
        self.measurements.append(m)
        adj = d2 <= self.threshold_chi2
        np.fill_diagonal(adj, False)
        if n + 1 <= self.max_exact:
            self._clique = _maximum_clique(adj, d2)
        elif all(adj[n, i] for i in self._clique):
            self._clique = sorted([*self._clique, n])
        else:
            grown = _grow_clique(adj, n)
            if len(grown) > len(self._clique):
                self._clique = grown
        return {self.measurements[i].id for i in self._clique}

    @property
    def accepted(self) -> set[int]:
        """Ids of the accepted measurements in the window."""
        return {self.measurements[i].id for i in self._clique}

    @property
    def ids(self) -> set[int]:
        """Ids of the measurements in the window."""
        return {m.id for m in self.measurements}


def _window_d2(olds: list[LoopMeasurement], m: LoopMeasurement, odo: BatchOdometry) -> FloatArray:
    """`_pairs_d2` of (old, m) for every old measurement of m's group, vectorized."""
    n = len(olds)
    ia = np.array([o.index_a for o in olds])
    ib = np.array([o.index_b for o in olds])
    T1 = np.array([o.T_a_b for o in olds])
    C1 = np.array([o.covariance for o in olds])
    T2 = np.broadcast_to(np.asarray(m.T_a_b, dtype=np.float64), (n, 3)).copy()
    C2 = np.broadcast_to(np.asarray(m.covariance, dtype=np.float64), (n, 3, 3)).copy()
    i2 = np.full(n, m.index_a)
    j2 = np.full(n, m.index_b)
    if m.robot_a == m.robot_b:  # loops of one robot: the shorter way round (see _aligned)
        straight = np.abs(ia - m.index_a) + np.abs(ib - m.index_b)
        crossed = np.abs(ia - m.index_b) + np.abs(ib - m.index_a)
        flip = crossed < straight
        if flip.any():
            r = _reversed(m)
            T2[flip], C2[flip] = r.T_a_b, r.covariance
            i2[flip], j2[flip] = m.index_b, m.index_a
    Ob, Cob = odo(m.robot_b, ib, j2)
    Oa, Coa = odo(m.robot_a, i2, ia)
    return _cycle_d2(T1, C1, T2, C2, Ob, Cob, Oa, Coa)


def _grow_clique(
    adj: NDArray[np.bool_], start: int, degree: NDArray[np.int64] | None = None
) -> list[int]:
    """A clique containing `start`, grown greedily by highest degree among candidates."""
    if degree is None:
        degree = adj.sum(axis=1)
    clique = [start]
    cand = adj[start].copy()
    while cand.any():
        v = int(np.flatnonzero(cand)[np.argmax(degree[cand])])
        clique.append(v)
        cand &= adj[v]
        cand[v] = False
    return sorted(clique)
