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

import pytest
from process_helpers import stored_keyframes, wait_for

from collabslam.launcher import agent_command, make_scenario
from collabslam.summary import build_summary
from collabslam.supervisor import ProcessGroup, free_port
from common.bus import endpoint
from common.config import dump_config, load_config
from common.scenario import write_scenario
from protocol import Keyframe, decode
from simulation.world import resolve_world

pytestmark = pytest.mark.e2e


def test_a_restarted_agent_goes_on_where_it_was(tmp_path: Path) -> None:
    out = tmp_path / "run"
    cfg = load_config(
        overrides={
            "basestation.map_update_period_s": 0.5,
            "basestation.drain_timeout_s": 5.0,
            "sim.tour_length_m": 400.0,
            "exploration.enabled": False,
        }
    )
    world = resolve_world("bshape")
    scenario = make_scenario(cfg, world, 2)
    write_scenario(out / "scenario.json", scenario)
    dump_config(cfg, out / "config.toml")
    db = out / "base.db"
    common = ["--config", str(out / "config.toml"), "--scenario", str(out / "scenario.json")]
    common += ["--out", str(out)]
    base_ep, sim_ep = endpoint(free_port()), endpoint(free_port())
    robots = [r.robot_id for r in scenario.robots]

    def agent_args(rid: str) -> list[str]:
        state = f'agent.state_dir="{out / "state" / rid}"'
        return [*agent_command(common, rid, sim_ep, base_ep), "--set", state]

    g = ProcessGroup(out)
    t0 = time.monotonic()
    try:
        base_args = ["basestation", *common, "--listen", base_ep, "--db", str(db)]
        base = g.spawn("basestation", base_args)
        sim = g.spawn("sim", ["sim", *common, "--listen", sim_ep, "--connect", base_ep])
        agents = {r: g.spawn(r, agent_args(r)) for r in robots}
        wait_for(lambda: all(stored_keyframes(db, r) >= 30 for r in robots), 60,
                 "keyframes of every robot", g, [sim, *agents.values()])  # fmt: skip
        os.kill(agents["r0"].proc.pid, signal.SIGKILL)  # a crash: no drain, no outputs
        agents["r0"].proc.wait()
        before = stored_keyframes(db, "r0")
        time.sleep(1.0)
        agents["r0"] = g.spawn("r0-restarted", agent_args("r0"))
        wait_for(lambda: stored_keyframes(db, "r0") >= before + 40, 60,
                 "keyframes of the restarted agent", g, [sim, *agents.values()])  # fmt: skip
        sim.proc.send_signal(signal.SIGINT)
        g.wait([sim], 30)
        for a in agents.values():
            a.proc.send_signal(signal.SIGINT)
        g.wait(list(agents.values()), 60)
        base.proc.send_signal(signal.SIGINT)
        g.wait([base], 120)
    finally:
        g.terminate_all()
    wall = time.monotonic() - t0

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
    summary = build_summary(out, world, robots, wall)
    assert summary["map_accuracy"] >= 0.95
    assert all(r["ate_rmse_m"] < 0.5 for r in summary["robots"])
