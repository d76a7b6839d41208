"""End to end: `collabslam run` starts the simulator, the base station and the
agents as separate processes over loopback Zenoh; every keyframe sent reaches
the graph and the map agrees with the world."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from common.map_io import GridMap, read_map, write_map
from common.trajectory_io import read_tum
from simulation.world_generator import random_floor

pytestmark = pytest.mark.e2e

OUTPUTS = ["map.pgm", "map.yaml", "map.png", "config.toml", "summary.json", "scenario.json"]


def _run(args: list[str], timeout: float = 400) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "collabslam.cli", "run", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _check_run(out: Path, n_robots: int) -> dict:
    for name in OUTPUTS:
        assert (out / name).is_file(), f"missing {name}"
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["robots"]) == n_robots
    for r in summary["robots"]:
        assert r["keyframes_sent"] > 0
        assert r["keyframes_in_graph"] == r["keyframes_sent"] == r["keyframes_acked"]
        assert r["distance_m"] > 1.0
        assert r["ate_rmse_m"] is not None and r["ate_rmse_m"] < 1.0
        est = read_tum(out / "trajectories" / f"{r['id']}.tum")
        gt = read_tum(out / "ground_truth" / f"{r['id']}.tum")
        assert len(est) == r["keyframes_in_graph"] and len(gt) > 10
    assert summary["sim_time_s"] > 0 and summary["wall_time_s"] > 0
    return summary


def test_two_robots_short_tour(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = _run(
        ["--world", "bshape", "--robots", "2", "--out", str(out), "--max-sim-time", "25",
         "--set", "exploration.enabled=false"]
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    summary = _check_run(out, 2)
    assert summary["map_accuracy"] >= 0.95
    assert summary["map_coverage"] > 0.2
    m = read_map(out / "map.yaml")
    assert (m.data == 100).sum() > 100 and (m.data == 0).sum() > 1000
    # the agents stopped at the mission's end say so: a stop each at INFO, no loss warned of
    base_log = (out / "logs" / "basestation.log").read_text()
    assert "lost (liveliness" not in base_log and "silent at" not in base_log, base_log[-2000:]
    assert all(f"INFO [basestation] basestation.node: agent {r} stopped" in base_log
               for r in ("r0", "r1"))  # fmt: skip


def test_unseen_world_three_robots(tmp_path: Path) -> None:
    """A random floor plan the code never saw, written as PGM+YAML by hand."""
    world: GridMap = random_floor(seed=12345, width_m=18.0, height_m=14.0)
    write_map(world, tmp_path / "unseen" / "floor.yaml", "floor.pgm")
    out = tmp_path / "run"
    res = _run(
        [
            "--world",
            str(tmp_path / "unseen" / "floor.yaml"),
            "--robots",
            "3",
            "--out",
            str(out),
            "--max-sim-time",
            "15",
            "--set",
            "sim.seed=4",
            "--set",
            "exploration.enabled=false",
        ]
    )
    assert res.returncode == 0, res.stderr[-3000:]
    summary = _check_run(out, 3)
    assert summary["map_accuracy"] >= 0.9


def test_robots_started_far_apart_end_in_one_map(tmp_path: Path) -> None:
    """Unknown start poses: the base station knows only r0's start (it fixes `map`);
    r1 and r2 start far away, facing random ways, and must be found by global search
    and inter-robot constraints. Every ATE below is in the world frame, so a robot
    left off the map would fail it."""
    out = tmp_path / "run"
    res = _run(
        [
            "--world", "bshape", "--robots", "3", "--out", str(out),
            "--set", "sim.start_apart=true", "--set", "basestation.known_start_poses=false",
            "--set", "exploration.enabled=false",
        ],
        timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    summary = _check_run(out, 3)
    base = json.loads((out / "basestation.json").read_text())
    assert all(r["anchored"] for r in base["robots"].values()), base["robots"]
    assert base["inter_robot_constraints"] >= 2
    assert all(r["ate_rmse_m"] < 0.3 for r in summary["robots"])
    assert summary["map_accuracy"] >= 0.95


def test_autonomous_exploration_finishes(tmp_path: Path) -> None:
    """Two drones, no tours: the base station's frontier paths take them through the
    room set until no frontier is left."""
    out = tmp_path / "run"
    res = _run(
        ["--world", "rooms15", "--robots", "2", "--out", str(out), "--max-sim-time", "400"],
        timeout=600,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-3000:]
    summary = _check_run(out, 2)
    assert summary["sim_end_reason"] == "robots_done", summary
    base = json.loads((out / "basestation.json").read_text())
    assert base["exploration"]["done"] and base["exploration"]["frontiers"] == 0
    assert 0 < base["exploration"]["step_ms_p50"] <= base["exploration"]["step_ms_max"]
    assert summary["map_coverage"] >= 0.9 and summary["map_accuracy"] >= 0.95
    # exploration ran in sim time: the clock waited for every base-station step
    sim = json.loads((out / "simulator.json").read_text())
    assert base["clock_syncs"] >= 10 and sim["basestation_sync_timeouts"] == 0
    # the first handshake is at t = 0 and waits for the first keyframes: the drones have
    # their first paths then, and one is on its way (flying, or turning to a goal behind
    # it) within the first second
    assert summary["coverage_curve"][0][0] == 0.0
    acted = []
    for i in range(2):
        g = np.loadtxt(out / "ground_truth" / f"r{i}.tum")
        a, b = g[0], g[g[:, 0] <= g[0, 0] + 1.0][-1]
        yaw = [2.0 * np.arctan2(q[6], q[7]) for q in (a, b)]  # level flight: about z
        acted.append(np.hypot(*(b[1:3] - a[1:3])) > 0.2 or abs(np.sin(yaw[1] - yaw[0])) > 0.2)
    assert any(acted), acted
    assert summary["time_to_95_s"] is not None and summary["time_to_95_s"] <= summary["sim_time_s"]
    assert all(r["collisions"] == 0 for r in summary["robots"]), summary["robots"]
    assert summary["min_robot_separation_m"] > 0.5  # the drones' discs never touched
    # each path a DEBUG line (43 of the 51 INFO lines of `make run` before), no loss at the end
    base_log = (out / "logs" / "basestation.log").read_text()
    assert " INFO " in base_log and not re.search(r" INFO .*: path \d+ for ", base_log)
    assert "exploration over for" in base_log and "lost (liveliness" not in base_log


def test_dead_child_is_named(tmp_path: Path) -> None:
    """A child that dies stops the run with an error naming it, and the others are
    stopped as at a mission's end: their outputs are written (they had been killed, and
    every output of the mission lost)."""
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "collabslam.cli",
            "run",
            "--world",
            "rooms15",
            "--robots",
            "1",
            "--out",
            str(out),
            "--max-sim-time",
            "300",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        pid = None
        deadline = time.monotonic() + 60
        while pid is None and time.monotonic() < deadline:
            log = out / "logs" / "r0.log"
            if log.is_file() and "running" in log.read_text():
                found = subprocess.run(
                    ["pgrep", "-f", "--", f"{out}.*--robot-id r0"], capture_output=True, text=True
                ).stdout.split()
                pid = int(found[0]) if found else None
            time.sleep(0.2)
        assert pid is not None, "agent r0 never started"
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1
    assert "r0" in err and "exited with code" in err
    for name in ("ground_truth/r0.tum", "basestation.json", "simulator.json", "summary.json"):
        assert (out / name).is_file(), name


def test_bad_world_is_one_clear_error(tmp_path: Path) -> None:
    res = _run(["--world", "no-such-world", "--robots", "1", "--out", str(tmp_path)], 60)
    assert res.returncode == 1
    assert "unknown world 'no-such-world'" in res.stderr
    assert "Traceback" not in res.stderr
