"""Comparing sensor stamps: sim stamps are `ticks * dt` in floating point, so a
period of 10 ticks measures 0.25 s, or 0.2499999999999999 s, or 0.2500000000000001 s."""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# s: stamps this close count as equal
STAMP_SLACK_S = 1e-6
# s: a stamp this far past the previous one is taken only once the next one follows it
MAX_STAMP_JUMP_S = 60.0
# correction epochs: a base station restarted on its database skips at most one reserved
# block (basestation.persistence.EPOCH_BLOCK, 1000)
MAX_EPOCH_JUMP = 100_000


def due(stamp: float, since: float, period_s: float) -> bool:
    """Whether `period_s` has passed from `since` to `stamp` (to `STAMP_SLACK_S`)."""
    return stamp - since >= period_s - STAMP_SLACK_S


@dataclass
class JumpGate:
    """Holds back a stamp far past the stream's last (`MAX_STAMP_JUMP_S`): taken as the
    newest, one such stamp (a driver's glitch: 1e9 s once) had every later message
    refused as going back in time, for good. It is taken when the next one follows it
    (the stream did jump: a sensor off for a while). `max_jump` in the stream's unit
    (s, or correction epochs)."""

    max_jump: float = MAX_STAMP_JUMP_S
    pending: float | None = None

    def holds(self, stamp: float, last: float | None) -> bool:
        """Whether the message stamped `stamp` (the stream's last taken: `last`) is held
        back (dropped by the caller, with a log line)."""
        p = self.pending
        follows = p is not None and p < stamp <= p + self.max_jump
        if last is None or stamp <= last + self.max_jump or follows:
            self.pending = None
            return False
        self.pending = stamp
        return True


# s: a sensor stamp this far before the latest is not a reordering but the clock's step
MAX_STAMP_BACK_S = 1.0
STEP_CONFIRM = 5  # messages in a row from the stepped-back clock before it counts


@dataclass
class ClockAgreement:
    """Names a sensor that stamps by another clock than the laser's (a driver's IMU on Unix
    time, its laser on time since boot). All of a drone's sensors must share one clock:
    an IMU far ahead became the latest stamp and every scan after it was dropped, odometry
    far ahead predicted no motion, without a word. A message that comes within
    `window_s` (wall) of the latest scan and whose stamp is more than `max_apart` (plus
    the wall time between them) from the scan's is a disagreement: counted, and an error
    line names the sensor and the offset (the first, then every 1000th); `in_a_row` such
    of one sensor in a row before any counts (a replay's log gap, a clock step back)."""

    max_apart: float = MAX_STAMP_BACK_S
    window_s: float = 0.5
    in_a_row: int = 5  # disagreements of a sensor in a row before they count (a log gap)
    disagreements: int = 0
    _scan: tuple[float, float] | None = None  # the latest scan's (stamp, wall time)
    _row: dict[str, int] = field(default_factory=dict)  # each sensor's, in a row

    def check(self, msg: Any, max_apart: float | None = None) -> bool:
        """Whether `msg` is not known to disagree with the latest scan (counted and logged
        only `in_a_row` in a row); `max_apart`: this kind's own tolerance (s)."""
        now = time.monotonic()
        kind = type(msg).__name__
        if kind == "LaserScan":
            self._scan = (msg.stamp, now)
            return True
        if self._scan is None or now - self._scan[1] > self.window_s:
            return True
        ahead = msg.stamp - self._scan[0]
        apart = self.max_apart if max_apart is None else max_apart
        if abs(ahead) <= apart + (now - self._scan[1]):
            self._row[kind] = 0
            return True
        self._row[kind] = row = self._row.get(kind, 0) + 1
        if row < self.in_a_row:  # (an unpaced replay's scan after a gap in its log)
            return False
        if self.disagreements % 1000 == 0:
            log.error("%s stamps are %.3f s %s the laser's: another clock? (all of a drone's "
                      "sensors must stamp by one clock; %d such so far)", kind, abs(ahead),
                      "ahead of" if ahead > 0 else "behind", self.disagreements + 1)  # fmt: skip
        self.disagreements += 1
        return False


@dataclass
class ScanRepeats:
    """A scan stamped like the last one used. A lock-step simulator's tick sent again
    (the same ranges) is answered again; a live driver's new scan with that stamp (stamps
    in whole seconds: a ROS stamp without its nanoseconds) is not used, and named: taken
    as a re-sent tick, 974 of 1,000 scans had been answered from a pose up to 1 s old,
    the safety guard on an old scan too, and the drone had flown 0.12 m from a wall."""

    stamp: float | None = None
    ranges: Any = None
    stale: int = 0  # new scans with the last one's stamp, not used

    def check(self, stamp: float, ranges: Any) -> str | None:
        """None: a new scan; "resent": the last one again; "stale": not used (logged)."""
        if self.stamp is None or stamp != self.stamp:
            return None
        if ranges is self.ranges or np.array_equal(ranges, self.ranges):
            return "resent"
        self.stale += 1
        if self.stale in (1, 10, 100) or self.stale % 1000 == 0:
            log.error("scan stamped %.6f like the one before: not used, the drone hovers "
                      "(%d so far; stamps must be in seconds with their fraction)", stamp,
                      self.stale)  # fmt: skip
        return "stale"

    def used(self, stamp: float, ranges: Any) -> None:
        self.stamp, self.ranges = stamp, ranges


@dataclass
class BackStepRepair:
    """A sensor clock that steps back (the host's time set back: NTP, GPS time) taken up:
    its later stamps are moved on by the step, so what is made of them (local SLAM,
    keyframes, states, commands) goes on forward. Before, every scan after the step was
    "not after the previous" and dropped for good: the agent flew blind on its last
    command, and its commands, stamped before the simulator's last, were ignored.

    All the agent's sensors share one clock. A stamp more than `max_back` before the
    latest is dropped (the caller counts it); `confirm` such in a row, each within
    `max_back` of the one before, are the clock's step: the offset then puts the first
    of them just after the latest, and from there stamps pass moved on by it. A single
    stray stamp, or one sensor stamping by another clock among good ones, never counts;
    nor does one far ahead (passed on: local SLAM's `JumpGate` holds it) until the next
    follows it.
    """

    max_back: float = MAX_STAMP_BACK_S
    confirm: int = STEP_CONFIRM
    offset: float = 0.0  # s added to every stamp
    latest: float = -float("inf")  # the latest stamp passed (moved on)
    steps: int = 0
    dropped: int = 0  # messages `take` dropped
    _back: tuple[float, ...] = ()  # raw stamps of a step not yet confirmed
    _ahead: JumpGate = field(default_factory=JumpGate)
    agreement: ClockAgreement = field(default_factory=ClockAgreement)

    def __call__(self, stamp: float) -> float | None:
        """`stamp` as the agent takes it (moved on by the offset), None: dropped."""
        t = stamp + self.offset
        if t >= self.latest - self.max_back:
            self._back = ()
            last = None if self.latest == -float("inf") else self.latest
            if not self._ahead.holds(t, last):  # one far ahead is not the latest yet
                self.latest = max(self.latest, t)
            return t
        if self._back and abs(stamp - self._back[-1]) > self.max_back:
            self._back = ()  # not the same clock as the ones before
        self._back += (stamp,)
        if len(self._back) < self.confirm:
            return None
        self.offset = self.latest + STAMP_SLACK_S - self._back[0]
        self.steps += 1
        self._back = ()
        t = stamp + self.offset
        self.latest = t
        return t

    def stats(self) -> dict[str, Any]:
        return {
            "sensor_clock_steps": self.steps,
            "sensor_clock_offset_s": self.offset,
            "sensor_messages_dropped": self.dropped,
            "sensor_clock_disagreements": self.agreement.disagreements,
        }

    def take(self, msg: Any) -> Any:
        """A sensor message on the agent's timeline: its stamp moved on by the offset
        (a copy if it changes), None if dropped; both logged."""
        steps = self.steps
        self.agreement.check(msg)
        stamp = self(msg.stamp)
        if stamp is None:
            if self.dropped % 400 == 0:  # ~10 s of scans at 40 Hz between two lines
                log.error("sensor stamp %.3f is %.3f s before the latest: dropped (%d so far)",
                          msg.stamp, self.latest - msg.stamp - self.offset,
                          self.dropped + 1)  # fmt: skip
            self.dropped += 1
            return None
        if self.steps > steps:
            log.error("the sensor clock stepped back: stamps are moved on by %.3f s from t=%.3f "
                      "(set the drone's clock by slewing, not steps: chrony's makestep at boot "
                      "only)", self.offset, msg.stamp)  # fmt: skip
        return msg if stamp == msg.stamp else dataclasses.replace(msg, stamp=stamp)
