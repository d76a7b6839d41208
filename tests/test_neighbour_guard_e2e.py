"""A real drone whose scripted tour runs through another, hovering one: the
neighbour guard keeps them apart.

Simulator, base station and two agents as separate processes over loopback Zenoh
(`collabslam.launcher.Launcher`); without the guard the drones fly through each other
(the simulated lasers do not see drones).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from collabslam.launcher import Launcher, resolve_world
from common.config import load_config
from common.scenario import RobotScenario, Scenario

# rooms15's south-west room (free 2.8 m around (3.0, 3.5)): r1 hovers in its middle;
# r0 first flies round the room (~25 s, real time: the base station, whose relay the
# guard needs, is up well before), then straight through where r1 is
TOURS = {
    "r0": np.array(
        [[1.3, 3.5], [1.3, 5.2], [4.8, 5.2], [4.8, 2.2], [1.6, 2.2], [1.3, 3.5], [5.0, 3.5]]
    ),
    "r1": np.array([[3.25, 3.6]]),
}
HEADINGS = {"r0": np.pi / 2, "r1": 0.0}


def _fly(out: Path, keep_m: float) -> tuple[dict, dict[str, dict]]:
    cfg = load_config(
        overrides={
            "exploration.enabled": False,
            "agent.neighbour_keep_m": keep_m,
            "agent.neighbour_guard_tours": True,  # tours: the guard is for exploration
            # in lock-step 2 drones fly ~3.5x faster than real time: the warm-up would be
            # over before a loaded machine has the base station up (no relay needed
            # without the guard: lock-step, quicker)
            "sim.clock": "realtime" if keep_m > 0 else "lockstep",
            # below real time: agents that share two cores with other tests still fly
            # every control tick in time (at 1.0 one run under two test workers had a contact)
            "sim.rate": 0.6,
            "sim.seed": 0,
        }
    )
    robots = [
        RobotScenario(rid, np.array([*tour[0], HEADINGS[rid]]), tour) for rid, tour in TOURS.items()
    ]
    world = resolve_world("rooms15")
    scenario = Scenario(str(world.resolve()), robots, 0)
    summary = Launcher(cfg, "rooms15", 2, out, 60.0, "WARNING", scenario=scenario).run()
    agents = {rid: json.loads((out / "agents" / f"{rid}.json").read_text()) for rid in TOURS}
    return summary, agents


@pytest.mark.e2e
def test_neighbour_guard_keeps_crossing_drones_a_metre_apart(tmp_path: Path) -> None:
    summary, agents = _fly(tmp_path / "guarded", keep_m=1.1)
    sep = summary["min_robot_separation_m"]
    assert all(r["collisions"] == 0 for r in summary["robots"]), summary["robots"]
    assert sep >= 1.0 and summary["robot_contact"] is False, sep  # 1.3 m kept, less late news
    assert sum(a["guard_neighbour_ticks"] for a in agents.values()) > 0, agents
    # the same tours without the guard: they meet (so the guard made the difference)
    summary_off, agents_off = _fly(tmp_path / "unguarded", keep_m=0.0)
    assert summary_off["min_robot_separation_m"] < 0.6, summary_off
    assert sum(a["guard_neighbour_ticks"] for a in agents_off.values()) == 0
