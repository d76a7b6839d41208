"""Where an agent's sensor data comes from, behind one interface.

A source yields protocol sensor messages (`Odometry`, `Imu`, `Altimeter`,
`LaserScan`) in time order, or `None` when nothing arrived for a moment (so the
agent can do housekeeping such as resending). The agent code never knows
whether the data comes from the simulator or a live driver over Zenoh
(`ZenohSensors`) or from a replayed CARMEN log (`CarmenReplay`).
"""

from __future__ import annotations

import heapq
import logging
import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from agent.carmen_log import CarmenLaser, read_carmen
from common.bus import Bus
from common.geometry import pose4_to_pose7
from protocol import Altimeter, Imu, LaserScan, Odometry

log = logging.getLogger(__name__)


class SensorSource(Protocol):
    def messages(self, stop: threading.Event) -> Iterator[Any | None]:
        """Sensor messages in time order; None on idle; returns when the source ends."""
        ...


class ZenohSensors:
    """A drone's sensors over Zenoh (`robot/<id>/sensor/*`), from the simulator or a driver."""

    def __init__(self, bus: Bus, robot_id: str) -> None:
        self._queue: queue.Queue[Any] = queue.Queue()
        for kind, typ in (
            ("odom", Odometry),
            ("imu", Imu),
            ("altimeter", Altimeter),
            ("scan", LaserScan),
        ):
            bus.subscribe(bus.keys.sensor(robot_id, kind), typ, lambda m, k: self._queue.put(m))

    def messages(self, stop: threading.Event) -> Iterator[Any | None]:
        while not stop.is_set():
            try:
                yield self._queue.get(timeout=0.05)
            except queue.Empty:
                yield None


class CarmenReplay:
    """A CARMEN log (`.clf` / `.clf.bz2`) as a drone's sensors.

    Each laser record becomes an `Odometry` (the log's odometry pose at the scan)
    followed by a `LaserScan`. Records are re-sorted by timestamp within
    `reorder_window_s` (some classic logs, Intel among them, step back in time by
    up to ~0.9 s in file order). `segment` = (start, end) ipc times, either None.
    """

    def __init__(
        self,
        path: str | Path,
        robot_id: str,
        segment: tuple[float | None, float | None] = (None, None),
        reorder_window_s: float = 2.0,
    ) -> None:
        self.path = Path(path)
        self.robot_id = robot_id
        self.segment = segment
        self.reorder_window_s = reorder_window_s
        self.scans = 0

    def _lasers(self) -> Iterator[CarmenLaser]:
        heap: list[tuple[float, int, CarmenLaser]] = []
        n = 0
        for rec in read_carmen(self.path, *self.segment):
            if not isinstance(rec, CarmenLaser):
                continue
            heapq.heappush(heap, (rec.stamp, n, rec))
            n += 1
            while heap and heap[0][0] < rec.stamp - self.reorder_window_s:
                yield heapq.heappop(heap)[2]
        while heap:
            yield heapq.heappop(heap)[2]

    def messages(self, stop: threading.Event) -> Iterator[Any | None]:
        rid = self.robot_id
        for rec in self._lasers():
            if stop.is_set():
                return
            x, y, th = rec.odom_pose
            yield Odometry(rid, rec.stamp, pose4_to_pose7([x, y, 0.0, th]), np.zeros(4))
            yield LaserScan(
                rid, rec.stamp, rec.angle_min, rec.angle_increment, 0.0, rec.range_max, rec.ranges
            )
            self.scans += 1
        log.info("replay of %s finished: %d scans", self.path.name, self.scans)
