"""ZenohSensors, a drone's sensor topics on a real loopback Zenoh session: scans that
come before the altimeter's first reading are dropped (a keyframe would say z = 0)."""

from __future__ import annotations

import threading
import time

import numpy as np

from agent.sensor_sources import ZenohSensors
from common.bus import Bus
from common.config import ZenohConfig
from protocol import Altimeter, LaserScan


def _scan(t: float) -> LaserScan:
    return LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, np.ones(201, np.float32))


def _take(source: ZenohSensors, n: int) -> list:
    """The next ``n`` messages the source yields (None: nothing arrived for a moment)."""
    stop = threading.Event()
    out = []
    for msg in source.messages(stop):
        if msg is not None:
            out.append(msg)
        if len(out) == n:
            break
    return out


def _put(bus: Bus, kind: str, msg: object) -> None:
    bus.publish(bus.keys.sensor("r0", kind), msg)
    time.sleep(0.05)  # one topic after the other, as a reordering network delivers them


def test_scans_before_the_first_altimeter_reading_are_dropped(endpoint: str) -> None:
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        source = ZenohSensors(bus, "r0")
        _put(bus, "scan", _scan(0.0))  # overtook the reading of its own tick
        _put(bus, "altimeter", Altimeter("r0", 0.0, 1.0))
        _put(bus, "scan", _scan(0.0))  # the tick sent again
        _put(bus, "scan", _scan(0.1))
        got = _take(source, 3)
    assert [type(m).__name__ for m in got] == ["Altimeter", "LaserScan", "LaserScan"]
    assert [m.stamp for m in got] == [0.0, 0.0, 0.1]


def test_a_drone_without_altimeter_gets_its_scans_after_a_few(endpoint: str) -> None:
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        source = ZenohSensors(bus, "r0", max_scans_before_altitude=3)
        for k in range(6):
            _put(bus, "scan", _scan(0.1 * k))
        got = _take(source, 3)
    assert [round(m.stamp, 1) for m in got] == [0.3, 0.4, 0.5]
