"""GPS fixes on the pose graph: queue each fix, attach it once its nodes exist.

GPS (seed 000 §III): ``add_gps_fix`` queues a fix until the node after it exists
(nodes need stamps), then adds a ``gps_factor`` on the two nodes around it, in
batches (``gps_batch_period_s``, see ``basestation.gps_fixes``). A GPS chain starts
with a loose prior (``PoseGraph.add_robot(..., start_sigmas)``) and counts as
anchored; use QR then.

Package-internal: a mixin of ``basestation.pose_graph.PoseGraph``.
"""

from __future__ import annotations

import gtsam
import numpy as np
from numpy.typing import ArrayLike

from basestation.gps_factor import GpsWeighting, gps_noise, make_gps_factor
from basestation.gps_fixes import GpsFix, GpsFixQueue
from basestation.pose_graph_state import Chain, PoseGraphState
from common.errors import CollabSlamError


class GpsMixin(PoseGraphState):
    """GPS fix queue per robot and the GPS factors made from it."""

    def _init_gps(
        self, weighting: GpsWeighting | None, max_pending_fixes: int, batch_period_s: float
    ) -> None:
        self._gps_weighting = weighting or GpsWeighting()
        self._gps = GpsFixQueue(max_pending_fixes, batch_period_s)
        self.num_gps_factors = 0
        self.gps_dropped_reduced = 0
        self._gps_robots: set[str] = set()  # robots with fixes (their nodes are not reduced)

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
        self._gps_robots.add(robot_id)
        self._gps.add(robot_id, GpsFix(float(stamp), xy, sig))
        return self._attach_gps(robot_id)

    def gps_stats(self) -> dict[str, int]:
        """GPS factors added, fixes waiting and fixes dropped (too old, queue overflow)."""
        return {
            "gps_factors": self.num_gps_factors,
            "gps_pending": sum(self._gps.pending(r) for r in self._chains),
            "gps_dropped_before_start": self._gps.dropped_before_start,
            "gps_dropped_overflow": self._gps.dropped_overflow,
            "gps_dropped_reduced": self.gps_dropped_reduced,
        }

    def flush_gps(self) -> int:
        """Turn every bracketed fix into a factor now, batch due or not (e.g. at shutdown)."""
        return sum(self._attach_gps(robot_id, flush=True) for robot_id in self._chains)

    def _check_stamp(self, robot_id: str, chain: Chain, stamp: float | None) -> None:
        """A new node's stamp (s) must increase along the chain; None only without fixes."""
        if stamp is None:
            if chain.stamps is not None and self._gps.pending(robot_id):
                raise CollabSlamError(f"robot {robot_id!r}: GPS fixes wait, nodes need stamps")
        elif chain.stamps is not None:
            if not np.isfinite(stamp) or (len(chain.stamps) and stamp <= chain.stamps[-1, 0]):
                raise CollabSlamError(f"robot {robot_id!r}: node stamps must increase, got {stamp}")

    def _attach_gps(self, robot_id: str, flush: bool = False) -> int:
        """Add a GPS factor for each fix now due; returns how many."""
        chain = self._chains[robot_id]
        if chain.stamps is None:
            return 0
        w = self._gps_weighting
        added = 0
        for b in self._gps.ready(robot_id, chain.stamps.view()[:, 0], flush):
            if any(i < len(chain.alias_key) and chain.alias_key[i] >= 0 for i in (b.i, b.j)):
                self.gps_dropped_reduced += 1  # a fix late enough to find its nodes reduced
                continue
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
