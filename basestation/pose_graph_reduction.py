"""Reduced pose graph: keyframes that add no new place become aliases of an old node.

A robot that flies over mapped ground keeps sending keyframes; if every keyframe were
a variable, iSAM2 would grow by ~4 kB per keyframe forever (Johannsson et al. 2013,
"Temporally scalable visual SLAM using a reduced pose graph"). Here, once the graph
has ``after_nodes`` nodes, every committed node ``lag`` keyframes behind its chain's
newest one (its loop closures have had time to arrive) is *aliased* onto a variable
node within ``max_distance_m`` (x-y, by the current estimate) that the pass has
already gone past (passes run once ``batch_nodes`` such nodes wait, oldest first):
the nearest one at most two factors away in the graph (its chain neighbours, or
nodes a loop closure or inter-robot constraint joined it to); failing that, if a
node within ``LINK_KEYFRAMES`` of it on its chain has such a constraint (its stretch
is registered against the map there), the nearest one however far in the graph.
Without either, a robot revisiting ground is not tied to it by proximity alone.
Candidates are variables of the node's own robot or of a robot it shares at least
``ACROSS_MIN_CONSTRAINTS`` inter-robot constraints with: an alias cannot be undone, so
the pair's relative placement must rest on several agreeing matches, not on one PCM
may still remove; a node aliased onto another robot's variable ties the two robots
into one component for good. The node's variable is removed from iSAM2, its pose
becomes ``T_map_anchor * offset`` with the offset frozen from the current estimate,
and every factor on it is moved onto the anchor (measurement and covariance
transformed). Odometry factors that end up between the same two variables are fused
into one (information-weighted in the tangent space), so revisits add no factors
either: the variables and factors grow with the area flown, not with the time flown,
and a team of robots over one area holds one set of variables, not one per robot.
Final constraints between the same two variables are fused too. Beyond ``tie_budget``
final-constraint ties per variable, one that would tie a new pair of variables is folded
into an existing tie next to it (``_fold``), and so is one that would tie two variables
more than ``LONG_TIE_M`` apart, budget or not: the ties, whose fill-in is most of iSAM2's
growth over a long mission in one area, then stop growing with the time flown too;
with a budget, an odometry factor that an alias would make a new tie between two
settled variables already joined within two hops is left out (``_redundant_odometry``).
Freezing offsets costs accuracy (the relations inside a cluster are dropped), so the
base station starts only on a large graph (``basestation.reduce_after_nodes``).

Keyframes keep their indices; ``PoseGraph.pose``, ``poses``, ``add_node`` and
``add_constraint`` resolve aliases, so callers do not see the reduction. Not reduced:
a chain's first node, anchors, nodes with priors or GPS factors, robots with GPS fixes.

Package-internal: a mixin of ``basestation.pose_graph.PoseGraph``.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import TYPE_CHECKING

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from basestation.between_measurements import (
    adjoint,
    covariance_of,
    fuse,
    moved_measurement,
    noise_with,
    pose_array,
)
from basestation.pose_graph_state import Chain, FloatArray, PoseGraphState, pose2
from common.errors import CollabSlamError
from common.geometry import se2_between, se2_inverse

logger = logging.getLogger(__name__)

CHAR_SHIFT = 56  # gtsam.symbol(c, i) == ord(c) << 56 | i
INDEX_MASK = (1 << CHAR_SHIFT) - 1
REDUCIBLE_KINDS = ("odometry", "constraint")
# Nodes aliased per update at most: when the reduction starts on a large graph, it catches
# up over many updates (one pass over 10,000 nodes in one update took 1.4 s).
MAX_ALIASES_PER_UPDATE = 100
# Settled nodes that wait before a pass runs: an update that aliases nodes re-eliminates
# old parts of the Bayes tree; in batches, most updates only append (10-robot soak replay:
# update p50 at 18,000-27,000 nodes 5.5-8.0 ms with a pass every update, 1.3-2.8 ms so).
REDUCE_BATCH_NODES = 100
# Inter-robot constraints two robots need in the graph before one's nodes may become
# aliases of the other's variables: an alias cannot be undone, so the robots' relative
# placement must rest on several agreeing matches, not one PCM may still remove.
ACROSS_MIN_CONSTRAINTS = 5
# A node with a loop closure or inter-robot constraint within this many keyframes of its
# chain is aliased onto the nearest passed variable close by, however many factors away:
# its stretch is registered against the map there (else only variables two factors away).
LINK_KEYFRAMES = 10
# m: a final constraint beyond the tie budget is folded into a tie whose far end is this
# close to its own (``_fold``); with none that close it ties a new pair (a new place).
FOLD_DISTANCE_M = 3.0
# m: a final constraint that would tie a new pair of variables farther apart than this is
# folded as if past the budget, from the first one on. Long ties make the fill-in: the
# 10-robot soak's graph at 100,000 keyframes holds 5 % of its ties over 3 m, and a fresh
# iSAM2 of it without them needs 28 % less memory. Folded, such matches join the tie next
# to them instead (soak replay: iSAM2 -7 %, trajectory error 0.0504 against 0.0517 m).
LONG_TIE_M = 2.0
SNAPSHOT_NEIGHBOURS = 8  # nearest variables looked at for one of an allowed robot


def _dist2(a: FloatArray, b: FloatArray) -> float:
    return float((a[0] - b[0]) ** 2 + (a[1] - b[1]) ** 2)


def _nearest(
    keys: list[int], poses: list[FloatArray], here: FloatArray
) -> tuple[int, FloatArray] | None:
    if not keys:
        return None
    best = min(range(len(keys)), key=lambda j: _dist2(poses[j], here))
    return keys[best], poses[best]


class _Snapshot:
    """The variables' estimate at the start of a pass, and a k-d tree of those the
    reduction has passed (they stay variables), for the nearest-variable queries."""

    def __init__(self, values: gtsam.Values, chains: dict[str, Chain], gps: set[str]) -> None:
        self.keys = np.fromiter(values.keys(), dtype=np.int64, count=values.size())
        self.poses = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64)
        self.poses = self.poses.reshape(-1, 3)
        passed = np.zeros(len(self.keys), dtype=bool)
        chars, index = self.keys >> CHAR_SHIFT, self.keys & INDEX_MASK
        for rid, chain in chains.items():
            if rid not in gps:
                passed |= (chars == ord(chain.char)) & (index < chain.reduce_next)
        self.passed = np.flatnonzero(passed)
        self.tree = cKDTree(self.poses[self.passed, :2]) if len(self.passed) else None

    def pose(self, key: int) -> FloatArray:
        return self.poses[int(np.searchsorted(self.keys, key))]

    def nearest(
        self, here: FloatArray, anchors: dict[int, tuple[str, Chain]]
    ) -> tuple[int, FloatArray] | None:
        """The nearest passed variable of the chains in ``anchors`` (among the
        ``SNAPSHOT_NEIGHBOURS`` nearest passed variables of all robots)."""
        if self.tree is None:
            return None
        k = min(SNAPSHOT_NEIGHBOURS, len(self.passed))
        _, rows = self.tree.query(here[:2], k=k)
        for row in np.atleast_1d(rows):
            key = int(self.keys[self.passed[row]])
            if key >> CHAR_SHIFT in anchors:
                return key, self.poses[self.passed[row]]
        return None


class ReductionMixin(PoseGraphState):
    """Aliases per chain, factor adjacency, and the reduction pass after each update."""

    if TYPE_CHECKING:  # provided by PoseGraph
        _isam: gtsam.ISAM2
        _gps_robots: set[str]
        _pair_count: Counter[tuple[str, str]]
        _alias_ties: set[tuple[str, str]]

        def _topology_changed(self) -> None: ...

        def _committed_guesses(self) -> gtsam.Values: ...

    def _init_reduction(
        self, max_distance_m: float, lag: int, after_nodes: int, batch_nodes: int, tie_budget: float
    ) -> None:
        self._reduce_distance = float(max_distance_m)
        self._reduce_lag = max(int(lag), 1)
        self._reduce_after = max(int(after_nodes), 0)
        self._reduce_batch = max(int(batch_nodes), 1)
        self.reduction_started = False
        self._anchors: set[int] = set()  # variables other nodes are aliased onto
        self.num_aliased = 0
        self.num_fused = 0  # final constraints fused into another between the same variables
        self._tie_budget = float(tie_budget)  # final-constraint ties per variable (_fold)
        self.num_folded = 0  # final constraints moved onto an existing tie (``_fold``)
        self.num_dropped = 0  # odometry ties between settled places left out (``_alias``)
        if self._reduce_distance > 0.0:
            self._adjacency = {}
            self._pairs = {}

    @property
    def reducing(self) -> bool:
        return self._adjacency is not None

    def reduction_stats(self) -> dict[str, int | bool]:
        """Nodes (keyframes), the variables iSAM2 holds for them, aliases, factors."""
        nodes = sum(c.size for c in self._chains.values())
        return {
            "reducing": self.reduction_started,
            "nodes": nodes,
            "variables": nodes - self.num_aliased,
            "aliased": self.num_aliased,
            "factors": sum(r.factor is not None for r in self._factors.values()),
            "factor_records": len(self._factors),  # also constraints inside one cluster
            "fused_constraints": self.num_fused,
            "final_ties": self._num_final_ties,  # pairs of variables final constraints tie
            "folded_constraints": self.num_folded,
            "dropped_odometry": self.num_dropped,
        }

    # ----- resolving keyframes to variables -------------------------------------------
    def _resolve(self, chain: Chain, index: int) -> tuple[int, FloatArray | None]:
        """(variable key, offset T_anchor_node or None) of node ``index`` of ``chain``."""
        if index < len(chain.alias_key) and chain.alias_key[index] >= 0:
            return int(chain.alias_key[index]), chain.alias_offset[index]
        return gtsam.symbol(chain.char, index), None

    def _between(
        self,
        chain_a: Chain,
        index_a: int,
        chain_b: Chain,
        index_b: int,
        T_a_b: FloatArray,
        noise: gtsam.noiseModel.Base,
    ) -> gtsam.BetweenFactorPose2 | None:
        """A between factor of two nodes, moved onto their variables; None if both are
        aliases of one variable (a relation inside a rigid cluster carries nothing)."""
        ka, off_a = self._resolve(chain_a, index_a)
        kb, off_b = self._resolve(chain_b, index_b)
        if ka == kb:
            return None
        if off_a is not None or off_b is not None:
            z, cov = T_a_b, covariance_of(noise)
            if off_a is not None:
                z, cov = moved_measurement(z, cov, 0, off_a)
            if off_b is not None:
                z, cov = moved_measurement(z, cov, 1, off_b)
            T_a_b, noise = z, noise_with(noise, cov)
        return gtsam.BetweenFactorPose2(ka, kb, pose2(T_a_b), noise)

    # ----- the reduction pass ---------------------------------------------------------
    def _reduce(self) -> int:
        """Alias every settled node that has a variable close by; returns how many."""
        if not self.reducing:
            return 0
        if not self.reduction_started:
            nodes = sum(c.num_committed for c in self._chains.values())
            if nodes < self._reduce_after:
                return 0
            self.reduction_started = True
            logger.info("pose graph: %d nodes, reducing from now on", nodes)
        settled = (
            c.num_committed - self._reduce_lag - c.reduce_next for c in self._chains.values()
        )
        if sum(max(n, 0) for n in settled) < self._reduce_batch:
            return 0  # most updates only append; every so many, one does the reduction
        count = 0
        snapshot = _Snapshot(self._isam.calculateEstimate(), self._chains, self._gps_robots)
        for robot_id, chain in self._chains.items():
            stop = chain.num_committed - self._reduce_lag
            if robot_id in self._gps_robots or stop <= chain.reduce_next:
                continue
            chain.grow_aliases(chain.num_committed)
            anchors = self._anchor_chains(robot_id)
            for index in range(max(chain.reduce_next, 1), stop):
                chain.reduce_next = index  # anchors: variables the pass has gone past
                if count >= MAX_ALIASES_PER_UPDATE:
                    break
                key = gtsam.symbol(chain.char, index)
                if chain.alias_key[index] >= 0 or key in self._anchors:
                    continue
                fids = self._adjacency.get(key)
                if not fids or any(self._factors[f].kind not in REDUCIBLE_KINDS for f in fids):
                    continue
                here = snapshot.pose(key)
                near = [  # variables the pass has gone past (they stay), of robots allowed
                    k
                    for k in self._two_hops(key, fids)
                    if (c := anchors.get(k >> CHAR_SHIFT)) is not None
                    and (k & INDEX_MASK) < c[1].reduce_next
                ]
                anchor = _nearest(near, [snapshot.pose(k) for k in near], here)
                if not self._close(anchor, here) and self._linked(chain, index):
                    anchor = snapshot.nearest(here, anchors)
                if anchor is None or not self._close(anchor, here):
                    continue
                self._alias(chain, index, key, anchor[0], se2_between(anchor[1], here))
                other = anchors[anchor[0] >> CHAR_SHIFT][0]
                tie = (min(robot_id, other), max(robot_id, other))
                if other != robot_id and tie not in self._alias_ties:
                    self._alias_ties.add(tie)  # one component for good
                    self._topology_changed()
                count += 1
            else:
                chain.reduce_next = stop
            # marks behind the pass are never read again (_linked looks around the pass)
            low = chain.reduce_next - LINK_KEYFRAMES
            chain.constrained = {i for i in chain.constrained if i >= low}
        self.num_aliased += count
        return count

    def _close(self, anchor: tuple[int, FloatArray] | None, here: FloatArray) -> bool:
        return anchor is not None and _dist2(anchor[1], here) <= self._reduce_distance**2

    def _linked(self, chain: Chain, index: int) -> bool:
        """Whether a node of ``chain`` within ``LINK_KEYFRAMES`` of ``index`` has a loop
        closure or inter-robot constraint: this stretch is registered against the map."""
        return any(
            i in chain.constrained
            for i in range(index - LINK_KEYFRAMES, index + 1 + LINK_KEYFRAMES)
        )

    def _anchor_chains(self, robot_id: str) -> dict[int, tuple[str, Chain]]:
        """Key character -> (robot, chain), for the chains whose (passed) variables
        ``robot_id``'s nodes may be aliased onto: its own, and those of robots it shares
        at least ``ACROSS_MIN_CONSTRAINTS`` inter-robot constraints with (no GPS robot)."""
        out = {}
        for rid, chain in self._chains.items():
            pair = (min(rid, robot_id), max(rid, robot_id))
            if rid == robot_id or (
                rid not in self._gps_robots and self._pair_count[pair] >= ACROSS_MIN_CONSTRAINTS
            ):
                out[ord(chain.char)] = (rid, chain)
        return out

    def _two_hops(self, key: int, fids: set[int]) -> set[int]:
        near: set[int] = set()
        for fid in fids:
            near.update(self._factors[fid].keys)
        first = list(near)
        for k in first:
            for fid in self._adjacency.get(k, ()):
                near.update(self._factors[fid].keys)
        near.discard(key)
        return near

    def _alias(self, chain: Chain, index: int, key: int, anchor: int, offset: FloatArray) -> None:
        """Make node ``index`` an alias of variable ``anchor``; move its factors there."""
        chain.alias_key[index] = anchor
        chain.alias_offset[index] = offset
        self._anchors.add(anchor)
        for fid in list(self._adjacency.get(key, ())):
            record = self._factors[fid]
            factor = record.factor
            ka, kb = record.keys
            z = pose_array(factor.measured())
            noise = factor.noiseModel()
            side = 0 if ka == key else 1
            z, cov = moved_measurement(z, covariance_of(noise), side, offset)
            ka, kb = (anchor, kb) if side == 0 else (ka, anchor)
            fusable = record.kind == "odometry" or record.final
            if ka == kb and fusable:  # inside one variable: carries nothing, for good
                self._drop_factor(fid)
                continue
            if record.final:
                ka, kb, z, cov = self._fold(ka, kb, z, cov, leaving=key)
            elif record.kind == "odometry" and self._redundant_odometry(fid, ka, kb, key):
                self._drop_factor(fid)
                self.num_dropped += 1
                continue
            if ka == kb:
                moved = None
            else:
                moved = gtsam.BetweenFactorPose2(ka, kb, pose2(z), noise_with(noise, cov))
            if fusable and moved is not None:
                other = self._pairs.get((record.final, min(ka, kb), max(ka, kb)))
                if other is not None and other != fid:
                    moved = self._fused(other, ka, kb, z, cov, record.count)
                    record.count += self._factors[other].count
                    self._drop_factor(other)
                    self.num_fused += record.final
            self._replace_factor(fid, moved)
        self._adjacency.pop(key, None)
        guesses = self._committed_guesses()
        if guesses.exists(key):
            guesses.erase(key)

    def finalize_constraint(self, factor_id: int) -> None:
        """Constraint ``factor_id`` will never be removed (it left PCM's window, so its
        state is final): a reducing graph fuses it with the other final constraints between
        the same two variables, now and whenever the reduction moves one onto another's
        pair, so these grow with the pairs of places, not with the revisits. One inside a
        rigid cluster is forgotten. Its robots stay connected (``components``). Without the
        reduction nothing changes."""
        record = self._factors.get(factor_id)
        if record is None or record.kind != "constraint" or record.final:
            raise CollabSlamError(f"no active constraint with id {factor_id} to finalize")
        if not self.reducing:
            record.final = True
            return
        if record.factor is None:
            self._drop_factor(factor_id)
            return
        self._unlink(factor_id, record)
        record.final = True
        ka, kb = record.factor.keys()
        noise = record.factor.noiseModel()
        z, cov = pose_array(record.factor.measured()), covariance_of(noise)
        ka, kb, z, cov = self._fold(ka, kb, z, cov)
        other = self._pairs.get((True, min(ka, kb), max(ka, kb)))
        if other is None:  # a new pair (never a folded one: it lands on a tie)
            self._link(factor_id, record)
            return
        fused = self._fused(other, ka, kb, z, cov, record.count)
        self._drop_factor(factor_id)
        self._replace_factor(other, fused)
        self._factors[other].count += record.count
        self.num_fused += 1

    def _fold(
        self, ka: int, kb: int, z: FloatArray, cov: FloatArray, leaving: int = -1
    ) -> tuple[int, int, FloatArray, FloatArray]:
        """A final constraint T_ka_kb, moved onto an existing tie once the final ties
        number ``tie_budget`` per variable (or, with any budget, when its variables are
        more than ``LONG_TIE_M`` apart): when it would tie a new pair and one end
        already has a final tie to a variable within ``FOLD_DISTANCE_M`` of the other
        end, that end is expressed through the nearest such variable (the offset frozen
        from the current estimate, as an alias's is) and the caller fuses the
        measurement into that tie. Ties between places make iSAM2's fill-in (a fresh
        iSAM2 of the 30-minute soak's graph: 19 MB at 30,000 keyframes, 38 at 79,000
        for the same places); matches next to an existing tie add none. Unchanged
        otherwise. ``leaving``: a variable being aliased (its ties are moving away)."""
        assert self._pairs is not None
        if self._tie_budget <= 0.0 or (True, min(ka, kb), max(ka, kb)) in self._pairs:
            return ka, kb, z, cov
        variables = sum(c.size for c in self._chains.values()) - self.num_aliased
        if self._num_final_ties < self._tie_budget * variables and not self._long(ka, kb):
            return ka, kb, z, cov
        best: tuple[float, int, int, FloatArray] | None = None
        for side, own, far in ((1, ka, kb), (0, kb, ka)):
            at: FloatArray | None = None
            for fid in self._adjacency.get(own, ()):
                record = self._factors[fid]
                if not record.final or record.factor is None:
                    continue
                p = record.keys[1] if record.keys[0] == own else record.keys[0]
                if p == leaving or not self._isam.valueExists(p):
                    continue
                if at is None:
                    if not self._isam.valueExists(far):
                        break
                    at = pose_array(self._isam.calculateEstimatePose2(far))
                there = pose_array(self._isam.calculateEstimatePose2(p))
                d2 = _dist2(there, at)
                if d2 <= FOLD_DISTANCE_M**2 and (best is None or d2 < best[0]):
                    best = (d2, side, p, se2_between(there, at))
        if best is None:
            return ka, kb, z, cov
        _, side, p, offset = best
        z, cov = moved_measurement(z, cov, side, offset)
        self.num_folded += 1
        return (ka, p, z, cov) if side == 1 else (p, kb, z, cov)

    def _long(self, ka: int, kb: int) -> bool:
        """Whether variables ka and kb are more than ``LONG_TIE_M`` apart (estimate)."""
        if not (self._isam.valueExists(ka) and self._isam.valueExists(kb)):
            return False
        a = pose_array(self._isam.calculateEstimatePose2(ka))
        b = pose_array(self._isam.calculateEstimatePose2(kb))
        return _dist2(a, b) > LONG_TIE_M**2

    def _redundant_odometry(self, fid: int, ka: int, kb: int, leaving: int) -> bool:
        """Whether odometry factor ``fid``, moved onto variables ka and kb by an alias,
        would tie a new pair of settled variables (anchors, or passed by the pass) that
        are already joined within two hops by odometry or final ties: with a tie
        budget, it is left out, so these ties grow with the places, not with the ways
        flown between them (the soak replay: 4,849 against 5,788 at 78,716 keyframes,
        trajectory error 0.0496 against 0.0490 m)."""
        assert self._pairs is not None and self._adjacency is not None
        if self._tie_budget <= 0.0 or ka == kb or (False, min(ka, kb), max(ka, kb)) in self._pairs:
            return False
        chains = {ord(c.char): c for c in self._chains.values()}
        for k in (ka, kb):
            c = chains.get(k >> CHAR_SHIFT)
            if c is None or (k not in self._anchors and (k & INDEX_MASK) >= c.reduce_next):
                return False

        def ties(k: int) -> set[int]:
            out: set[int] = set()
            for f in self._adjacency.get(k, ()):
                r = self._factors[f]
                if f != fid and r.factor is not None and (r.kind == "odometry" or r.final):
                    out.update(r.keys)
            out.discard(k)
            out.discard(leaving)
            return out

        near = ties(ka)
        return kb in near or not near.isdisjoint(ties(kb))

    def _fused(
        self, other: int, ka: int, kb: int, z: FloatArray, cov: FloatArray, count: int
    ) -> gtsam.BetweenFactorPose2:
        """Factor ``other`` (odometry or a final constraint, between the same two
        variables) fused with z, itself ``count`` fused measurements. A robust kernel of
        width k becomes k sqrt(n) for the n measurements in all: n agreeing residuals r
        then cost what n separate factors did (huber_k(r) n = huber_{k sqrt n}(r sqrt n)),
        where keeping k would down-weight them once sqrt(n) r passes k."""
        record = self._factors[other]
        factor = record.factor
        z1, cov1 = pose_array(factor.measured()), covariance_of(factor.noiseModel())
        if record.keys[0] != ka:  # stored the other way round: turn it
            ad = adjoint(z1)
            z1, cov1 = se2_inverse(z1), ad @ cov1 @ ad.T
        zf, covf = fuse(z1, cov1, z, cov)
        gauss = gtsam.noiseModel.Gaussian.Covariance(0.5 * (covf + covf.T))
        noise: gtsam.noiseModel.Base = gauss
        if record.kernel is not None:
            name, k = record.kernel
            kernel = getattr(gtsam.noiseModel.mEstimator, name.capitalize())
            width = k * np.sqrt(record.count + count)
            noise = gtsam.noiseModel.Robust.Create(kernel.Create(width), gauss)
        return gtsam.BetweenFactorPose2(ka, kb, pose2(zf), noise)
