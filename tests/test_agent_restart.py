"""End to end, real processes: a drone's agent is SIGKILLed in the middle of a
two-drone mission and restarted on its state folder (`agent.state_dir`, as systemd
restarts it). It goes on where it was: the keyframes it had not got acknowledged are
sent again, its next keyframe spans the restart in the same odometry frame, and the
base station's trajectory of the robot goes on without a break. Before, the restarted
agent began again at seq 0 in a new frame, and the base station linked its keyframes
into the old trajectory."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest
from process_helpers import TourMission, end_mission, stored_keyframes, tour_mission, wait_for

from agent.control_log import control_positions, read_control_log
from collabslam.summary import build_summary
from collabslam.supervisor import ProcessGroup
from protocol import Keyframe, decode

pytestmark = pytest.mark.e2e


def _tour_with_a_restart(tmp_path: Path, with_state: bool) -> tuple[TourMission, int, float]:
    """A two-drone tour whose r0 agent is SIGKILLed once every robot has 30 keyframes
    stored and started again 1 s later, on its state folder or afresh (none), until 40
    more of r0's are stored (as r0, or as its segment r0~2). (the mission, r0's keyframes
    stored at the kill, wall time)"""
    m = tour_mission(tmp_path)
    out, robots, db = m.out, m.robots, m.out / "base.db"

    g = ProcessGroup(out)
    t0 = time.monotonic()
    try:
        base = g.spawn("basestation", m.base(db))
        sim = g.spawn("sim", m.sim())
        agents = {r: g.spawn(r, m.agent(r, state=with_state)) for r in robots}
        wait_for(lambda: all(stored_keyframes(db, r) >= 30 for r in robots), 60,
                 "keyframes of every robot", g, [sim, *agents.values()])  # fmt: skip
        os.kill(agents["r0"].proc.pid, signal.SIGKILL)  # a crash: no drain, no outputs
        agents["r0"].proc.wait()
        before = stored_keyframes(db, "r0")
        time.sleep(1.0)
        agents["r0"] = g.spawn("r0-restarted", m.agent("r0", state=with_state))
        new = ("r0", before + 40) if with_state else ("r0~2", 40)
        wait_for(lambda: stored_keyframes(db, new[0]) >= new[1], 60,
                 "keyframes of the restarted agent", g, [sim, *agents.values()])  # fmt: skip
        end_mission(g, sim, list(agents.values()), base)
    finally:
        g.terminate_all()
    return m, before, time.monotonic() - t0


def test_a_restarted_agent_goes_on_where_it_was(tmp_path: Path) -> None:
    m, before, wall = _tour_with_a_restart(tmp_path, with_state=True)
    out, robots, db = m.out, m.robots, m.out / "base.db"
    stats = json.loads((out / "basestation.json").read_text())["robots"]["r0"]
    agent = json.loads((out / "agents" / "r0.json").read_text())  # the restarted one's
    assert not stats["another_source"] and stats["id_conflicts"] == 0
    sent = agent["keyframes_sent"]  # seqs of the whole mission, both agents'
    assert stats["keyframes_in_graph"] == sent == agent["keyframes_acked"] >= before + 40
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT seq, payload FROM keyframes WHERE robot_id = 'r0'").fetchall()
    kfs = sorted((decode(p, Keyframe) for _, p in rows), key=lambda k: k.seq)
    assert [k.seq for k in kfs] == list(range(sent)) and {k.chain for k in kfs} == {0}
    assert all(b.stamp > a.stamp for a, b in zip(kfs, kfs[1:], strict=False))
    # it went on along its tour from where it was (from the tour's first waypoint it
    # had flown into a wall and stood there, the guard holding it, for the rest)
    assert agent["guard_limited_ticks"] < 0.2 * agent["scans"]
    log = (out / "logs" / "r0-restarted.log").read_text()
    assert "resuming from" in log
    assert not (out / "state" / "r0" / "state.json").exists()  # stopped: forgotten
    summary = build_summary(out, m.world, robots, wall)
    assert summary["map_accuracy"] >= 0.95
    assert all(r["ate_rmse_m"] < 0.5 for r in summary["robots"])


@pytest.mark.parametrize("with_state", [True, False], ids=["resumed", "afresh"])
def test_a_restarted_agent_explores_on(tmp_path: Path, with_state: bool) -> None:
    """The same in an exploring team (lock-step: each step, an agent waits for what the
    base station sent it): the mission ends with the map explored and the restarted
    agent never waits for paths sent to the agent before it (it had, 10 s a step).
    Restarted afresh (no state folder), it explores on as segment r1~2, started in r1's
    frame (from one place, a hovering drone's matches could not join it to the map:
    it had hovered to the end, without a path)."""
    m = tour_mission(tmp_path, 3, "rooms15", explore=True)
    out, db = m.out, m.out / "base.db"

    g = ProcessGroup(out)
    t0 = time.monotonic()
    try:
        base = g.spawn("basestation", [*m.base(db), "--lockstep"])
        sim = g.spawn("sim", [*m.sim(), "--max-sim-time", "200"])
        agents = {r: g.spawn(r, m.agent(r, "--await-base", state=with_state)) for r in m.robots}
        wait_for(lambda: stored_keyframes(db, "r1") >= 25, 60, "keyframes of r1", g,
                 [sim, *agents.values()])  # fmt: skip
        os.kill(agents["r1"].proc.pid, signal.SIGKILL)
        agents["r1"].proc.wait()
        before = stored_keyframes(db, "r1")
        time.sleep(1.0)
        agents["r1"] = g.spawn("r1-restarted", m.agent("r1", "--await-base", state=with_state))
        g.wait([sim], 240)  # to the end of the exploration
        end_mission(g, sim, list(agents.values()), base)
    finally:
        g.terminate_all()
    summary = build_summary(out, m.world, m.robots, time.monotonic() - t0)
    assert summary["sim_end_reason"] == "robots_done"
    assert summary["map_coverage"] >= 0.95 and summary["min_robot_separation_m"] >= 1.0
    agent = json.loads((out / "agents" / "r1.json").read_text())
    assert agent["lockstep_downlink_timeouts"] == 0
    r1 = next(r for r in summary["robots"] if r["id"] == "r1")  # all its segments
    segments = json.loads((out / "basestation.json").read_text())["robot_segments"]
    if with_state:
        assert r1["keyframes_in_graph"] == r1["keyframes_sent"] > 25 and not segments
    else:
        assert r1["keyframes_in_graph"] == before + r1["keyframes_sent"]
        assert segments["r1"]["r1~2"] == agent["session"] and r1["keyframes_sent"] > 20
    assert r1["ate_rmse_m"] < 0.5


def test_an_agent_restarted_afresh_maps_on_as_a_new_segment(tmp_path: Path) -> None:
    """Restarted with no state to take up (no state folder here; or one older than
    `agent.resume_within_s`) the agent starts again at seq 0 in a session of its own: the
    base station maps it as segment r0~2, started where r0's odometry frame puts it (it
    began in flight), and it flies on from its tour's waypoint nearest to it. Before, its
    keyframes were refused as another source's, and nothing more of r0 was mapped."""
    m, _, wall = _tour_with_a_restart(tmp_path, with_state=False)
    out, robots = m.out, m.robots

    base_stats = json.loads((out / "basestation.json").read_text())
    first, second = base_stats["robots"]["r0"], base_stats["robots"]["r0~2"]
    agent = json.loads((out / "agents" / "r0.json").read_text())  # the restarted one's
    assert not first["another_source"] and not second["another_source"]
    assert second["keyframes_in_graph"] == agent["keyframes_sent"] == agent["keyframes_acked"]
    assert base_stats["robot_segments"]["r0"]["r0~2"] == agent["session"]
    assert (out / "trajectories" / "r0~2.tum").is_file()  # on the map
    log = (out / "logs" / "r0-restarted.log").read_text()
    assert "restarted in flight" in log and agent["correction_epoch"] > 0
    base_log = (out / "logs" / "basestation.log").read_text()
    assert "robot segment r0~2 starts in the odometry frame of r0" in base_log  # the prior
    assert agent["guard_limited_ticks"] < 0.2 * agent["scans"]  # flew on, not into a wall
    summary = build_summary(out, m.world, robots, wall)
    assert summary["map_accuracy"] >= 0.95
    r0 = next(r for r in summary["robots"] if r["id"] == "r0")  # both segments
    assert r0["keyframes_in_graph"] == first["keyframes_in_graph"] + agent["keyframes_sent"]
    assert all(r["ate_rmse_m"] < 0.5 for r in summary["robots"])
    # its control pose takes the placement at once: it had slid there over ~7 s from the
    # scenario's start pose, known wrong and 10 m off (9.5 m, then 6 m 2 s later)
    c = read_control_log(out / "control_poses" / "r0.csv")
    placed = np.any(c.T_map_odom_raw != c.T_map_odom_raw[0], axis=1)
    applied = control_positions(c.T_map_odom_applied, c.T_odom_base)[placed, :2]
    gt = np.loadtxt(out / "ground_truth" / "r0.tum")
    true = np.column_stack([np.interp(c.stamps[placed], gt[:, 0], gt[:, i]) for i in (1, 2)])
    assert placed.sum() > 100 and np.linalg.norm(applied - true, axis=1).max() < 0.5
