"""summary.json's per-robot figures: ATE only over a robot's segments on the map (and
this mission's), and horizontal (the height is the altimeter's)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from collabslam.summary import build_summary
from collabslam.supervisor import RUN_MARKER, clear_run_outputs
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


def test_a_folder_used_again_holds_this_missions_outputs_only(tmp_path: Path) -> None:
    """`make run` writes to runs/latest every time: an earlier mission's map history had
    given a 10 s tour the exploration's time_to_95_s, and its segment r0~2.tum (an agent
    restart) made r0's ATE 4.4 m. A folder a mission wrote into is cleared of the names
    a mission writes; a user's own folder (`--out .`) is left as it is."""
    own = tmp_path / "own"
    (own / "logs").mkdir(parents=True)
    clear_run_outputs(own)
    assert (own / "logs").is_dir() and (own / RUN_MARKER).is_file()
    run = tmp_path / "run"
    run.mkdir()
    clear_run_outputs(run)  # the first mission
    t = np.linspace(0.0, 5.0, 20)
    truth = Trajectory.from_pose4(t, np.column_stack([t, np.zeros(20), np.ones(20), 0.0 * t]))
    far = Trajectory.from_pose4(t + 9.0, np.column_stack([t, 4 + 0 * t, np.ones(20), 0.0 * t]))
    for name, traj in (("ground_truth/r0", truth), ("trajectories/r0", truth),
                       ("trajectories/r0~2", far)):  # fmt: skip
        write_tum(run / f"{name}.tum", traj)
    (run / "map_history.npz").write_bytes(b"")
    (run / "notes.txt").write_text("mine")
    robots = {"r0": {"anchored": True}}  # this run's base station mapped no r0~2
    (run / "basestation.json").write_text(json.dumps({"robots": robots}))
    r0 = build_summary(run, resolve_world("bshape"), ["r0"], 1.0)["robots"][0]
    assert r0["ate_rmse_m"] == 0.0  # the stale segment left out
    clear_run_outputs(run)  # the next mission
    assert sorted(p.name for p in run.iterdir()) == [RUN_MARKER, "notes.txt"]
