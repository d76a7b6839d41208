"""ZenohSensors, a drone's sensor topics on a real loopback Zenoh session: scans that
come before the altimeter's first reading are dropped (a keyframe would say z = 0)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from agent import sensor_sources
from agent.sensor_sources import SensorQueue, ZenohSensors
from collabslam.supervisor import free_port
from common.bus import Bus
from common.config import ZenohConfig
from common.stamps import BackStepRepair
from protocol import Altimeter, GnssFix, LaserScan

LLA = np.array([45.81, 16.01, 160.0])
SIG = np.array([1.5, 1.5, 3.0])


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


@contextlib.contextmanager
def _base_agent_driver(got: list[float]) -> Iterator[tuple[Bus, Bus]]:
    """A base station's session (the stamps of the fixes it gets go into `got`), an
    agent's linked to it, and a driver's on the agent's listener: (agent, driver)."""
    base_ep, agent_ep = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    quiet = {"gossip_scouting": False}  # as the deploy configs: only the links configured
    with (
        Bus(ZenohConfig(listen=[base_ep], **quiet), "default") as base,
        Bus(ZenohConfig(listen=[agent_ep], connect=[base_ep], **quiet), "default") as agent,
        Bus(ZenohConfig(connect=[agent_ep], **quiet), "default") as driver,
    ):
        base.subscribe(
            base.keys.all_robots("sensor/gnss"), GnssFix, lambda m, k: got.append(m.stamp)
        )
        yield agent, driver


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


@pytest.mark.parametrize("relay", [True, False])
def test_a_drivers_gnss_fixes_reach_the_base_station_through_the_agent(relay: bool) -> None:
    """On a drone the driver talks to the agent only (tcp/127.0.0.1:7448): a Zenoh peer
    routes nothing between its links, so the base station heard no fix at all. With
    `agent.relay_gnss` the agent passes each fix on, once (its own echo is not), whatever
    its stamp (a stamp limit had stopped the relay for good at one glitch of 1e9 s)."""
    got: list[float] = []
    with _base_agent_driver(got) as (agent, driver):
        source = ZenohSensors(agent, "r0", relay_gnss=relay)
        time.sleep(1.0)  # links up
        for t in (0.0, 1e9, 1.0, 2.0):  # a glitched stamp among them (passed on as is)
            driver.publish(driver.keys.sensor("r0", "gnss"), GnssFix("r0", t, LLA, SIG))
        stop = threading.Event()
        deadline = time.monotonic() + 3.0
        for _ in source.messages(stop):
            if time.monotonic() > deadline:
                break
    assert got == ([0.0, 1e9, 1.0, 2.0] if relay else [])


def test_relayed_fixes_are_on_the_agents_timeline_and_by_the_lasers_clock() -> None:
    """After the sensor clock stepped back, the agent moves its stamps on; relayed fixes
    had kept the old timeline (the graph tied them to nodes 30 s off: 46 m RMS). A
    receiver stamping GPS time (UTC + 18 s) had bent the map 26 m without a word: its
    fixes are named and not relayed."""
    got: list[float] = []
    with _base_agent_driver(got) as (agent, driver):
        source = ZenohSensors(agent, "r0", max_scans_before_altitude=0, relay_gnss=True)
        source.clock = clock = BackStepRepair(offset=30.0)  # a step back of 30 s taken up
        time.sleep(1.0)  # links up
        for k in range(8):
            _put(driver, "scan", _scan(100.0 + 0.1 * k))
            t = 100.05 + 0.1 * k if k < 2 else 118.05 + 0.1 * k  # then on GPS time
            _put(driver, "gnss", GnssFix("r0", t, LLA, SIG))
        stop = threading.Event()
        deadline = time.monotonic() + 3.0
        for msg in source.messages(stop):
            if isinstance(msg, LaserScan):
                clock.take(msg)  # as the agent takes each scan
            if time.monotonic() > deadline:
                break
    assert [round(t, 2) for t in got] == [130.05, 130.15]
    assert source.stats()["gnss_fixes_not_relayed"] == 6
    assert clock.agreement.disagreements == 2  # named from the 5th in a row


def test_scans_lagging_behind_the_newest_are_dropped(endpoint: str) -> None:
    """Local SLAM behind its laser (a stall): the scans waiting more than
    `agent.max_scan_lag_s` of sensor time behind the newest are dropped and counted, the
    other messages kept in order (the queue had grown without end, control lagging)."""
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        source = ZenohSensors(bus, "r0", max_scans_before_altitude=0, max_scan_lag_s=1.0)
        bus.publish(bus.keys.sensor("r0", "altimeter"), Altimeter("r0", 0.0, 1.0))
        for k in range(31):  # 3 s of a 10 Hz laser, while the agent is busy
            bus.publish(bus.keys.sensor("r0", "scan"), _scan(0.1 * k))
        time.sleep(0.3)
        got = _take(source, 12)
    assert type(got[0]).__name__ == "Altimeter"
    assert [round(m.stamp, 1) for m in got[1:]] == [round(2.0 + 0.1 * k, 1) for k in range(11)]
    assert source.stats() == {"sensor_scans_dropped_lagging": 20, "sensor_messages_overflow": 0,
                              "gnss_fixes_not_relayed": 0}  # fmt: skip


def test_a_full_sensor_queue_drops_the_newest_and_counts_them() -> None:
    queue = SensorQueue("r0", max_scan_lag_s=0.0, queue_max=3)
    for k in range(5):
        queue.put(_scan(0.1 * k))
    got = [queue.get(timeout=0.01) for _ in range(4)]
    assert [round(m.stamp, 1) for m in got[:3]] == [0.0, 0.1, 0.2] and got[3] is None
    assert queue.stats()["sensor_messages_overflow"] == 2


def test_an_agent_hearing_no_sensor_says_so(endpoint: str, monkeypatch, caplog) -> None:  # noqa: ANN001
    """A driver publishing as another robot id or fleet: the agent had logged "running"
    and then nothing for good."""
    monkeypatch.setattr(sensor_sources, "SILENCE_WARN_S", 0.3)
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        source = ZenohSensors(bus, "r0")
        stop = threading.Event()
        t0 = time.monotonic()
        for _ in source.messages(stop):
            if time.monotonic() - t0 > 0.6:
                break
    assert "no sensor message on collabslam/default/robot/r0/sensor/* for 0 s" in caplog.text


def test_the_agents_own_time_on_a_message_is_no_silence(endpoint: str, monkeypatch, caplog) -> None:  # noqa: ANN001
    """In a lock-step simulation nothing comes until the agent answers: a first scan's
    15 s of compiling its kernels had it ask whether the driver was running."""
    monkeypatch.setattr(sensor_sources, "SILENCE_WARN_S", 0.3)
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        source = ZenohSensors(bus, "r0")
        source._put(Altimeter("r0", 0.0, 1.0), "")
        stop = threading.Event()
        t0 = None
        for msg in source.messages(stop):
            if msg is not None:
                time.sleep(0.5)  # working on it
                t0 = time.monotonic()
            elif t0 is not None and time.monotonic() - t0 > 0.2:
                break
    assert "no sensor message" not in caplog.text
