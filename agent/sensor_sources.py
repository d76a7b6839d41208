"""Where an agent's sensor data comes from, behind one interface.

A source yields protocol sensor messages (`Odometry`, `Imu`, `Altimeter`,
`LaserScan`) in time order, or `None` when nothing arrived for a moment (so the
agent can do housekeeping such as resending). The agent code never knows
whether the data comes from the simulator or a live driver over Zenoh
(`ZenohSensors`) or from a replayed CARMEN log (`CarmenReplay`).
"""

from __future__ import annotations

import bisect
import dataclasses
import heapq
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from agent.carmen_log import (
    CarmenLaser,
    CarmenOdometry,
    carmen_time_span,
    odometry_stamps_regular,
    read_carmen,
    saturation_range_m,
)
from common.bus import Bus
from common.errors import ConfigError
from common.geometry import pose4_to_pose7, se2_between, wrap_angle
from common.stamps import BackStepRepair
from protocol import Altimeter, ClockSync, GnssFix, Imu, LaserScan, Odometry

log = logging.getLogger(__name__)


# on robot/<id>/sensor/*: ClockSync is a lock-step simulator's (agent/downlink_gate.py)
# s: a relayed fix's stamp this far from the laser's is on another clock (GPS time is
# 18 s ahead of UTC; a boot-time clock hours off); a slow link (serial NMEA, a loaded
# companion computer) delivers a fix up to ~1.5 s late, as the IMU's 1 s would refuse
FIX_MAX_APART_S = 5.0
SENSOR_MESSAGES = (Odometry, Imu, Altimeter, LaserScan, ClockSync, GnssFix)


SILENCE_WARN_S = 10.0  # s wall without a sensor message before the agent says so


class SensorSource(Protocol):
    def messages(self, stop: threading.Event) -> Iterator[Any | None]:
        """Sensor messages in time order; None on idle; returns when the source ends."""
        ...


class SensorQueue:
    """A live drone's sensor messages waiting for the agent, bounded.

    Local SLAM that falls behind its laser (a slow computer, a stall) would work through
    ever older scans, its control pose and keyframes lagging more and more, and the
    queue would grow without end. A scan waiting more than `max_scan_lag_s` of sensor
    time behind the newest scan is dropped (0: never), and past `queue_max` messages
    the newest are dropped; both counted, and logged (the first, then every 100th).
    Sensor time, not wall time: a lock-step simulator's ticks wait for the agent, so
    none is dropped there however loaded the machine is."""

    def __init__(self, robot_id: str, max_scan_lag_s: float, queue_max: int) -> None:
        self._robot_id = robot_id
        self._max_lag = max_scan_lag_s
        self._queue: queue.Queue[list[Any]] = queue.Queue(maxsize=queue_max)
        self._scans: deque[list[Any]] = deque()  # cells of the scans waiting, oldest first
        self._lock = threading.Lock()
        self.scans_dropped = 0  # behind the newest scan by more than max_scan_lag_s
        self.overflow = 0  # past queue_max

    def put(self, msg: Any) -> None:
        cell = [msg]  # a dropped scan's cell is emptied: skipped when taken
        with self._lock:
            if isinstance(msg, LaserScan):
                self._drop_lagging(msg.stamp)
            try:
                self._queue.put_nowait(cell)
            except queue.Full:
                self.overflow += 1
                if self.overflow % 100 == 1:
                    log.error("robot %s: %d sensor messages waiting: %d dropped so far (the "
                              "agent has stalled)", self._robot_id, self._queue.maxsize,
                              self.overflow)  # fmt: skip
                return
            if isinstance(msg, LaserScan):
                self._scans.append(cell)

    def _drop_lagging(self, newest: float) -> None:
        while (
            self._max_lag > 0.0
            and self._scans
            and (self._scans[0][0].stamp < newest - self._max_lag)
        ):
            self._scans.popleft()[0] = None
            self.scans_dropped += 1
            if self.scans_dropped % 100 == 1:
                log.warning("robot %s: local SLAM falls behind the laser: scans more than "
                            "%.1f s behind the newest dropped (%d so far)", self._robot_id,
                            self._max_lag, self.scans_dropped)  # fmt: skip

    def get(self, timeout: float) -> Any | None:
        """The oldest message waiting; None if none came within ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0.0:
            try:
                cell = self._queue.get(timeout=left)
            except queue.Empty:
                return None
            with self._lock:
                msg = cell[0]
                if self._scans and self._scans[0] is cell:
                    self._scans.popleft()
            if msg is not None:
                return msg
        return None

    def stats(self) -> dict[str, int]:
        return {"sensor_scans_dropped_lagging": self.scans_dropped,
                "sensor_messages_overflow": self.overflow}  # fmt: skip


class ZenohSensors:
    """A drone's sensors over Zenoh (`robot/<id>/sensor/*`), from the simulator or a driver.

    Keyframes carry the altimeter's height, so scans that come before the altimeter's
    first reading are dropped (when each topic had its own subscriber, a scan could
    overtake the reading published before it, and the first keyframe then said z = 0,
    a 1 m error in one robot's ATE in about every other `make run`; a driver may also
    start its laser first); the simulator's lock-step sends such a tick again. After
    `max_scans_before_altitude` such scans, a drone with no altimeter flies on at z = 0
    (warned once)."""

    def __init__(
        self,
        bus: Bus,
        robot_id: str,
        max_scans_before_altitude: int = 5,
        relay_gnss: bool = False,
        max_scan_lag_s: float = 1.0,
        queue_max: int = 100_000,
    ) -> None:
        self._queue = SensorQueue(robot_id, max_scan_lag_s, queue_max)
        self._robot_id = robot_id
        # GnssFix from the drone's driver on to the base station (`agent.relay_gnss`): a
        # Zenoh peer routes nothing between its links, and the base station heard none
        self._bus = bus if relay_gnss else None
        # the fixes relayed whose echo (its own subscriber hears them) has not come yet:
        # matched exactly (a stamp limit had stopped the relay for good at a glitch)
        self._relayed: deque[tuple[float, bytes]] = deque(maxlen=64)
        self.clock: BackStepRepair | None = None  # the agent's (`AgentNode.clock`), if any
        self.fixes_not_relayed = 0  # stamped by another clock than the laser's
        self._scans_waiting = max_scans_before_altitude  # left to drop; 0: pass them on
        # one subscriber for all of them: Zenoh keeps a sender's samples in order per
        # subscriber, not between two (a scan overtook the altimeter's reading of its tick)
        self._key = bus.keys.robot(robot_id, "sensor/*")
        bus.subscribe(self._key, SENSOR_MESSAGES, self._put)
        self._heard = time.monotonic()  # wall time of the last message (or the start)
        self._silence_told = 0.0  # s of silence last logged

    def _put(self, msg: Any, key: str) -> None:
        if not isinstance(msg, GnssFix) or self._bus is not None:  # (else the base's only)
            self._queue.put(msg)

    def stats(self) -> dict[str, int]:
        return {**self._queue.stats(), "gnss_fixes_not_relayed": self.fixes_not_relayed}

    def _relay(self, msg: GnssFix) -> None:
        """A driver's fix on to the base station, on the agent's timeline: stamped by the
        laser's clock, moved on by the agent's clock steps (`BackStepRepair.offset`).
        Relayed as it came, fixes had gone on the old timeline after a step back (a 30 s
        step: the graph's fixes tied to nodes 30 s off, 46 m RMS), and fixes on another
        clock (GPS time, boot time) had bent the map or been dropped without a word: such
        are named (`ClockAgreement`) and not relayed."""
        fix = (msg.stamp, msg.lla.tobytes())
        if fix in self._relayed:  # its own echo
            self._relayed.remove(fix)
            return
        if self._bus is None:
            return
        if self.clock is not None:
            if not self.clock.agreement.check(msg, FIX_MAX_APART_S):
                self.fixes_not_relayed += 1
                return
            if self.clock.offset:
                msg = dataclasses.replace(msg, stamp=msg.stamp + self.clock.offset)
        self._relayed.append((msg.stamp, msg.lla.tobytes()))
        self._bus.publish(self._bus.keys.robot(self._robot_id, "sensor/gnss"), msg)

    def _tell_silence(self) -> None:
        """No sensor message for `SILENCE_WARN_S` (then every 6x as long): a driver on
        another robot id or fleet, or not running, had left the agent idle without a
        line in any log."""
        silent = time.monotonic() - self._heard
        if silent >= max(SILENCE_WARN_S, 6.0 * self._silence_told):
            self._silence_told = silent
            log.warning("robot %s: no sensor message on %s for %.0f s: is the driver running, "
                        "with this robot id and fleet?", self._robot_id, self._key,
                        silent)  # fmt: skip

    def messages(self, stop: threading.Event) -> Iterator[Any | None]:
        self._heard = time.monotonic()  # (silence counts from here: not the start's wait)
        while not stop.is_set():
            if (msg := self._queue.get(timeout=0.05)) is None:
                self._tell_silence()
                yield None
                continue
            self._heard, self._silence_told = time.monotonic(), 0.0
            if isinstance(msg, GnssFix):
                self._relay(msg)
                yield None
                continue
            if isinstance(msg, Altimeter):
                self._scans_waiting = 0
            elif isinstance(msg, LaserScan) and self._scans_waiting > 0:
                self._scans_waiting -= 1
                if self._scans_waiting == 0:
                    log.warning("robot %s: no altimeter: keyframes at z = 0", self._robot_id)
                yield None  # dropped: no altitude for its keyframe yet
                continue
            yield msg
            # the agent's own time on it is no silence: in a lock-step simulation nothing
            # comes until it answers (a first scan's 15 s of compiling had it warn)
            self._heard = time.monotonic()


class OdometryTrack:
    """A log's ODOM records, for the odometry pose at a laser's own stamp.

    A FLASER record carries the newest odometry pose at logging time, which can be
    from up to a scan period before or after the scan (ACES: a scan 0.12 s after the
    previous one carried 0.31 s of odometry, 0.22 m, while turning); the ODOM
    records have their own stamps, so the pose at the scan's stamp is interpolated
    between the two around it (linear in x, y and the shorter way in yaw).
    """

    def __init__(self, max_gap_s: float = 1.0) -> None:
        self.max_gap_s = max_gap_s  # s: farther-apart neighbours are not interpolated
        self._stamps: list[float] = []
        self._poses: list[np.ndarray] = []

    def add(self, stamp: float, pose: np.ndarray) -> None:
        k = bisect.bisect_right(self._stamps, stamp)  # logs step back in time now and then
        self._stamps.insert(k, stamp)
        self._poses.insert(k, np.asarray(pose, dtype=np.float64))

    def forget_before(self, stamp: float) -> None:
        k = max(bisect.bisect_left(self._stamps, stamp) - 1, 0)  # keep one older record
        del self._stamps[:k], self._poses[:k]

    def at(self, stamp: float, fallback: np.ndarray) -> np.ndarray:
        """[x, y, theta] at ``stamp``; ``fallback`` without records around it."""
        k = bisect.bisect_left(self._stamps, stamp)
        if k < len(self._stamps) and self._stamps[k] == stamp:
            return self._poses[k].copy()
        if k == 0 or k == len(self._stamps):
            return np.asarray(fallback, dtype=np.float64)
        t0, t1 = self._stamps[k - 1], self._stamps[k]
        if t1 - t0 > self.max_gap_s:
            return np.asarray(fallback, dtype=np.float64)
        a = (stamp - t0) / (t1 - t0)
        p0, p1 = self._poses[k - 1], self._poses[k]
        xy = p0[:2] + a * (p1[:2] - p0[:2])
        return np.array([xy[0], xy[1], float(wrap_angle(p0[2] + a * wrap_angle(p1[2] - p0[2])))])


class CarmenReplay:
    """A CARMEN log (`.clf` / `.clf.bz2`) as a drone's sensors.

    Each laser record becomes an `Odometry` (the odometry pose at the scan's stamp,
    see `OdometryTrack` and `odometry_stamps_regular`) followed by a `LaserScan`.
    Records are re-sorted by timestamp within `reorder_window_s` (some classic logs,
    Intel among them, step back in time by up to ~0.9 s in file order). `segment` =
    (start, end) ipc times, either None. With `rate` > 0 the scans come at the log's
    pace times `rate`, the first at `start_unix` (wall clock; 0: now); 0: at once.
    """

    def __init__(
        self,
        path: str | Path,
        robot_id: str,
        segment: tuple[float | None, float | None] = (None, None),
        reorder_window_s: float = 2.0,
        rate: float = 0.0,
        start_unix: float = 0.0,
    ) -> None:
        if not (math.isfinite(rate) and rate >= 0.0):
            raise ConfigError(f"replay rate must be >= 0 (0: as fast as possible), got {rate}")
        self.rate = rate
        self.start_unix = start_unix
        self.path = Path(path)
        self.robot_id = robot_id
        self.segment = segment
        self.reorder_window_s = reorder_window_s
        self.scans = 0
        # no scan in the log or the segment: say so now, not "0 scans" at the end
        lo, hi = carmen_time_span(self.path)
        if (segment[0] is not None and segment[0] > hi) or (
            segment[1] is not None and segment[1] < lo
        ):
            raise ConfigError(
                f"segment {segment[0]}:{segment[1]} holds no scan of {self.path.name} "
                f"(its scans span {lo:.3f} to {hi:.3f} s of log time)"
            )
        # the odometry at each scan: interpolated from the ODOM records at the scan's stamp
        # where their stamps are regular, else the pose logged with the scan (OdometryTrack)
        self.odometry_at_stamps = odometry_stamps_regular(self.path)
        log.info(
            "%s: odometry at each scan %s",
            self.path.name,
            "interpolated from the ODOM records' stamps"
            if self.odometry_at_stamps
            else "as logged with the scan (ODOM stamps irregular or missing)",
        )

        # a laser that writes "no return" as a range below the log's range_max (ACES: 50 m)
        self.no_return_m = saturation_range_m(self.path)
        if self.no_return_m is not None:
            log.info("%s: readings of %.2f m (the largest, %s) taken as no return",
                     self.path.name, self.no_return_m, "a saturated laser's")  # fmt: skip

    def _lasers(self) -> Iterator[tuple[CarmenLaser, np.ndarray]]:
        """Lasers in stamp order, each with the odometry pose at its stamp."""
        heap: list[tuple[float, int, CarmenLaser]] = []
        odometry = OdometryTrack() if self.odometry_at_stamps else None
        n = 0
        for rec in read_carmen(self.path, *self.segment, drop_malformed=True):
            if isinstance(rec, CarmenOdometry):
                if odometry is not None:
                    odometry.add(rec.stamp, rec.pose)
                continue
            heapq.heappush(heap, (rec.stamp, n, rec))
            n += 1
            while heap and heap[0][0] < rec.stamp - self.reorder_window_s:
                laser = heapq.heappop(heap)[2]
                if odometry is None:
                    yield laser, laser.odom_pose
                    continue
                yield laser, odometry.at(laser.stamp, laser.odom_pose)
                odometry.forget_before(laser.stamp - self.reorder_window_s)
        while heap:
            laser = heapq.heappop(heap)[2]
            yield (
                laser,
                laser.odom_pose if odometry is None else odometry.at(laser.stamp, laser.odom_pose),
            )

    def messages(self, stop: threading.Event) -> Iterator[Any | None]:
        rid = self.robot_id
        start = self.start_unix or time.time()
        first: float | None = None
        for rec, odom_pose in self._lasers():
            if first is None:
                first = rec.stamp
                if self.rate > 0.0 and (late := time.time() - start) > 1.0:
                    log.warning("%s: the replay starts %.0f s after its start time: the "
                                "first %.0f s of log come unpaced", self.path.name, late,
                                late * self.rate)  # fmt: skip
                mount = se2_between(rec.odom_pose, rec.laser_pose)
                if np.abs(mount).max() > 1e-3:  # (the shipped logs' is zero)
                    log.warning("%s: the laser is mounted at %s from the robot (x, y, yaw): "
                                "not applied, local SLAM tracks the laser, not the robot",
                                self.path.name, np.round(mount, 3))  # fmt: skip
            if self.rate > 0.0:  # the log's own pace, `rate` times faster
                stop.wait(max(0.0, start + (rec.stamp - first) / self.rate - time.time()))
            if stop.is_set():
                return
            x, y, th = odom_pose
            yield Odometry(rid, rec.stamp, pose4_to_pose7([x, y, 0.0, th]), np.zeros(4))
            r_max = (
                rec.range_max if self.no_return_m is None else min(rec.range_max, self.no_return_m)
            )
            yield LaserScan(
                rid, rec.stamp, rec.angle_min, rec.angle_increment, 0.0, r_max, rec.ranges
            )
            self.scans += 1
        log.info("replay of %s finished: %d scans", self.path.name, self.scans)
