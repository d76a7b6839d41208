"""The pose graph's bookkeeping: chain and factor records, the state its parts share.

Package-internal: ``PoseGraph`` (``basestation.pose_graph``) is assembled from
``PoseGraphState`` and the mixins that work on it (``pose_graph_gauge``,
``pose_graph_gps``); nothing else should touch these records. Conversions from
numpy to gtsam live here too, so each part validates its inputs the same way.

Conventions as in ``basestation.pose_graph``: poses ``[x, y, yaw]`` (m, m, rad),
covariances 3x3 in the node's body frame (m^2 / rad^2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError
from common.growable import Rows, empty, grown

FloatArray = NDArray[np.float64]
FactorKind = Literal["odometry", "start", "gauge", "constraint", "gps"]  # start: known-start prior


class UpdateStats(NamedTuple):
    """What one ``PoseGraph.update`` did (a tuple: built once per update, cheaply)."""

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


class GtsamProblem(NamedTuple):
    """Package-internal snapshot for batch_solver: active committed factors and values."""

    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values


@dataclass
class Chain:
    """One robot's pose chain; node i has key ``gtsam.symbol(char, i)``."""

    char: str
    T_map_first: FloatArray | None  # known start, or None if the chain floats
    num_committed: int = 0  # nodes already inside iSAM2
    pending: list[gtsam.Pose2] = field(default_factory=list)  # initial guesses not yet inside
    gauge_factor: int | None = None  # factor id of this chain's gauge prior, if any
    start_sigmas: FloatArray | None = None  # loose start prior (GPS: virtual ENU origin)
    # node stamps (s; float64 in an array: 8 bytes a node, not a 32-byte float object each);
    # None: unstamped
    stamps: Rows | None = field(default_factory=lambda: Rows(1))
    # reduced pose graph (pose_graph_reduction): node i is an alias of variable
    # alias_key[i] (-1: its own variable) at T_anchor_node = alias_offset[i] (float32: an
    # offset is at most a few metres, 1e-7 of it is far below the map's resolution)
    alias_key: np.ndarray = field(default_factory=lambda: empty((), np.int64))
    alias_offset: np.ndarray = field(default_factory=lambda: empty((3,), np.float32))
    reduce_next: int = 1  # first node the reduction pass has not looked at
    # nodes with a loop closure or inter-robot constraint (reducing graphs only; from
    # LINK_KEYFRAMES behind reduce_next on: the reduction pass drops older ones)
    constrained: set[int] = field(default_factory=set)
    key_base: int = field(init=False)  # node i's key is key_base + i (gtsam.symbol(char, i))

    def __post_init__(self) -> None:
        self.key_base = gtsam.symbol(self.char, 0)

    @property
    def size(self) -> int:
        return self.num_committed + len(self.pending)

    def grow_aliases(self, n: int) -> None:
        """Room for ``n`` nodes in the alias arrays (new: no alias)."""
        self.alias_key = grown(self.alias_key, n, fill=-1)
        self.alias_offset = grown(self.alias_offset, n)


@dataclass(slots=True)
class FactorRecord:
    """An active factor (committed to iSAM2 or pending)."""

    factor: gtsam.NonlinearFactor | None  # None: a constraint inside one rigid cluster
    kind: FactorKind
    robots: tuple[str, str] | None = None  # the two robots of an inter-robot constraint
    isam_index: int | None = None  # slot inside iSAM2 once committed
    keys: tuple[int, ...] = ()  # the factor's variables (kept only by a reducing graph)
    final: bool = False  # a constraint that will never be removed (fused with its peers)
    kernel: tuple[str, float] | None = None  # a constraint's robust kernel and width k
    count: int = 1  # measurements fused into it (a final constraint's kernel: k sqrt(count))
    dormant: bool = False  # a tie a rebuild left out of iSAM2 (pose_graph_sparsify)


PairKey = tuple[bool, int, int]  # (final constraint, else odometry; smaller key, larger key)


def pair_key(record: FactorRecord) -> PairKey | None:
    """Where a reducing graph files a two-variable factor that may be fused with another
    between the same variables: odometry, and final constraints (each with its kind)."""
    if (record.kind != "odometry" and not record.final) or len(record.keys) != 2:
        return None
    a, b = record.keys
    return (record.final, min(a, b), max(a, b))


def vec3(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as a finite ``[x, y, yaw]`` array; CollabSlamError naming ``name`` if not."""
    arr = np.asarray(value, dtype=np.float64)
    # one sum of python floats: NaN and inf survive it (validation in plain Python leaves
    # the CPU caches to iSAM2, whose update runs right after, see pose_graph.py)
    if arr.shape != (3,) or not math.isfinite(sum(arr.tolist())):
        raise CollabSlamError(f"{name} must be a finite [x, y, yaw] array, got {value!r}")
    return arr


def gaussian_noise(covariance: ArrayLike) -> gtsam.noiseModel.Gaussian:
    """A gtsam noise model from a finite, symmetric, positive definite 3x3 covariance."""
    cov = np.asarray(covariance, dtype=np.float64)
    if cov.shape != (3, 3):
        raise CollabSlamError(f"covariance must be a finite 3x3 matrix, got shape {cov.shape}")
    (a, b, c), (d, e, f), (g, h, i) = cov.tolist()
    if not math.isfinite(a + b + c + d + e + f + g + h + i):
        raise CollabSlamError("covariance must be a finite 3x3 matrix, got NaN or inf")
    largest = max(abs(a), abs(b), abs(c), abs(d), abs(e), abs(f), abs(g), abs(h), abs(i))
    if max(abs(b - d), abs(c - g), abs(f - h)) > 1e-9 * largest:
        raise CollabSlamError("covariance must be symmetric")
    b, c, f = 0.5 * (b + d), 0.5 * (c + g), 0.5 * (f + h)
    det = a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c)
    if not (a > 0 and a * e - b * b > 0 and det > 0):  # Sylvester: leading minors > 0
        raise CollabSlamError("covariance must be positive definite")
    return gtsam.noiseModel.Gaussian.Covariance(np.array(((a, b, c), (b, e, f), (c, f, i))))


def pose2(T: FloatArray) -> gtsam.Pose2:
    """``[x, y, yaw]`` as a gtsam Pose2."""
    x, y, yaw = T.tolist()  # python floats: pybind picks the overload at once
    return gtsam.Pose2(x, y, yaw)


def pose_array(p: gtsam.Pose2) -> FloatArray:
    """A gtsam Pose2 as ``[x, y, yaw]``."""
    return np.array((p.x(), p.y(), p.theta()))


class PoseGraphState:
    """Chains and active factors, shared by ``PoseGraph`` and its mixins.

    ``PoseGraph.__init__`` sets every attribute; factors added here wait in
    ``_pending_ids`` (removals in ``_pending_removals``) until ``PoseGraph.update``.
    The next update's factor graph is built as they come (``_pending_graph``, its
    factors' ids in ``_pending_graph_ids``), as a gtsam user builds it between two
    updates; a pending factor dropped or replaced before the update makes it stale
    (``update`` then builds it again from ``_pending_ids``).
    """

    _chains: dict[str, Chain]  # registration order = key-character order
    _factors: dict[int, FactorRecord]  # active factors (committed or pending)
    _pending_ids: list[int]
    _pending_removals: list[int]  # iSAM2 slots
    _pending_graph: gtsam.NonlinearFactorGraph | None  # None: no factor since the update
    _pending_graph_ids: list[int]
    _pending_stale: bool
    _next_id: int
    _prior_noise: gtsam.noiseModel.Base  # firm prior: known starts and gauge priors
    # reducing graphs only (else None): variable -> ids of its factors, and the odometry
    # factor or the final constraint between two variables (``pair_key``), for
    # pose_graph_reduction
    _adjacency: dict[int, set[int]] | None = None
    _pairs: dict[PairKey, int] | None = None
    _num_final_ties = 0  # entries of _pairs for final constraints

    def _chain(self, robot_id: str) -> Chain:
        try:
            return self._chains[robot_id]
        except KeyError:
            raise CollabSlamError(f"unknown robot {robot_id!r}") from None

    def _add_factor(
        self,
        factor: gtsam.NonlinearFactor | None,
        kind: FactorKind,
        robots: tuple[str, str] | None = None,
    ) -> int:
        fid = self._next_id
        self._next_id += 1
        record = FactorRecord(factor, kind, robots)
        self._factors[fid] = record
        self._pending_ids.append(fid)
        self._add_pending(fid, factor)
        self._link(fid, record)
        return fid

    def _add_pending(self, factor_id: int, factor: gtsam.NonlinearFactor | None) -> None:
        if factor is None:
            return
        if self._pending_graph is None:
            self._pending_graph = gtsam.NonlinearFactorGraph()
        self._pending_graph.add(factor)
        self._pending_graph_ids.append(factor_id)

    def _drop_factor(self, factor_id: int) -> None:
        record = self._factors.pop(factor_id)
        self._unlink(factor_id, record)
        if record.isam_index is not None:
            self._pending_removals.append(record.isam_index)
        elif record.factor is not None and not record.dormant:  # pending: in the update's graph
            self._pending_stale = True

    def _replace_factor(self, factor_id: int, factor: gtsam.NonlinearFactor | None) -> None:
        """Swap an active factor for another (same id, same kind) at the next update."""
        record = self._factors[factor_id]
        self._unlink(factor_id, record)
        if record.isam_index is not None:
            self._pending_removals.append(record.isam_index)
            record.isam_index = None
            self._pending_ids.append(factor_id)
            self._add_pending(factor_id, factor)
        elif record.dormant:  # out of iSAM2 since a rebuild: it holds new information now
            record.dormant = False
            self._pending_ids.append(factor_id)
            self._add_pending(factor_id, factor)
        else:  # still pending (or inert: then one with a factor would have to be added)
            self._pending_stale = True
        record.factor = factor
        self._link(factor_id, record)

    def _link(self, factor_id: int, record: FactorRecord) -> None:
        if self._adjacency is None or record.factor is None:
            return
        record.keys = tuple(record.factor.keys())
        for key in record.keys:
            self._adjacency.setdefault(key, set()).add(factor_id)
        pair = pair_key(record)
        if pair is not None and self._pairs is not None:
            self._num_final_ties += pair[0] and pair not in self._pairs
            self._pairs[pair] = factor_id

    def _unlink(self, factor_id: int, record: FactorRecord) -> None:
        if self._adjacency is None or not record.keys:
            return
        for key in record.keys:
            fids = self._adjacency.get(key)
            if fids is not None:
                fids.discard(factor_id)
                if not fids:  # an aliased node's key: no factor left on it
                    del self._adjacency[key]
        pair = pair_key(record)
        if pair is not None and self._pairs is not None and self._pairs.get(pair) == factor_id:
            del self._pairs[pair]
            self._num_final_ties -= pair[0]
        record.keys = ()
