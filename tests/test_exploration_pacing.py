"""When the base station explores: on a lock-step simulator's clock only, or by the wall
clock without one (real Zenoh, a real BaseStationNode)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from process_helpers import synthetic_keyframe

from basestation.node import BaseStationNode
from common.bus import Bus
from common.config import ZenohConfig, load_config
from common.map_io import GridMap, write_map
from common.scenario import RobotScenario, Scenario
from protocol import ClockSync


def _explore(tmp_path: Path, endpoint: str, sets: dict, clock_at_s: float | None) -> tuple:
    """(exploration steps, clock syncs answered, keyframes in the graph) of a base station
    fed two keyframes and stepped for 3 s of wall time; the simulator's clock request at
    `clock_at_s`, if any."""
    write_map(GridMap(np.zeros((100, 100), np.int8), 0.1, (-5.0, -5.0, 0.0)), tmp_path / "w.yaml")
    scenario = Scenario(str(tmp_path / "w.yaml"), [RobotScenario("r0", np.zeros(3))])
    cfg = load_config(
        overrides={
            "exploration.enabled": True,
            "exploration.period_s": 0.2,
            "basestation.map_update_period_s": 0.1,
            "basestation.constraints.enabled": False,
            "sim.sync_wait_s": 0.5,
            **sets,
        }
    )
    with Bus(ZenohConfig(listen=[endpoint]), "default") as base_bus:
        node = BaseStationNode(cfg, base_bus, scenario, lockstep=True)
        node.start()
        with Bus(ZenohConfig(connect=[endpoint]), "default") as sim_bus:
            time.sleep(0.5)
            for seq in range(2):
                step = np.array([0.2 if seq else 0.0, 0.0, 0.0])
                kf = synthetic_keyframe("r0", seq, step * seq, step)
                sim_bus.publish(sim_bus.keys.robot("r0", "keyframe"), kf)
            t0 = time.monotonic()
            while time.monotonic() - t0 < 3.0:
                node.step(timeout=0.05)
                if clock_at_s is not None and time.monotonic() - t0 >= clock_at_s:
                    sim_bus.publish(sim_bus.keys.clock("sim"), ClockSync("sim", 0.0))
                    clock_at_s = None
        graph = node.slam.graph
        nodes = graph.num_nodes("r0") if "r0" in graph.robots() else 0
        return len(node._explore_ms), node.syncs, nodes


@pytest.mark.parametrize(
    ("sets", "clock_at_s", "steps"),
    [
        ({}, None, 0),  # lock-step simulation: its clock only (none came)
        ({}, 2.0, 1),  # ... which it answers (t = 0) with one step
        ({"sim.clock": "realtime"}, None, 5),  # no lock-step: every period of wall time
        ({"sim.basestation_timeout_s": 1.5}, None, 3),  # no clock within the timeout
    ],
)  # lock-step: keyframes too are taken only when the clock asks (none: 0 in the graph)
def test_exploration_waits_for_a_lockstep_clock(
    tmp_path: Path, endpoint: str, sets: dict, clock_at_s: float | None, steps: int
) -> None:
    """A step paced by the wall clock before the lock-step simulator's first handshake
    planned on whatever scans were in and sent paths that held drones for seconds
    (bshape, 3 drones, seed 1: 18 s to 95 % instead of 10)."""
    explored, syncs, nodes = _explore(tmp_path, endpoint, sets, clock_at_s)
    assert syncs == (clock_at_s is not None)
    assert nodes == (0 if steps == 0 else 2)
    if steps <= 1:
        assert explored == steps
    else:
        assert explored >= steps
