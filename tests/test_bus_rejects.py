"""The bus's log of bad messages on a real loopback Zenoh session: the first few of
each kind are logged, so one kind's flood does not hide another's."""

from __future__ import annotations

import numpy as np
import pytest
from process_helpers import poll_until

from common.bus import REJECTS_LOGGED_PER_KIND, Bus
from common.config import ZenohConfig
from protocol import Altimeter, LaserScan, encode


def test_a_flood_of_one_kind_does_not_hide_another(
    endpoint: str, caplog: pytest.LogCaptureFixture
) -> None:
    """After 20 rejections of any kind nothing new had been logged: an old agent's
    states, then another robot's bad scans, dropped without a line."""
    got: list[object] = []
    bus = Bus(ZenohConfig(listen=[endpoint]), "default", max_message_bytes=5000)
    with bus, caplog.at_level("ERROR"):
        on = bus.keys.all_robots("sensor/*")
        bus.subscribe(on, (Altimeter, LaserScan), lambda m, k: got.append(m))
        key = bus.keys.sensor("r0", "altimeter")
        for _ in range(30):  # 30 of one kind: truncated payloads
            bus.put_raw(key, b"\x92\x01")
        for k in range(80):  # 80 oversized ones, each its own size: one kind too (each
            bus.put_raw(key, b"x" * (6000 + k))  # had been a kind, and filled the kinds)
        bad_scan = LaserScan("r1", 1.0, -1.0, 1e37, 0.1, 30.0, np.ones(181, np.float32))
        bus.put_raw(bus.keys.sensor("r1", "scan"), encode(bad_scan))
        bus.publish(key, Altimeter("r0", 2.0, 1.0))  # a valid one after them is taken
        assert poll_until(lambda: len(got) == 1 and sum(bus.rejected.values()) == 111)
    lines = [r.getMessage() for r in caplog.records if "dropped bad message" in r.getMessage()]
    assert len(lines) == 2 * REJECTS_LOGGED_PER_KIND + 1
    assert "one turn at most" in lines[-1]  # the other kind's, after the flood
    assert len(bus.rejected) == 3
