"""The agent's RobotState comes every `agent.state_period_s` of sensor time, on the same
stamps a lock-step simulator syncs the base station at (ticks x dt), over real Zenoh:
the base station's exploration step at t = 1 s sees where the drone is at 1 s."""

from __future__ import annotations

import threading
import time

import numpy as np

from agent.node import AgentNode
from agent.vehicle import NullVehicle
from common.bus import Bus
from common.config import Config, ZenohConfig
from common.geometry import pose4_to_pose7
from protocol import LaserScan, Odometry, RobotState


def test_states_stay_on_the_sync_stamps(cfg: Config, endpoint: str) -> None:
    cfg.agent.local_slam.enabled = False  # odometry integration: fast, exact local poses
    dt = 1.0 / cfg.sim.laser.rate_hz  # the simulator's tick (40 Hz)
    ticks = int(3.0 / dt)
    stamps: list[float] = []
    lock = threading.Lock()

    def on_state(msg: RobotState, key: str) -> None:
        with lock:
            stamps.append(msg.stamp)

    with (
        Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus_agent,
        Bus(ZenohConfig(connect=[endpoint]), cfg.fleet) as bus_base,
    ):
        bus_base.subscribe(bus_base.keys.robot("r0", "state"), RobotState, on_state)
        time.sleep(0.3)  # the subscription reaches the agent's session
        node = AgentNode(cfg, "r0", bus_agent, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        node.start()
        for k in range(ticks + 1):
            t = k * dt  # as the simulator stamps its ticks: 0.4 - 0.2 < 0.2 here
            pose = pose4_to_pose7([0.5 * t, 0.0, 0.0, 0.0])
            node.handle(Odometry("r0", t, pose, np.array([0.5, 0.0, 0.0, 0.0])))
            node.handle(LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, np.ones(201, np.float32)))
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            with lock:
                if stamps and stamps[-1] >= ticks * dt - 1e-9:
                    break
            time.sleep(0.01)
    with lock:
        got = np.array(stamps)
    period = cfg.agent.state_period_s
    want = np.arange(0.0, ticks * dt + 1e-9, period)
    assert len(got) == len(want), (len(got), len(want))  # one every period, none skipped
    np.testing.assert_allclose(got, want, atol=1e-9)  # every one on a multiple of it
