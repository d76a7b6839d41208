"""Multi-robot 2-D pose graph solved incrementally with gtsam iSAM2.

The only class that sees gtsam types for the 2-D back end; callers use robot ids,
node indices and numpy arrays.

Conventions:
- Every pose is ``T_map_node = [x, y, yaw]`` (m, m, rad) in the base station's map
  frame; a relative pose ``T_a_b`` is node b expressed in node a's frame.
- Covariances are 3x3 over ``[x, y, yaw]`` in the local (body) frame of the node
  (gtsam's Pose2 tangent space), in m^2 / rad^2.
- Keys: robot k (registration order) is ``ROBOT_KEY_ALPHABET[k]``, node i is
  ``gtsam.symbol(char, i)``; 62 letters and digits.

Ordering: with ``heads_last`` every chain's newest node is constrained to the end of
iSAM2's elimination order (the root of the Bayes tree), so when robots take turns the
next node of any robot re-eliminates the root clique only; the solution is the same.

Parts: ``pose_graph_state`` (chain and factor records), ``pose_graph_estimate`` (all
poses as arrays, aliases resolved, which robots moved), ``pose_graph_gauge`` (robot
components; one gauge prior per floating component, removed when components merge),
``pose_graph_gps`` (GPS fixes queued until their nodes exist, then ``gps_factor``s,
seed 000 §III), ``isam2_params`` (ISAM2Params and the options from the config).
"""

from __future__ import annotations

import logging
import time

import gtsam
import numpy as np
from numpy.typing import ArrayLike

from basestation.gps_factor import GpsWeighting
from basestation.isam2_params import make_isam2_params, pose_graph_options
from basestation.pose_graph_estimate import EstimateMixin
from basestation.pose_graph_gauge import GaugeMixin
from basestation.pose_graph_gps import GpsMixin
from basestation.pose_graph_rebuild import RebuildMixin
from basestation.pose_graph_reduction import REDUCE_BATCH_NODES, ReductionMixin
from basestation.pose_graph_state import (
    Chain,
    FloatArray,
    GtsamProblem,
    UpdateStats,
    gaussian_noise,
    pose2,
    pose_array,
    vec3,
)
from common.config import BaseStationConfig
from common.errors import CollabSlamError
from common.geometry import se2_compose, se2_inverse
from common.growable import empty

logger = logging.getLogger(__name__)

# one chain per robot (and per later segment of one, basestation/robot_segments.py); ASCII
# only: keys are also handled as int64 (ord(char) << 56)
ROBOT_KEY_ALPHABET = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789"
ROBUST_KERNELS = ("huber", "cauchy")
GUESS_MERGE_BATCH = 64  # updates whose initial guesses are merged at once


class PoseGraph(EstimateMixin, GaugeMixin, GpsMixin, ReductionMixin, RebuildMixin):
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
        reduce_distance_m: float = 0.0,  # > 0: reduced pose graph (pose_graph_reduction)
        reduce_lag: int = 20,  # nodes behind a chain's newest before one may be aliased
        reduce_after_nodes: int = 0,  # the reduction starts once the graph has this many
        reduce_batch_nodes: int = REDUCE_BATCH_NODES,  # settled nodes waiting before a pass
        tie_budget: float = 0.0,  # final-constraint ties per variable, then folded (0: no cap)
        rebuild_nodes: int = 0,  # reduced graphs: a fresh iSAM2 each this many nodes (0: never)
        tie_degree: int = 0,  # at a rebuild, ties per place kept beyond a spanning forest (0: all)
    ) -> None:
        params = make_isam2_params(
            factorization=factorization,
            relinearize_threshold=relinearize_threshold,
            relinearize_skip=relinearize_skip,
            wildfire_threshold=wildfire_threshold,
            cache_linearized_factors=cache_linearized_factors,
            adaptive_reorder_threshold=adaptive_reorder_threshold,
        )
        self._isam = gtsam.ISAM2(params)
        self._prior_noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(prior_sigmas, float))
        self._change_epsilon = change_epsilon
        self._settle_iterations = settle_iterations
        self._track_changes = track_changes
        # heads_last: every chain's newest node (committed or pending), kept by add_node
        self._heads = gtsam.KeyGroupMap() if heads_last else None
        self._chains = {}
        self._factors = {}
        self._pending_ids = []
        self._pending_removals = []
        self._pending_graph, self._pending_graph_ids, self._pending_stale = None, [], False
        self._pending_values: gtsam.Values | None = None  # the pending nodes' guesses
        self._pending_nodes: dict[str, int] = {}  # robot id -> its pending nodes
        self._next_id = 0
        self._init_gauges()
        self._guesses = gtsam.Values()  # every initial guess handed to iSAM2 (for batch)
        self._new_guesses: list[gtsam.Values] = []  # the latest updates' (merged in batches)
        self._estimate = np.zeros((0, 3))  # committed poses, rows in key order
        self._estimate_buffers = [empty((3,), np.float64), empty((3,), np.float64)]
        self._estimate_valid = True  # False: recompute on the next full-estimate query
        self._init_gps(gps_weighting, max_pending_gps_fixes, gps_batch_period_s)
        self._init_reduction(
            reduce_distance_m, reduce_lag, reduce_after_nodes, reduce_batch_nodes, tie_budget
        )
        self._init_rebuild(rebuild_nodes, tie_degree)

    @classmethod
    def from_config(cls, b: BaseStationConfig, track_changes: bool | None = None) -> PoseGraph:
        """The base station's pose graph (``track_changes`` None: ``b.track_changes``)."""
        return cls(**pose_graph_options(b, track_changes))

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
        if self.full():
            raise CollabSlamError(f"at most {len(ROBOT_KEY_ALPHABET)} robots are supported")
        start = None if T_map_first is None else vec3(T_map_first, "T_map_first")
        chain = Chain(ROBOT_KEY_ALPHABET[len(self._chains)], start)
        if start_sigmas is not None:
            if start is None:
                raise CollabSlamError("start_sigmas needs a T_map_first")
            chain.start_sigmas = vec3(start_sigmas, "start_sigmas")
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
        guess = None if initial_guess is None else pose2(vec3(initial_guess, "initial_guess"))
        key = gtsam.symbol(chain.char, index)
        if index == 0:
            if delta is not None:
                raise CollabSlamError("the first node of a chain takes no delta")
            start = chain.T_map_first
            if guess is None:
                guess = gtsam.Pose2() if start is None else pose2(start)
            if start is not None:
                noise = self._prior_noise
                if chain.start_sigmas is not None:
                    noise = gtsam.noiseModel.Diagonal.Sigmas(chain.start_sigmas)
                prior = gtsam.PriorFactorPose2(key, pose2(start), noise)
                self._add_factor(prior, "start")
            self._topology_changed()
        else:
            if delta is None or covariance is None:
                raise CollabSlamError("nodes after the first need delta and covariance")
            d = vec3(delta, "delta")
            noise = gaussian_noise(covariance)
            if guess is None:  # gtsam's compose: no numpy between two iSAM2 updates
                guess = self._pose2(robot_id, chain, index - 1).compose(pose2(d))
            factor = self._between(chain, index - 1, chain, index, d, noise)
            self._add_factor(factor, "odometry")
        chain.pending.append(guess)
        self._pending_nodes[robot_id] = len(chain.pending)
        # the next update's values and heads are kept as nodes come, not built in update()
        if self._pending_values is None:
            self._pending_values = gtsam.Values()
        self._pending_values.insert(key, pose2=guess)  # keyword: skips pybind's array tries
        if self._heads is not None:  # the chain's newest node replaces its old head
            if index:
                self._heads.erase(key - 1)
            self._heads.insert2(key, 1)
        if stamp is None:
            chain.stamps = None
        elif chain.stamps is not None:
            chain.stamps.append([stamp])
        self._attach_gps(robot_id)

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
        chain_a, chain_b = self._node_chain(*key_a), self._node_chain(*key_b)
        if key_a == key_b:
            raise CollabSlamError(f"constraint from node {key_a} to itself")
        noise = gaussian_noise(covariance)
        if robust is not None:
            if robust not in ROBUST_KERNELS or not robust_k > 0:
                raise CollabSlamError(f"robust must be one of {ROBUST_KERNELS} with k > 0")
            kernel_cls = getattr(gtsam.noiseModel.mEstimator, robust.capitalize())
            noise = gtsam.noiseModel.Robust.Create(kernel_cls.Create(robust_k), noise)
        T = vec3(T_a_b, "T_a_b")
        factor = self._between(chain_a, key_a[1], chain_b, key_b[1], T, noise)
        if self.reducing:
            chain_a.constrained.add(key_a[1])
            chain_b.constrained.add(key_b[1])
        robots = None
        if key_a[0] != key_b[0]:
            robots = (min(key_a[0], key_b[0]), max(key_a[0], key_b[0]))
            self._pair_count[robots] += 1
            if self._pair_count[robots] == 1:  # the grouping depends on which pairs are tied
                self._topology_changed()
        fid = self._add_factor(factor, "constraint", robots)
        if robust is not None:
            self._factors[fid].kernel = (robust, robust_k)
        return fid

    def remove_constraint(self, factor_id: int) -> None:
        """Remove a constraint returned by ``add_constraint`` at the next update."""
        record = self._factors.get(factor_id)
        if record is None or record.kind != "constraint" or record.final:
            raise CollabSlamError(f"no active constraint with id {factor_id} (or a final one)")
        if record.robots is not None:
            self._pair_count[record.robots] -= 1
            if self._pair_count[record.robots] == 0:
                self._topology_changed()
        self._drop_factor(factor_id)

    # ----- solving ------------------------------------------------------------------
    def update(self, extra_iterations: int = 0) -> UpdateStats:
        """Run iSAM2 on everything pending (no-op if nothing is pending and no extras).

        ``extra_iterations`` adds empty iSAM2 updates (relinearization steps); they stop
        early once no variable is relinearized.
        """
        t_start = time.perf_counter()
        merged = self._reconcile_gauges() if self._topology_dirty else False
        factors = self._factors
        if self._pending_stale:  # a pending factor was dropped or replaced: build anew
            new_ids = [
                fid
                for fid in dict.fromkeys(self._pending_ids)  # a moved factor may come twice
                if (record := factors.get(fid)) is not None and record.factor is not None
            ]
            graph = gtsam.NonlinearFactorGraph()
            for fid in new_ids:
                graph.add(factors[fid].factor)
        else:
            new_ids = self._pending_graph_ids
            graph = self._pending_graph
            if graph is None:
                graph = gtsam.NonlinearFactorGraph()
        removals = self._pending_removals
        if not new_ids and not removals and extra_iterations == 0:
            return UpdateStats(0.0, 0.0, 0, 0, 0, 0, frozenset(), frozenset())
        values = self._pending_values if self._pending_values is not None else gtsam.Values()
        new_nodes = self._pending_nodes

        t_solve = time.perf_counter()
        try:
            # heads None: iSAM2's default, the keys of the new factors go last
            result = self._isam.update(graph, values, removals, constrainedKeys=self._heads)
            slots = result.getNewFactorsIndices()
            iterations, reordered = 1, result.getBatchReorderTriggered()
            # a merge or a GPS batch moves whole chains: settle them within this update
            settle = merged or (
                self._gps_robots and any(factors[fid].kind == "gps" for fid in new_ids)
            )
            if settle or extra_iterations:
                iterations, reordered = self._iterate(extra_iterations, settle, reordered)
        except RuntimeError as exc:  # e.g. gtsam's IndeterminantLinearSystemException
            self._refactor_with_qr(exc, values)  # (every factor gets its slot there)
            new_ids, slots, iterations, reordered = [], [], 1, True
        solve_ms = (time.perf_counter() - t_solve) * 1e3
        for fid, slot in zip(new_ids, slots, strict=True):
            factors[fid].isam_index = slot

        # Merged into the big Values in batches, not between the update and the reads of
        # the new estimate that follow it: its map would evict iSAM2's tree from the caches.
        if new_nodes:
            self._new_guesses.append(values)
            self._pending_values = None
            if len(self._new_guesses) >= GUESS_MERGE_BATCH:
                self._committed_guesses()
        self._pending_ids, self._pending_removals = [], []
        self._pending_graph, self._pending_graph_ids, self._pending_stale = None, [], False
        self._pending_nodes = {}
        self._after_update(sum(new_nodes.values()))  # a fresh iSAM2 now and then
        changed, chains = None, self._chains
        if self._track_changes:  # then the previous estimate is always valid
            old_estimate, old_counts = self._estimate, [c.num_committed for c in chains.values()]
        for robot_id, count in new_nodes.items():
            chain = chains[robot_id]
            chain.num_committed, chain.pending = chain.num_committed + count, []
        self._estimate_valid = False
        if self._track_changes:
            changed = self._changed_robots(old_estimate, self._full_estimate(), old_counts)
        if self.reducing:
            self._reduce()  # its moved factors go to iSAM2 with the next update
        stats = UpdateStats(
            (time.perf_counter() - t_start) * 1e3,  # wall_ms
            solve_ms,
            iterations,
            len(new_ids),  # num_new_factors
            len(removals),  # num_removed_factors
            sum(new_nodes.values()),  # num_new_nodes
            changed,  # changed_robots
            frozenset(new_nodes),  # robots_with_new_nodes
            reordered,  # batch_reordered
        )
        if logger.isEnabledFor(logging.DEBUG):
            logger.debug(
                "iSAM2 update: %d factors, %d removed, %d nodes, %d iterations, %.2f ms "
                "(solve %.2f)",
                *stats[3:6],
                iterations,
                stats.wall_ms,
                solve_ms,
            )
        return stats

    def _iterate(self, extra: int, settle: bool, reordered: bool) -> tuple[int, bool]:
        """``extra`` more iSAM2 iterations, or the settle iterations if more; they stop
        early once no variable is relinearized. Returns (iterations in all, reordered)."""
        iterations = 1
        for _ in range(max(extra, self._settle_iterations if settle else 0)):
            iterations += 1
            result = self._isam.update(  # force: even between relinearization skips
                constrainedKeys=self._heads, force_relinearize=True
            )
            reordered = reordered or result.getBatchReorderTriggered()
            if result.getVariablesRelinearized() == 0:
                break
        if settle:  # back-substitute now (lazy in gtsam: it would land in the next update)
            self._isam.getDelta()
        return iterations, reordered

    # ----- queries ------------------------------------------------------------------
    def pose(self, robot_id: str, index: int) -> FloatArray:
        """T_map_node of one node (its initial guess while it waits for ``update``)."""
        chain = self._chains.get(robot_id)
        if chain is None or not 0 <= index < chain.num_committed + len(chain.pending):
            self._node_chain(robot_id, index)  # raises the error
        if index >= chain.num_committed:
            return pose_array(chain.pending[index - chain.num_committed])
        if self._estimate_valid:
            return self._estimate[self._offset(robot_id) + index].copy()
        if index < len(chain.alias_key) and chain.alias_key[index] >= 0:
            key, offset = self._resolve(chain, index)
            return se2_compose(pose_array(self._isam.calculateEstimatePose2(key)), offset)
        # most queries: a chain's newest node, for its correction, right after an update
        p = self._isam.calculateEstimatePose2(chain.key_base + index)  # O(1)-ish
        return np.array((p.x(), p.y(), p.theta()))

    def poses(self, robot_id: str) -> FloatArray:
        """(N, 3) poses of a chain in index order (pending nodes: their initial guess)."""
        chain = self._chain(robot_id)
        offset = self._offset(robot_id)
        committed = self._full_estimate()[offset : offset + chain.num_committed]
        if not chain.pending:
            return committed.copy()
        return np.vstack([committed, *(pose_array(p) for p in chain.pending)])

    def num_nodes(self, robot_id: str | None = None) -> int:
        if robot_id is None:
            return sum(c.size for c in self._chains.values())
        return self._chain(robot_id).size

    def full(self) -> bool:
        """Whether no more robots (chains) can be added."""
        return len(self._chains) >= len(ROBOT_KEY_ALPHABET)

    def robots(self) -> list[str]:
        return list(self._chains)

    def factor_slots(self) -> int:
        """iSAM2's factor slots: its graph never shrinks, a removed factor leaves an empty
        slot (memory: what the base station's samples report)."""
        return int(self._isam.getFactorsUnsafe().size())

    def latest_index(self, robot_id: str) -> int | None:
        chain = self._chains.get(robot_id) or self._chain(robot_id)  # the latter raises
        size = chain.num_committed + len(chain.pending)
        return size - 1 if size else None

    def marginal_covariance(self, robot_id: str, index: int) -> FloatArray:
        """3x3 marginal covariance of a node (body frame, [x, y, yaw]); needs ``update``."""
        chain = self._node_chain(robot_id, index)
        if index >= chain.num_committed:
            raise CollabSlamError(f"node ({robot_id!r}, {index}) is not optimized yet")
        key, offset = self._resolve(chain, index)
        cov = np.asarray(self._isam.marginalCovariance(key))
        if offset is None:
            return cov
        ad = np.asarray(pose2(se2_inverse(offset)).AdjointMap())  # node = anchor * offset
        return ad @ cov @ ad.T

    def chi2(self) -> float:
        """Sum of squared whitened residuals of the current estimate (2x gtsam's error).

        Robust factors contribute 2 * rho(residual). Pending changes are not included.
        """
        return 2.0 * self._isam.getFactorsUnsafe().error(self._isam.calculateEstimate())

    # ----- package-internal (batch_solver) -----------------------------------------
    def _gtsam_problem(self, start: str) -> GtsamProblem:
        """Active committed factors with the initial guesses ("guess") or estimate ("current")."""
        graph = gtsam.NonlinearFactorGraph()
        for record in self._factors.values():
            if record.isam_index is not None and record.factor is not None:
                graph.add(record.factor)
        if start == "current":
            return GtsamProblem(graph, self._isam.calculateEstimate())
        if start == "guess":
            return GtsamProblem(graph, gtsam.Values(self._committed_guesses()))
        raise CollabSlamError(f"start must be 'guess' or 'current', got {start!r}")

    def _split(self, values: gtsam.Values) -> dict[str, FloatArray]:
        rows = self._extract(values)
        out, offset = {}, 0
        for robot_id, chain in self._chains.items():
            out[robot_id] = rows[offset : offset + chain.num_committed]
            offset += chain.num_committed
        return out

    # ----- internals ----------------------------------------------------------------
    def _node_chain(self, robot_id: str, index: int) -> Chain:
        """The chain of node ``index`` of ``robot_id`` (CollabSlamError if no such node)."""
        chain = self._chain(robot_id)
        if not 0 <= index < chain.size:
            raise CollabSlamError(f"robot {robot_id!r} has no node {index}")
        return chain

    def _committed_guesses(self) -> gtsam.Values:
        """The initial guess of every variable iSAM2 holds (merges the latest first)."""
        for values in self._new_guesses:
            self._guesses.insert(values)
        self._new_guesses = []
        return self._guesses

    def _pose2(self, robot_id: str, chain: Chain, index: int) -> gtsam.Pose2:
        """A node's pose as a gtsam Pose2 (a chain's newest nodes: without numpy)."""
        if index >= chain.num_committed:
            return chain.pending[index - chain.num_committed]
        if index < len(chain.alias_key) and chain.alias_key[index] >= 0:
            return pose2(self.pose(robot_id, index))
        return self._isam.calculateEstimatePose2(chain.key_base + index)
