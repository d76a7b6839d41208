"""Multi-robot 2-D pose graph solved incrementally with gtsam iSAM2.

The only class that sees gtsam types for the 2-D back end; callers use robot ids,
node indices and numpy arrays.

Conventions:
- Every pose is ``T_map_node = [x, y, yaw]`` (m, m, rad) in the base station's map
  frame; a relative pose ``T_a_b`` is node b expressed in node a's frame.
- Covariances are 3x3 over ``[x, y, yaw]`` in the local (body) frame of the node
  (gtsam's Pose2 tangent space), in m^2 / rad^2.
- Keys: robot k (registration order) is ``ROBOT_KEY_ALPHABET[k]``, node i is
  ``gtsam.symbol(char, i)``; 26 lower-case letters, upper case left for the rest.

Ordering: with ``heads_last`` every chain's newest node is constrained to the end of
iSAM2's elimination order (the root of the Bayes tree), so when robots take turns the
next node of any robot re-eliminates the root clique only; the solution is the same.

Gauge (how disjoint chains stay well-posed): the graph is split into connected
components of robots (linked by inter-robot constraints). A component containing a
robot with a known start is held by those start priors alone. A floating component
gets exactly one *gauge prior* (``prior_sigmas``) on the first node of its
earliest-registered robot, at that node's current estimate: it fixes the
component's own frame and carries no information. When a constraint joins
components, surplus gauge priors are removed in the same update (so the merge is
not biased) and extra iterations let the moved chain settle; if removing a
constraint splits a component again, a gauge prior is re-added.

GPS (seed 000 §III): ``add_gps_fix`` queues a fix until the node after it exists
(nodes need stamps), then adds a ``gps_factor`` on the two nodes around it, in
batches (``gps_batch_period_s``). A GPS chain starts with a loose prior
(``add_robot(..., start_sigmas)``) and counts as anchored; use QR then.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from basestation.gps_factor import GpsWeighting, gps_noise, make_gps_factor
from basestation.gps_fixes import GpsFix, GpsFixQueue
from common.config import BaseStationConfig
from common.errors import CollabSlamError
from common.geometry import se2_compose, wrap_angle

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
ROBOT_KEY_ALPHABET = "abcdefghijklmnopqrstuvwxyz"
ROBUST_KERNELS = ("huber", "cauchy")
FactorKind = Literal["odometry", "start", "gauge", "constraint", "gps"]  # start: known-start prior


@dataclass(frozen=True)
class UpdateStats:
    """What one ``PoseGraph.update`` did."""

    wall_ms: float  # whole call: iSAM2 iterations plus estimate extraction
    solve_ms: float  # iSAM2 update() calls only
    iterations: int  # iSAM2 update() calls (1 + extra relinearization iterations)
    num_new_factors: int
    num_removed_factors: int
    num_new_nodes: int
    # robots whose already-estimated nodes moved > epsilon; None if track_changes is off
    changed_robots: frozenset[str] | None
    robots_with_new_nodes: frozenset[str]
    batch_reordered: bool = False  # iSAM2 re-ordered the whole tree (adaptive reorder)


class _GtsamProblem(NamedTuple):
    """Package-internal snapshot for batch_solver: active committed factors and values."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values


@dataclass
class _Chain:
    char: str
    T_map_first: FloatArray | None  # known start, or None if the chain floats
    num_committed: int = 0  # nodes already inside iSAM2
    pending: list[FloatArray] = field(default_factory=list)  # initial guesses not yet inside
    gauge_factor: int | None = None  # factor id of this chain's gauge prior, if any
    start_sigmas: FloatArray | None = None  # loose start prior (GPS: virtual ENU origin)
    stamps: list[float] | None = field(default_factory=list)  # node stamps; None: unstamped

    @property
    def size(self) -> int:
        return self.num_committed + len(self.pending)


@dataclass
class _Factor:
    factor: gtsam.NonlinearFactor
    kind: FactorKind
    robots: tuple[str, str] | None = None  # the two robots of an inter-robot constraint
    isam_index: int | None = None  # slot inside iSAM2 once committed


def _vec3(value: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise CollabSlamError(f"{name} must be a finite [x, y, yaw] array, got {value!r}")
    return arr


def _gaussian(covariance: ArrayLike) -> gtsam.noiseModel.Gaussian:
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        raise CollabSlamError(f"covariance must be a finite 3x3 matrix, got shape {cov.shape}")
    if np.abs(cov - cov.T).max() > 1e-9 * np.abs(cov).max():
        raise CollabSlamError("covariance must be symmetric")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError as exc:
        raise CollabSlamError("covariance must be positive definite") from exc
    return gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))


def _pose2(T: FloatArray) -> gtsam.Pose2:
    x, y, yaw = T.tolist()  # python floats: pybind picks the overload at once
    return gtsam.Pose2(x, y, yaw)


class PoseGraph:
    """Pose chains of several robots plus constraints between any two nodes, on iSAM2.

    Not thread-safe: build, update and query it from one thread. Changes (nodes,
    constraints, removals) are pending until ``update``; queries of pending nodes
    return their initial guess.
    """

    def __init__(
        self,
        relinearize_threshold: float = 0.1,
        relinearize_skip: int = 1,
        prior_sigmas: tuple[float, float, float] = (0.01, 0.01, 0.001),  # m, m, rad
        change_epsilon: float = 1e-4,  # m or rad: a robot "changed" beyond this
        settle_iterations: int = 10,  # max extra iterations after components merge
        track_changes: bool = True,  # False: no changed_robots, the O(n) estimate is lazy
        gps_weighting: GpsWeighting | None = None,  # None: GpsWeighting() defaults
        max_pending_gps_fixes: int = 1000,  # per robot, fixes waiting for their nodes
        gps_batch_period_s: float = 0.0,  # s of node time between GPS releases (0: at once)
        wildfire_threshold: float = 0.001,  # rad or m: back-substitution stops below this
        # QR with loose start priors (GPS): gtsam's Cholesky calls a 100 m start prior next
        # to 1 mm odometry "indeterminate" (information ratio 1e10).
        factorization: str = "CHOLESKY",  # or "QR"
        cache_linearized_factors: bool = True,
        adaptive_reorder_threshold: float = 0.0,  # fill-in growth factor; 0: off
        heads_last: bool = False,  # True: each chain's newest node is ordered last (root)
    ) -> None:
        params = gtsam.ISAM2Params()
        if factorization not in ("CHOLESKY", "QR"):
            raise CollabSlamError(f"factorization must be CHOLESKY or QR, got {factorization!r}")
        params.setFactorization(factorization)
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = relinearize_skip
        gauss_newton = gtsam.ISAM2GaussNewtonParams()
        gauss_newton.setWildfireThreshold(wildfire_threshold)
        params.setOptimizationParams(gauss_newton)
        params.cacheLinearizedFactors = cache_linearized_factors
        params.findUnusedFactorSlots = False  # factor slots stay stable for removal
        if adaptive_reorder_threshold > 0:
            params.enableAdaptiveReorder = True
            params.adaptiveReorderThreshold = adaptive_reorder_threshold
        self._isam = gtsam.ISAM2(params)
        self._prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(prior_sigmas, float))
        self._change_epsilon = change_epsilon
        self._settle_iterations = settle_iterations
        self._track_changes = track_changes
        self._heads_last = heads_last
        self._chains: dict[str, _Chain] = {}  # registration order = key-character order
        self._factors: dict[int, _Factor] = {}  # active factors (committed or pending)
        self._pending_ids: list[int] = []
        self._pending_removals: list[int] = []  # iSAM2 slots
        self._next_id = 0
        self._pair_count: Counter[tuple[str, str]] = Counter()
        self._topology_dirty = False
        self._topology_version = 0  # bumped on every change of the robots' grouping
        self._components_cache: tuple[int, list[list[str]]] = (-1, [])
        self._component_of: dict[str, int] = {}  # robot -> component label at last update
        self._guesses = gtsam.Values()  # every initial guess handed to iSAM2 (for batch)
        self._estimate = np.zeros((0, 3))  # committed poses, rows in key order
        self._estimate_valid = True  # False: recompute on the next full-estimate query
        self._gps_weighting = gps_weighting or GpsWeighting()
        self._gps = GpsFixQueue(max_pending_gps_fixes, gps_batch_period_s)
        self.num_gps_factors = 0

    @classmethod
    def from_config(cls, b: BaseStationConfig, track_changes: bool | None = None) -> PoseGraph:
        """The base station's pose graph (``track_changes`` None: ``b.track_changes``)."""
        return cls(
            relinearize_threshold=b.relinearize_threshold,
            relinearize_skip=b.relinearize_skip,
            prior_sigmas=(b.prior_sigma_xy_m, b.prior_sigma_xy_m, b.prior_sigma_yaw_rad),
            track_changes=b.track_changes if track_changes is None else track_changes,
            wildfire_threshold=b.wildfire_threshold,
            cache_linearized_factors=b.cache_linearized_factors,
            adaptive_reorder_threshold=b.adaptive_reorder_threshold,
            heads_last=b.heads_last,
            gps_weighting=GpsWeighting.from_config(b.gps),
            max_pending_gps_fixes=b.gps.max_pending_fixes,
            gps_batch_period_s=b.gps.batch_period_s,
            # QR with GPS's loose start priors (Cholesky calls them indeterminate)
            factorization="QR" if b.gps.enabled else b.isam2_factorization,
        )

    # ----- building the graph -------------------------------------------------------
    def add_robot(
        self,
        robot_id: str,
        T_map_first: ArrayLike | None,
        start_sigmas: ArrayLike | None = None,
    ) -> None:
        """Register a chain; ``T_map_first`` is its known start, or None if it floats.

        ``start_sigmas`` ([m, m, rad]) makes the start prior loose instead of the firm
        ``prior_sigmas``: with GPS, ``T_map_first`` is the first fix with the autopilot's
        heading (seed 000 §III-C, a virtual ENU-origin trajectory) and the fixes anchor
        the chain. Such a chain counts as anchored (it lives in ``map``).
        """
        if robot_id in self._chains:
            raise CollabSlamError(f"robot {robot_id!r} is already registered")
        if len(self._chains) >= len(ROBOT_KEY_ALPHABET):
            raise CollabSlamError(f"at most {len(ROBOT_KEY_ALPHABET)} robots are supported")
        start = None if T_map_first is None else _vec3(T_map_first, "T_map_first")
        chain = _Chain(ROBOT_KEY_ALPHABET[len(self._chains)], start)
        if start_sigmas is not None:
            if start is None:
                raise CollabSlamError("start_sigmas needs a T_map_first")
            chain.start_sigmas = _vec3(start_sigmas, "start_sigmas")
            if np.any(chain.start_sigmas <= 0):
                raise CollabSlamError(f"start_sigmas must be > 0, got {start_sigmas!r}")
        self._chains[robot_id] = chain

    def add_node(
        self,
        robot_id: str,
        index: int,
        delta: ArrayLike | None,
        covariance: ArrayLike | None,
        initial_guess: ArrayLike | None = None,
        stamp: float | None = None,
    ) -> None:
        """Append node ``index`` to a chain; ``delta`` is T_prev_node (None for index 0).

        The initial guess defaults to the previous node's estimate composed with
        ``delta`` (index 0: the known start, or the origin of a floating chain).
        ``stamp`` (s, increasing along the chain) is needed for GPS fixes; a node
        added without one turns GPS off for its chain.
        """
        chain = self._chain(robot_id)
        if index != chain.size:
            raise CollabSlamError(f"robot {robot_id!r}: expected node {chain.size}, got {index}")
        self._check_stamp(robot_id, chain, stamp)
        guess = None if initial_guess is None else _vec3(initial_guess, "initial_guess")
        key = gtsam.symbol(chain.char, index)
        if index == 0:
            if delta is not None:
                raise CollabSlamError("the first node of a chain takes no delta")
            start = chain.T_map_first
            if guess is None:
                guess = np.zeros(3) if start is None else start
            if start is not None:
                noise = self._prior_noise
                if chain.start_sigmas is not None:
                    noise = gtsam.noiseModel.Diagonal.Sigmas(chain.start_sigmas)
                prior = gtsam.PriorFactorPose2(key, _pose2(start), noise)
                self._add_factor(prior, "start")
            self._topology_dirty = True
            self._topology_version += 1
        else:
            if delta is None or covariance is None:
                raise CollabSlamError("nodes after the first need delta and covariance")
            d = _vec3(delta, "delta")
            noise = _gaussian(covariance)
            if guess is None:
                guess = se2_compose(self.pose(robot_id, index - 1), d)
            prev = gtsam.symbol(chain.char, index - 1)
            self._add_factor(gtsam.BetweenFactorPose2(prev, key, _pose2(d), noise), "odometry")
        chain.pending.append(guess)
        if stamp is None:
            chain.stamps = None
        elif chain.stamps is not None:
            chain.stamps.append(float(stamp))
        self._attach_gps(robot_id)

    def add_gps_fix(
        self, robot_id: str, stamp: float, enu_xy: ArrayLike, sigmas_enu: ArrayLike
    ) -> int:
        """Queue a GPS fix ([east, north] m in ``map`` = ENU, reported [sigma_e, sigma_n,
        sigma_u] m, eq. 4) taken at ``stamp``; returns how many GPS factors this added
        (0 while the fix waits for the node after it, see ``basestation.gps_fixes``)."""
        chain = self._chain(robot_id)
        if chain.stamps is None:
            raise CollabSlamError(f"robot {robot_id!r} has unstamped nodes: no GPS possible")
        xy = np.asarray(enu_xy, dtype=np.float64).reshape(-1)
        sig = np.asarray(sigmas_enu, dtype=np.float64).reshape(-1)
        if xy.shape != (2,) or sig.shape != (3,) or not np.all(np.isfinite([*xy, *sig, stamp])):
            raise CollabSlamError("a GPS fix needs a finite stamp, [east, north] and 3 sigmas")
        if np.any(sig <= 0):
            raise CollabSlamError(f"GPS sigmas must be > 0, got {sigmas_enu!r}")
        self._gps.add(robot_id, GpsFix(float(stamp), xy, sig))
        return self._attach_gps(robot_id)

    def gps_stats(self) -> dict[str, int]:
        """GPS factors added, fixes waiting and fixes dropped (too old, queue overflow)."""
        return {
            "gps_factors": self.num_gps_factors,
            "gps_pending": sum(self._gps.pending(r) for r in self._chains),
            "gps_dropped_before_start": self._gps.dropped_before_start,
            "gps_dropped_overflow": self._gps.dropped_overflow,
        }

    def _check_stamp(self, robot_id: str, chain: _Chain, stamp: float | None) -> None:
        if stamp is None:
            if chain.stamps is not None and self._gps.pending(robot_id):
                raise CollabSlamError(f"robot {robot_id!r}: GPS fixes wait, nodes need stamps")
        elif chain.stamps is not None:
            if not np.isfinite(stamp) or (chain.stamps and stamp <= chain.stamps[-1]):
                raise CollabSlamError(f"robot {robot_id!r}: node stamps must increase, got {stamp}")

    def flush_gps(self) -> int:
        """Turn every bracketed fix into a factor now, batch due or not (e.g. at shutdown)."""
        return sum(self._attach_gps(robot_id, flush=True) for robot_id in self._chains)

    def _attach_gps(self, robot_id: str, flush: bool = False) -> int:
        chain = self._chains[robot_id]
        if chain.stamps is None:
            return 0
        w = self._gps_weighting
        added = 0
        for b in self._gps.ready(robot_id, chain.stamps, flush):
            factor = make_gps_factor(
                gtsam.symbol(chain.char, b.i),
                gtsam.symbol(chain.char, b.j),
                b.beta,
                b.fix.enu_xy,
                gps_noise(b.fix.sigmas_enu, w),
                w.lever_arm,
            )
            self._add_factor(factor, "gps")
            added += 1
        self.num_gps_factors += added
        return added

    def add_constraint(
        self,
        key_a: tuple[str, int],
        key_b: tuple[str, int],
        T_a_b: ArrayLike,
        covariance: ArrayLike,
        robust: str | None = "huber",
        robust_k: float = 1.345,
    ) -> int:
        """Add a loop closure / inter-robot constraint; returns its id for removal.

        ``robust`` is "huber", "cauchy" or None; ``robust_k`` is the kernel width in
        units of the whitened (Mahalanobis) residual.
        """
        ka, kb = self._key(*key_a), self._key(*key_b)
        if ka == kb:
            raise CollabSlamError(f"constraint from node {key_a} to itself")
        noise = _gaussian(covariance)
        if robust is not None:
            if robust not in ROBUST_KERNELS or not robust_k > 0:
                raise CollabSlamError(f"robust must be one of {ROBUST_KERNELS} with k > 0")
            kernel_cls = getattr(gtsam.noiseModel.mEstimator, robust.capitalize())
            noise = gtsam.noiseModel.Robust.Create(kernel_cls.Create(robust_k), noise)
        factor = gtsam.BetweenFactorPose2(ka, kb, _pose2(_vec3(T_a_b, "T_a_b")), noise)
        robots = None
        if key_a[0] != key_b[0]:
            robots = (min(key_a[0], key_b[0]), max(key_a[0], key_b[0]))
            self._pair_count[robots] += 1
            self._topology_dirty = True
            self._topology_version += 1
        return self._add_factor(factor, "constraint", robots)

    def remove_constraint(self, factor_id: int) -> None:
        """Remove a constraint returned by ``add_constraint`` at the next update."""
        record = self._factors.get(factor_id)
        if record is None or record.kind != "constraint":
            raise CollabSlamError(f"no active constraint with id {factor_id}")
        if record.robots is not None:
            self._pair_count[record.robots] -= 1
            self._topology_dirty = True
            self._topology_version += 1
        self._drop_factor(factor_id)

    # ----- solving ------------------------------------------------------------------
    def update(self, extra_iterations: int = 0) -> UpdateStats:
        """Run iSAM2 on everything pending (no-op if nothing is pending and no extras).

        ``extra_iterations`` adds empty iSAM2 updates (relinearization steps); they stop
        early once no variable is relinearized.
        """
        t_start = time.perf_counter()
        merged = self._reconcile_gauges() if self._topology_dirty else False
        new_ids = [fid for fid in self._pending_ids if fid in self._factors]
        removals = self._pending_removals
        if not new_ids and not removals and extra_iterations == 0:
            return UpdateStats(0.0, 0.0, 0, 0, 0, 0, frozenset(), frozenset())
        graph = gtsam.NonlinearFactorGraph()
        for fid in new_ids:
            graph.add(self._factors[fid].factor)
        values = gtsam.Values()
        new_nodes: dict[str, int] = {}
        for robot_id, chain in self._chains.items():
            if chain.pending:
                for i, guess in enumerate(chain.pending, start=chain.num_committed):
                    # the keyword skips pybind's failed array conversions (~3x faster)
                    values.insert(gtsam.symbol(chain.char, i), pose2=_pose2(guess))
                new_nodes[robot_id] = len(chain.pending)

        heads = None  # None: iSAM2's default, the keys of the new factors go last
        if self._heads_last:
            heads = gtsam.KeyGroupMap()
            for chain in self._chains.values():
                if chain.size:
                    heads.insert2(gtsam.symbol(chain.char, chain.size - 1), 1)

        t_solve = time.perf_counter()
        try:
            result = self._isam.update(graph, values, removals, constrainedKeys=heads)
            for fid, slot in zip(new_ids, result.getNewFactorsIndices(), strict=True):
                self._factors[fid].isam_index = slot
            reordered = result.getBatchReorderTriggered()
            iterations = 1
            # a merge or a GPS batch moves whole chains: settle them within this update
            gps = any(self._factors[fid].kind == "gps" for fid in new_ids)
            settle = self._settle_iterations if merged or gps else 0
            for _ in range(max(extra_iterations, settle)):
                iterations += 1
                extra = self._isam.update(  # force: even between relinearization skips
                    constrainedKeys=heads, force_relinearize=True
                )
                reordered = reordered or extra.getBatchReorderTriggered()
                if extra.getVariablesRelinearized() == 0:
                    break
            if settle:  # back-substitute now (lazy in gtsam: it would land in the next update)
                self._isam.getDelta()
        except RuntimeError as exc:  # e.g. gtsam's IndeterminantLinearSystemException
            raise CollabSlamError(
                f"iSAM2 update failed, the pose graph is unusable: {exc}"
            ) from exc
        solve_ms = (time.perf_counter() - t_solve) * 1e3

        self._guesses.insert(values)
        self._pending_ids, self._pending_removals = [], []
        old_estimate, old_counts = self._estimate, [c.num_committed for c in self._chains.values()]
        for chain in self._chains.values():
            chain.num_committed, chain.pending = chain.size, []
        self._estimate_valid = False
        changed = None
        if self._track_changes:  # then the previous estimate is always valid
            changed = self._changed_robots(old_estimate, self._full_estimate(), old_counts)
        stats = UpdateStats(
            wall_ms=(time.perf_counter() - t_start) * 1e3,
            solve_ms=solve_ms,
            iterations=iterations,
            num_new_factors=len(new_ids),
            num_removed_factors=len(removals),
            num_new_nodes=sum(new_nodes.values()),
            changed_robots=changed,
            robots_with_new_nodes=frozenset(new_nodes),
            batch_reordered=reordered,
        )
        logger.debug(
            "iSAM2 update: %d factors, %d removed, %d nodes, %d iterations, %.2f ms (solve %.2f)",
            stats.num_new_factors,
            stats.num_removed_factors,
            stats.num_new_nodes,
            iterations,
            stats.wall_ms,
            solve_ms,
        )
        return stats

    # ----- queries ------------------------------------------------------------------
    def pose(self, robot_id: str, index: int) -> FloatArray:
        """T_map_node of one node (its initial guess while it waits for ``update``)."""
        chain = self._chain(robot_id)
        if not 0 <= index < chain.size:
            raise CollabSlamError(f"robot {robot_id!r} has no node {index}")
        if index >= chain.num_committed:
            return chain.pending[index - chain.num_committed].copy()
        if self._estimate_valid:
            return self._estimate[self._offset(robot_id) + index].copy()
        p = self._isam.calculateEstimatePose2(gtsam.symbol(chain.char, index))  # O(1)-ish
        return np.array([p.x(), p.y(), p.theta()])

    def poses(self, robot_id: str) -> FloatArray:
        """(N, 3) poses of a chain in index order (pending nodes: their initial guess)."""
        chain = self._chain(robot_id)
        offset = self._offset(robot_id)
        committed = self._full_estimate()[offset : offset + chain.num_committed]
        return np.vstack([committed, *chain.pending]) if chain.pending else committed.copy()

    def num_nodes(self, robot_id: str | None = None) -> int:
        if robot_id is None:
            return sum(c.size for c in self._chains.values())
        return self._chain(robot_id).size

    def robots(self) -> list[str]:
        return list(self._chains)

    def components(self) -> list[list[str]]:
        """Robots grouped by inter-robot constraints (including pending ones); within a
        group, poses share one frame. Robots with no node yet are not listed."""
        return [list(c) for c in self._components()]

    def is_anchored(self, robot_id: str) -> bool:
        """True if the robot's group contains a robot with a known start (the map frame)."""
        for comp in self._components():
            if robot_id in comp:
                return any(self._chains[r].T_map_first is not None for r in comp)
        return False

    def latest_index(self, robot_id: str) -> int | None:
        size = self._chain(robot_id).size
        return size - 1 if size else None

    def marginal_covariance(self, robot_id: str, index: int) -> FloatArray:
        """3x3 marginal covariance of a node (body frame, [x, y, yaw]); needs ``update``."""
        key = self._key(robot_id, index)
        if index >= self._chains[robot_id].num_committed:
            raise CollabSlamError(f"node ({robot_id!r}, {index}) is not optimized yet")
        return np.asarray(self._isam.marginalCovariance(key))

    def chi2(self) -> float:
        """Sum of squared whitened residuals of the current estimate (2x gtsam's error).

        Robust factors contribute 2 * rho(residual). Pending changes are not included.
        """
        return 2.0 * self._isam.getFactorsUnsafe().error(self._isam.calculateEstimate())

    # ----- package-internal (batch_solver) -----------------------------------------
    def _gtsam_problem(self, start: str) -> _GtsamProblem:
        """Active committed factors with the initial guesses ("guess") or estimate ("current")."""
        graph = gtsam.NonlinearFactorGraph()
        for record in self._factors.values():
            if record.isam_index is not None:
                graph.add(record.factor)
        if start == "current":
            return _GtsamProblem(graph, self._isam.calculateEstimate())
        if start == "guess":
            return _GtsamProblem(graph, gtsam.Values(self._guesses))
        raise CollabSlamError(f"start must be 'guess' or 'current', got {start!r}")

    def _split(self, values: gtsam.Values) -> dict[str, FloatArray]:
        rows = self._extract(values)
        out, offset = {}, 0
        for robot_id, chain in self._chains.items():
            out[robot_id] = rows[offset : offset + chain.num_committed]
            offset += chain.num_committed
        return out

    # ----- internals ----------------------------------------------------------------
    def _chain(self, robot_id: str) -> _Chain:
        try:
            return self._chains[robot_id]
        except KeyError:
            raise CollabSlamError(f"unknown robot {robot_id!r}") from None

    def _key(self, robot_id: str, index: int) -> int:
        chain = self._chain(robot_id)
        if not 0 <= index < chain.size:
            raise CollabSlamError(f"robot {robot_id!r} has no node {index}")
        return gtsam.symbol(chain.char, index)

    def _offset(self, robot_id: str) -> int:
        offset = 0
        for rid, chain in self._chains.items():
            if rid == robot_id:
                return offset
            offset += chain.num_committed
        raise CollabSlamError(f"unknown robot {robot_id!r}")

    def _full_estimate(self) -> FloatArray:
        """All committed poses (one O(n) calculateEstimate, cached until the next update)."""
        if not self._estimate_valid:
            self._estimate = self._extract(self._isam.calculateEstimate())
            self._estimate_valid = True
        return self._estimate

    def _extract(self, values: gtsam.Values) -> FloatArray:
        # Keys sort by (character, index), so rows come chain after chain in index order.
        rows = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64).reshape(-1, 3)
        expected = sum(c.num_committed for c in self._chains.values())
        if rows.shape[0] != expected:
            raise CollabSlamError(f"estimate has {rows.shape[0]} poses, expected {expected}")
        return rows

    def _add_factor(
        self, factor: gtsam.NonlinearFactor, kind: FactorKind, robots: tuple[str, str] | None = None
    ) -> int:
        fid = self._next_id
        self._next_id += 1
        self._factors[fid] = _Factor(factor, kind, robots)
        self._pending_ids.append(fid)
        return fid

    def _drop_factor(self, factor_id: int) -> None:
        record = self._factors.pop(factor_id)
        if record.isam_index is not None:
            self._pending_removals.append(record.isam_index)

    def _components(self) -> list[list[str]]:
        """Cached until the grouping changes (queried per robot after every update);
        callers must not modify the lists."""
        version, cached = self._components_cache
        if version != self._topology_version:
            cached = self._compute_components()
            self._components_cache = (self._topology_version, cached)
        return cached

    def _compute_components(self) -> list[list[str]]:
        parent = {rid: rid for rid, c in self._chains.items() if c.size > 0}

        def find(r: str) -> str:
            while parent[r] != r:
                parent[r] = parent[parent[r]]
                r = parent[r]
            return r

        for (a, b), count in self._pair_count.items():
            if count > 0:
                parent[find(a)] = find(b)
        groups: dict[str, list[str]] = {}
        for rid in parent:  # registration order inside each group
            groups.setdefault(find(rid), []).append(rid)
        return list(groups.values())

    def _reconcile_gauges(self) -> bool:
        """Give each floating component exactly one gauge prior; True if components merged."""
        components = self._components()
        merged = any(
            len({self._component_of.get(r, -1 - i) for i, r in enumerate(component)}) > 1
            for component in components
        )
        self._component_of = {r: n for n, comp in enumerate(components) for r in comp}
        for component in components:
            anchored = any(self._chains[r].T_map_first is not None for r in component)
            holders = [r for r in component if self._chains[r].gauge_factor is not None]
            keep = None if anchored else (holders[0] if holders else component[0])
            for rid in holders:
                chain = self._chains[rid]
                if rid != keep and chain.gauge_factor is not None:
                    self._drop_factor(chain.gauge_factor)
                    chain.gauge_factor = None
                    logger.debug("robot %r merged into another frame: gauge removed", rid)
            if keep is not None and self._chains[keep].gauge_factor is None:
                chain = self._chains[keep]
                prior = gtsam.PriorFactorPose2(
                    gtsam.symbol(chain.char, 0), _pose2(self.pose(keep, 0)), self._prior_noise
                )
                chain.gauge_factor = self._add_factor(prior, "gauge")
        self._topology_dirty = False
        return merged

    def _changed_robots(
        self, old: FloatArray, new: FloatArray, old_counts: list[int]
    ) -> frozenset[str]:
        changed, old_off, new_off = set(), 0, 0
        for (robot_id, chain), n_old in zip(self._chains.items(), old_counts, strict=True):
            if n_old:
                diff = new[new_off : new_off + n_old] - old[old_off : old_off + n_old]
                diff[:, 2] = wrap_angle(diff[:, 2])
                if np.abs(diff).max() > self._change_epsilon:
                    changed.add(robot_id)
            old_off += n_old
            new_off += chain.num_committed
        return frozenset(changed)
