"""A fresh iSAM2 now and then for a reduced pose graph: every factor, in one batch step
linearized at the current estimate.

iSAM2 relinearizes a variable only once its step passes the threshold and re-eliminates
only the part of its Bayes tree an update touches, in an order chosen for that part (the
chains' heads last). On a reduced graph, where the reduction keeps moving factors onto a
bounded set of variables, both drift: linearization points lag behind the estimate, and
the tree holds more than one ordered in one go (COLAMD over the whole graph). A replay of
the 10-robot, 30-minute soak's database (78,716 keyframes, 3,186 variables, 11,033
factors) with a fresh iSAM2 every 1,000 new nodes: trajectory error 0.0486 m against
0.0518 m, heap 7 MB less right after a rebuild (3 MB at the end), 0.1 s a rebuild.
Only once the reduction has started: the graph is then bounded, and so is a rebuild.
Live, in the 30-minute soak, the base station's heap per keyframe was the same as without
(``basestation.isam2_rebuild_nodes``, 1000 by default; 0: never).
With ``basestation.reduce_tie_degree`` each rebuild also leaves out of iSAM2 the ties
between places past that degree (``pose_graph_sparsify``): the 30-minute soak's heap
in use then stays flat.

Package-internal: a mixin of ``basestation.pose_graph.PoseGraph``.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import gtsam
import numpy as np

from basestation.pose_graph_reduction import CHAR_SHIFT, INDEX_MASK
from basestation.pose_graph_sparsify import Tie, ties_to_drop
from basestation.pose_graph_state import PoseGraphState, pair_key
from common.errors import CollabSlamError

logger = logging.getLogger(__name__)


class RebuildMixin(PoseGraphState):
    """``rebuild`` and when the update calls it (``isam2_rebuild_nodes``)."""

    if TYPE_CHECKING:  # provided by PoseGraph
        _isam: gtsam.ISAM2
        _heads: gtsam.KeyGroupMap | None
        _anchors: set[int]
        _gps_robots: set[str]
        reduction_started: bool

    def _init_rebuild(self, every_nodes: int, tie_degree: int = 0) -> None:
        self._rebuild_every = max(int(every_nodes), 0)  # 0: never
        self._tie_degree = max(int(tie_degree), 0)  # 0: keep every tie
        self._nodes_since_rebuild = 0
        self.num_rebuilds = 0
        self.num_dormant = 0  # ties the last rebuild left out of iSAM2 (pose_graph_sparsify)

    def _after_update(self, new_nodes: int) -> None:
        """Count the new nodes; rebuild once ``every_nodes`` came since the last one."""
        if not self._rebuild_every or not self.reduction_started:
            return
        self._nodes_since_rebuild += new_nodes
        if self._nodes_since_rebuild >= self._rebuild_every:
            self.rebuild()

    def rebuild(self) -> None:
        """Replace iSAM2 by a fresh one holding the same factors (less the ties a tie
        degree leaves dormant), linearized and ordered anew at the current estimate
        (module doc). Only between updates (nothing pending); factor ids stay, their
        iSAM2 slots are renumbered."""
        if self._pending_ids or self._pending_removals:
            raise CollabSlamError("the pose graph is rebuilt between updates only")
        t0 = time.perf_counter()
        estimate = self._isam.calculateEstimate()
        records = [r for r in self._factors.values() if r.isam_index is not None or r.dormant]
        if self._tie_degree and self.reduction_started:
            self._sparsify(estimate)
        records = [r for r in records if not r.dormant]
        for record in self._factors.values():
            if record.dormant:
                record.isam_index = None
        graph = gtsam.NonlinearFactorGraph()
        for record in records:
            graph.add(record.factor)
        self._isam = gtsam.ISAM2(self._isam.params())  # the old tree goes first
        result = self._isam.update(graph, estimate, [], constrainedKeys=self._heads)
        for record, slot in zip(records, result.getNewFactorsIndices(), strict=True):
            record.isam_index = slot
        self._nodes_since_rebuild = 0
        self.num_rebuilds += 1
        ms = (time.perf_counter() - t0) * 1e3
        logger.debug("pose graph: a fresh iSAM2, %d factors, in %.0f ms", len(records), ms)

    def _refactor_with_qr(self, exc: RuntimeError, values: gtsam.Values) -> None:
        """iSAM2's Cholesky failed in an update (`exc`: a factor's covariance nearly
        singular in some direction; a corridor's odometry of variances 100 and 1e-6 m^2
        did it after 14 keyframes, and the base station stopped): a fresh iSAM2 that
        factors by QR (slower; never failed on those) takes every factor, at the estimate
        and the new nodes' guesses (`values`). With QR already: CollabSlamError."""
        params = self._isam.params()
        if params.getFactorization() == "QR":
            raise CollabSlamError(f"iSAM2 update failed, the pose graph is unusable: {exc}")
        logger.error("iSAM2's Cholesky failed (%s): the pose graph goes on with QR", exc)
        estimate = self._isam.calculateEstimate()  # (with the new nodes it took)
        estimate.insert_or_assign(values)
        pending = set(self._pending_ids)
        records = [
            r for fid, r in self._factors.items()
            if r.factor is not None and not r.dormant
            and (r.isam_index is not None or fid in pending)
        ]  # fmt: skip
        graph = gtsam.NonlinearFactorGraph()
        for record in records:
            graph.add(record.factor)
        params.setFactorization("QR")
        self._isam = gtsam.ISAM2(params)
        result = self._isam.update(graph, estimate, [], constrainedKeys=self._heads)
        for record, slot in zip(records, result.getNewFactorsIndices(), strict=True):
            record.isam_index = slot
        self.num_rebuilds += 1

    def _sparsify(self, estimate: gtsam.Values) -> None:
        """Mark ``dormant`` the ties between settled places past ``tie_degree`` per
        variable (``pose_graph_sparsify``), chosen anew from every tie, dormant or not:
        the fresh iSAM2 leaves them out. They stay in the records, so the reduction sees
        the places joined as before (its aliases and ties do not change), and one that
        takes in a new measurement (fused) is back in iSAM2 at the next update."""
        keys = np.fromiter(estimate.keys(), dtype=np.int64, count=estimate.size())
        xy = np.asarray(gtsam.utilities.extractPose2(estimate), dtype=np.float64)
        xy = xy.reshape(-1, 3)[:, :2]
        chains = {ord(c.char): (rid, c) for rid, c in self._chains.items()}

        def settled(k: int) -> bool:
            rid, chain = chains.get(k >> CHAR_SHIFT, ("", None))
            if chain is None or rid in self._gps_robots:
                return False
            return k in self._anchors or (k & INDEX_MASK) < chain.reduce_next

        records = [
            (fid, r) for fid, r in self._factors.items()
            if r.factor is not None and len(r.keys) == 2 and (r.isam_index is not None or r.dormant)
        ]  # fmt: skip
        if not records:
            return
        ends = np.searchsorted(keys, np.array([r.keys for _, r in records], np.int64))
        lengths = np.hypot(*(xy[ends[:, 0]] - xy[ends[:, 1]]).T).tolist()
        ties = [
            Tie(fid, *r.keys, length, pair_key(r) is not None and all(map(settled, r.keys)))
            for (fid, r), length in zip(records, lengths, strict=True)
        ]
        drop = set(ties_to_drop(ties, self._tie_degree))
        for fid, record in records:
            record.dormant = fid in drop
        self.num_dormant = len(drop)
