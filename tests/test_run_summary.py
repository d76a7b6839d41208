"""summary.json's per-robot figures: ATE only over a robot's segments on the map, and
horizontal (the height is the altimeter's)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from collabslam.summary import build_summary
from common.trajectory_io import Trajectory, write_tum
from simulation.world import resolve_world


def test_a_robot_that_never_joined_the_map_has_no_ate(tmp_path: Path) -> None:
    """A floating robot's trajectory is in its own frame: scored against the ground
    truth it had given an ATE of 4.94 m, with nothing saying it was off the map."""
    t = np.linspace(0.0, 5.0, 20)
    truth = Trajectory.from_pose4(t, np.column_stack([t, np.zeros(20), np.ones(20), np.zeros(20)]))
    off = Trajectory.from_pose4(t, np.column_stack([t - 5.0, np.ones(20), np.ones(20), 0.0 * t]))
    for rid, est in (("r0", truth), ("r1", off)):
        write_tum(tmp_path / "ground_truth" / f"{rid}.tum", truth)
        write_tum(tmp_path / "trajectories" / f"{rid}.tum", est)
    robots = {"r0": {"anchored": True, "keyframes_in_graph": 20}, "r1": {"anchored": False}}
    (tmp_path / "basestation.json").write_text(json.dumps({"robots": robots}))
    summary = build_summary(tmp_path, resolve_world("bshape"), ["r0", "r1", "r2"], 1.0)
    r0, r1, r2 = summary["robots"]
    assert r0["on_map"] and r0["ate_rmse_m"] == 0.0
    assert not r1["on_map"] and r1["ate_rmse_m"] is None
    assert not r2["on_map"] and r2["keyframes_in_graph"] == 0  # never heard of


def test_given_up_lock_step_waits_are_counted(tmp_path: Path) -> None:
    """A base station compiling its numba kernels for over a minute on a loaded machine:
    the simulator went on without it, the mission took another course (95 % at 17 s, not
    20), and only sim.log said so. The summary counts the waits given up."""
    (tmp_path / "agents").mkdir()
    sim = {"basestation_sync_timeouts": 1, "late_states": 4}
    (tmp_path / "simulator.json").write_text(json.dumps(sim))
    (tmp_path / "basestation.json").write_text(json.dumps({"clock_input_timeouts": 8}))
    (tmp_path / "agents" / "r0.json").write_text(json.dumps({"lockstep_downlink_timeouts": 2}))
    summary = build_summary(tmp_path, resolve_world("bshape"), ["r0", "r1"], 1.0)
    assert summary["lockstep_timeouts"] == 15
