"""GPS fixes waiting for the two nodes that bracket them in time (seed 000 §III-A).

A fix at ``t`` becomes a factor once its robot has nodes ``i`` and ``j = i + 1``
with ``t_i <= t <= t_j``: in practice when the first keyframe stamped at or after
the fix arrives. A fix older than the chain's first node can never be bracketed
and is dropped; so is the oldest fix when more than ``max_pending`` wait. Gaps
between fixes (outages) simply mean no factors.

Fixes are released in batches, once per ``batch_period_s`` of the robot's node
time (seed 000 feeds GPS to its periodic optimizations, once a minute): each fix
changes the whole georeferenced trajectory a little, so each iSAM2 update with a
GPS factor back-substitutes through the whole Bayes tree; batching makes that
one update per period instead of one per fix. Early on, while few fixes are in,
a batch is also due as soon as as many fixes wait as were released so far
(1, 1, 2, 4, 8, ...): the first minute gets georeferenced quickly at the cost of
a logarithmic number of extra batches.
"""

from __future__ import annotations

import bisect
import logging
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from basestation.gps_factor import interpolation_factor
from common.geometry import pose7_to_pose4, se2_compose, se2_inverse
from common.logging_setup import worth_logging
from protocol import Keyframe, RobotState

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class GpsFix:
    """One fix in the ``map`` (ENU) frame."""

    stamp: float  # s, same clock as the keyframe stamps
    enu_xy: NDArray[np.float64]  # (2,) east, north, m
    sigmas_enu: NDArray[np.float64]  # (3,) reported sigma east, north, up (eq. 4), m


@dataclass(frozen=True)
class BracketedFix:
    """A fix with the nodes around it and its interpolation factor (eq. 3)."""

    i: int
    j: int
    beta: float
    fix: GpsFix


class GpsFixQueue:
    """Pending fixes per robot; not thread-safe (the pose graph's thread)."""

    def __init__(self, max_pending: int = 1000, batch_period_s: float = 0.0) -> None:
        self._max_pending = max_pending
        self._batch_period_s = batch_period_s
        self._pending: dict[str, deque[GpsFix]] = {}
        self._last_release: dict[str, float] = {}  # node stamp of each robot's last batch
        self._released: dict[str, int] = {}  # fixes released per robot so far
        self.dropped_before_start = 0  # fixes older than the chain's first node
        self.dropped_overflow = 0  # fixes pushed out by max_pending

    def add(self, robot_id: str, fix: GpsFix) -> None:
        queue = self._pending.setdefault(robot_id, deque())
        if queue and fix.stamp < queue[-1].stamp:  # keep time order (rare: late delivery)
            items = sorted([*queue, fix], key=lambda f: f.stamp)
            queue.clear()
            queue.extend(items)
        else:
            queue.append(fix)
        while len(queue) > self._max_pending:
            queue.popleft()
            if worth_logging(self.dropped_overflow):  # (a hovering drone adds no nodes)
                logger.warning("robot %r: too many GPS fixes wait for nodes, oldest dropped "
                               "(%d so far)", robot_id, self.dropped_overflow + 1)  # fmt: skip
            self.dropped_overflow += 1

    def pending(self, robot_id: str) -> int:
        return len(self._pending.get(robot_id, ()))

    def ready(
        self, robot_id: str, node_stamps: Sequence[float], flush: bool = False
    ) -> list[BracketedFix]:
        """Pop every fix of ``robot_id`` that two nodes now bracket (stamps increasing),
        if a batch is due (``flush``: whether or not)."""
        queue = self._pending.get(robot_id)
        if not queue or len(node_stamps) == 0:
            return []
        last = self._last_release.get(robot_id)
        if not flush and last is not None and node_stamps[-1] - last < self._batch_period_s:
            waiting = bisect.bisect_right([f.stamp for f in queue], node_stamps[-1])
            if waiting < self._released.get(robot_id, 0):
                return []  # the next batch is not due yet
        out: list[BracketedFix] = []
        while queue:
            fix = queue[0]
            if fix.stamp < node_stamps[0]:
                queue.popleft()
                if worth_logging(self.dropped_before_start):
                    logger.warning("robot %r: GPS fix at t=%.3f before its first keyframe "
                                   "(t=%.3f): dropped (%d so far; if all are, its fixes "
                                   "stamp by another clock)", robot_id, fix.stamp,
                                   node_stamps[0], self.dropped_before_start + 1)  # fmt: skip
                self.dropped_before_start += 1
                continue
            if fix.stamp > node_stamps[-1] or len(node_stamps) < 2:
                break  # waits for a later node
            j = max(bisect.bisect_left(node_stamps, fix.stamp), 1)
            i = j - 1
            beta = interpolation_factor(node_stamps[i], node_stamps[j], fix.stamp)
            out.append(BracketedFix(i, j, beta, queue.popleft()))
        if out:
            self._last_release[robot_id] = node_stamps[-1]
            self._released[robot_id] = self._released.get(robot_id, 0) + len(out)
        return out


def gnss_start(
    fix_en: np.ndarray, heading: float, odom: np.ndarray, odom_now: np.ndarray | None
) -> np.ndarray:
    """A GNSS-started robot's first node [x, y, yaw] in `map` (ENU, seed 000 §III-C):
    its odom frame is turned by the autopilot's `heading` at takeoff and put so that the
    robot's latest local pose `odom_now` ([x, y, yaw]; None: the node's own, `odom`) is
    at its latest fix `fix_en`. A chain that starts on the way (a new base station: its
    first keyframe from long before) had been put at the latest fix, as far off as the
    robot had flown since."""
    now = np.asarray(odom if odom_now is None else odom_now, dtype=np.float64)
    T_map_odom = se2_compose([fix_en[0], fix_en[1], heading + now[2]], se2_inverse(now))
    return se2_compose(T_map_odom, odom)


def local_pose(state: RobotState | None) -> np.ndarray | None:
    """A robot's local pose [x, y, yaw] in its odom frame, by its latest `RobotState`."""
    return None if state is None else pose7_to_pose4(state.pose_odom)[[0, 1, 3]]


def node_stamp(stamps: dict[str, float], kf: Keyframe) -> float:
    """The keyframe's stamp, nudged past its predecessor's (in `stamps`: robot -> the
    latest node's, updated) if time went backwards (bad input must not stop the base
    station; GPS factors need increasing node stamps; past 1e12 s, 1e-6 s more is the
    same float: the next one up)."""
    last = stamps.get(kf.robot_id) if kf.seq > 0 else None
    stamp = float(kf.stamp)
    if last is not None and not stamp > last:
        logger.warning("robot %s keyframe %d: stamp %.3f not after %.3f", kf.robot_id,
                       kf.seq, stamp, last)  # fmt: skip
        stamp = max(last + 1e-6, float(np.nextafter(last, np.inf)))
    stamps[kf.robot_id] = stamp
    return stamp
