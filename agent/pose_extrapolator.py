"""Predicts the pose at the next scan from odometry (or constant velocity).

With odometry, the prediction is the last matched pose composed with the odometry
motion between that scan's stamp and the new scan's stamp. Odometry comes at its own
rate (an autopilot's 50-100 Hz, not the LiDAR's 10-40 Hz), so the odometry pose at a
scan stamp is interpolated between the two odometry messages around it (extrapolated
at the last velocity, for up to `MAX_EXTRAPOLATION_S`, when the scan is newer than
all of them). Without odometry, the last
velocity is held.
"""

from __future__ import annotations

import bisect
import logging

import numpy as np

from common.geometry import se2_compose, se2_inverse, wrap_angle
from common.logging_setup import worth_logging
from common.stamps import JumpGate

log = logging.getLogger(__name__)

# Odometry kept for interpolation: a few seconds at 100 Hz, more than one scan period.
MAX_ODOMETRY = 512
# A scan newer than every odometry message (odometry arrives on its own topic, and may
# come just after the scan of the same instant) gets the odometry extrapolated at the
# last velocity for up to this long (s), then held. Holding it instead would predict no
# motion for that gap, and the matcher's prior pulls toward the prediction.
MAX_EXTRAPOLATION_S = 0.5
# s: the last velocity is measured over at least this much odometry (stamped on arrival,
# two messages can be 1 ms apart with 20 ms of motion between them)
MIN_VELOCITY_BASE_S = 0.05


class PoseExtrapolator:
    def __init__(self, use_odometry: bool = True) -> None:
        self.use_odometry = use_odometry
        self._odom_t: list[float] = []  # odometry stamps, increasing
        self._odom: list[np.ndarray] = []  # odometry poses [x, y, yaw], its own frame
        self._poses: list[tuple[float, np.ndarray]] = []  # last two (stamp, T_local_base)
        self.rejected_odometry = 0
        self.stalled_predictions = 0  # scans predicted without odometry it had stopped
        self._jump = JumpGate()

    def add_odometry(self, stamp: float, pose_xyyaw: np.ndarray) -> None:
        """One odometry pose; stamps must increase (an older one is logged and dropped,
        as is one far ahead of the last until the next follows it: `JumpGate`)."""
        if self._jump.holds(stamp, self._odom_t[-1] if self._odom_t else None):
            log.error("odometry stamp %.3f is far past the previous %.3f: dropped unless "
                      "the next follows it", stamp, self._odom_t[-1])  # fmt: skip
            self.rejected_odometry += 1
            return
        if self._odom_t and stamp <= self._odom_t[-1]:
            if stamp < self._odom_t[-1]:
                if worth_logging(self.rejected_odometry):
                    log.error("odometry stamp %.3f is before the previous %.3f: dropped "
                              "(%d so far)", stamp, self._odom_t[-1],
                              self.rejected_odometry + 1)  # fmt: skip
                self.rejected_odometry += 1
            else:  # the same stamp again: the newer message wins
                self._odom[-1] = np.asarray(pose_xyyaw, dtype=np.float64)
            return
        self._odom_t.append(float(stamp))
        self._odom.append(np.asarray(pose_xyyaw, dtype=np.float64))
        keep, over = self._oldest_needed(), len(self._odom_t) - MAX_ODOMETRY
        if over > keep and self._poses:  # a laser gap: the odometry at the last pose stays
            t = self._poses[-1][0]  # (the next scan's motion is counted from there: without
            at = self.odometry_at(t)  # it, a 7 s dropout at 0.5 m/s left the pose 0.93 m off)
            del self._odom_t[: over + 1], self._odom[: over + 1]
            self._odom_t.insert(0, t)
            self._odom.insert(0, at)
        elif keep > 0 or over > 0:
            keep = max(keep, over)
            del self._odom_t[:keep], self._odom[:keep]

    def forget_odometry(self) -> None:
        """Keep only the newest odometry: the source jumped (a reset moved its frame), so
        motion is predicted from what comes after it, not across the jump."""
        del self._odom_t[:-1], self._odom[:-1]

    def _oldest_needed(self) -> int:
        """Index of the oldest odometry still needed: the last one at or before the
        newest matched pose's stamp (it brackets that stamp)."""
        last_two = self._velocity_base()  # the last velocity, to extrapolate
        if not self._poses:
            return last_two
        return min(max(0, bisect.bisect_right(self._odom_t, self._poses[-1][0]) - 1), last_two)

    def _velocity_base(self) -> int:
        n = len(self._odom_t)
        if n < 2:
            return 0
        j = bisect.bisect_right(self._odom_t, self._odom_t[-1] - MIN_VELOCITY_BASE_S) - 1
        return max(0, min(j, n - 2))

    def odometry_at(self, stamp: float) -> np.ndarray | None:
        """The odometry pose at ``stamp``: interpolated between the messages around it;
        before them the oldest; after them extrapolated at the last velocity for up to
        ``MAX_EXTRAPOLATION_S``, then the newest; None before any odometry."""
        if not self._odom_t:
            return None
        k = bisect.bisect_left(self._odom_t, stamp)
        if k == 0:
            return self._odom[0].copy()
        if k == len(self._odom_t):  # newer than all: the last odometry velocity, briefly
            if k == 1 or stamp - self._odom_t[-1] > MAX_EXTRAPOLATION_S:
                return self._odom[-1].copy()
            j = self._velocity_base()  # along the last MIN_VELOCITY_BASE_S of odometry
            t0, t1, p0, p1 = self._odom_t[j], self._odom_t[-1], self._odom[j], self._odom[-1]
            s = (stamp - t0) / (t1 - t0)
            xy = p0[:2] + s * (p1[:2] - p0[:2])
            return np.array([xy[0], xy[1], wrap_angle(p0[2] + s * wrap_angle(p1[2] - p0[2]))])
        if self._odom_t[k] == stamp:
            return self._odom[k].copy()
        t0, t1 = self._odom_t[k - 1], self._odom_t[k]
        p0, p1 = self._odom[k - 1], self._odom[k]
        s = (stamp - t0) / (t1 - t0)
        xy = p0[:2] + s * (p1[:2] - p0[:2])
        yaw = wrap_angle(p0[2] + s * wrap_angle(p1[2] - p0[2]))
        return np.array([xy[0], xy[1], yaw])

    def add_pose(self, stamp: float, pose: np.ndarray) -> None:
        self._poses = [*self._poses[-1:], (stamp, np.asarray(pose, dtype=np.float64).copy())]

    @property
    def has_pose(self) -> bool:
        return bool(self._poses)

    def predict(self, stamp: float) -> np.ndarray:
        if not self._poses:
            return np.zeros(3)
        t1, p1 = self._poses[-1]
        if self.use_odometry and self._odom_t:
            if stamp - self._odom_t[-1] <= MAX_EXTRAPOLATION_S:
                odom_then, odom_now = self.odometry_at(t1), self.odometry_at(stamp)
                return se2_compose(p1, se2_compose(se2_inverse(odom_then), odom_now))
            # odometry that stopped: the last velocity, as with none (held, it predicted
            # no motion: the matcher followed, and the pose froze while the drone flew on)
            if worth_logging(self.stalled_predictions):
                log.warning("no odometry for %.1f s: the pose goes on at its last velocity "
                            "(%d scans so far)", stamp - self._odom_t[-1],
                            self.stalled_predictions + 1)  # fmt: skip
            self.stalled_predictions += 1
        if len(self._poses) == 2:
            t0, p0 = self._poses[0]
            if t1 > t0:
                step = se2_compose(se2_inverse(p0), p1)
                return se2_compose(p1, step * ((stamp - t1) / (t1 - t0)))
        return p1.copy()
