"""End to end, real processes: a base station with `--db` is SIGKILLed in the
middle of a two-drone mission and restarted on the same database. The agents keep
flying on local SLAM meanwhile, keep their keyframes in their outboxes, and drain
them when it is back; at the end every keyframe sent is in the graph exactly once.
Replaced by one with a new database instead (a new laptop), it gets every keyframe
again: the agents send what they kept as a new keyframe chain."""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest
from process_helpers import end_mission, stored_keyframes, tour_mission, wait_for

from collabslam.summary import build_summary
from collabslam.supervisor import Child, ProcessGroup
from protocol import Keyframe, decode

pytestmark = pytest.mark.e2e


def test_basestation_killed_and_restarted_loses_nothing(tmp_path: Path) -> None:
    m = tour_mission(tmp_path)
    out, robots, db = m.out, m.robots, m.out / "base.db"
    g = ProcessGroup(out)
    t0 = time.monotonic()
    try:
        base = g.spawn("basestation", m.base(db))
        sim = g.spawn("sim", [*m.sim(), "--max-sim-time", "600"])
        agents = [g.spawn(r, m.agent(r)) for r in robots]
        for kill in range(2):  # killed and restarted once, then run on a little
            # every robot's link must be up before the kill (its loss is checked below)
            before = {r: stored_keyframes(db, r) for r in robots}
            wait_for(
                lambda b=before: all(stored_keyframes(db, r) >= b[r] + 10 for r in robots),
                60,
                "keyframes of every robot",
                g,
                [sim, *agents],
            )
            if kill == 1:
                break
            base = _kill_and_start(g, base, m.base(db), f"basestation{kill + 2}")
        end_mission(g, sim, agents, base)
    finally:
        g.terminate_all()
    wall = time.monotonic() - t0

    stats = json.loads((out / "basestation.json").read_text())
    assert stats["persistence"]["starts"] == 2
    assert stats["persistence"]["recovered"]["keyframes"] >= 20  # what it waited for
    with sqlite3.connect(db) as con:
        seqs = dict(con.execute("SELECT robot_id, group_concat(seq) FROM keyframes GROUP BY 1"))
    for r in robots:
        agent = json.loads((out / "agents" / f"{r}.json").read_text())
        sent = agent["keyframes_sent"]
        assert sent > 60
        assert stats["robots"][r]["keyframes_in_graph"] == sent == agent["keyframes_acked"]
        # stored once each, nothing missing: seqs 0..sent-1
        assert sorted(int(s) for s in seqs[r].split(",")) == list(range(sent))
        assert agent["base_station_links"]["losses"] >= 1
        log = (out / "logs" / f"{r}.log").read_text()
        held = [int(n) for n in re.findall(r"is back: resending (\d+) keyframes", log)]
        assert held and max(held) > 0, "the outbox held nothing while the base was gone"
    summary = build_summary(out, m.world, robots, wall)
    assert summary["map_accuracy"] >= 0.95
    assert all(r["ate_rmse_m"] < 0.5 for r in summary["robots"])


def _first_keyframe(db: Path, robot_id: str) -> Keyframe:
    with sqlite3.connect(db) as con:
        row = con.execute(
            "SELECT payload FROM keyframes WHERE robot_id = ? AND seq = 0", (robot_id,)
        ).fetchone()
    return decode(row[0], Keyframe)


def test_a_base_station_with_a_new_database_gets_the_whole_mission(tmp_path: Path) -> None:
    """A laptop lost with its database: the base station started in its place has none
    of the robots' keyframes. It had waited for seq 0, dropped by the agents once the
    first acked it, and mapped nothing of them; now each agent sends what it kept (its
    acknowledged keyframes are on disk) as keyframe chain 1, from its first keyframe.
    When the first laptop comes back on its older database, it follows on: its ack -1
    of chain 1 has everything sent again as chain 2, whose first keyframes it has (it
    had frozen those robots, refusing chain 1 as another source's)."""
    m = tour_mission(tmp_path)
    out, robots = m.out, m.robots
    lost, new = out / "lost.db", out / "new.db"
    g = ProcessGroup(out)
    t0 = time.monotonic()
    try:
        base = g.spawn("basestation", m.base(lost))
        sim = g.spawn("sim", m.sim())
        agents = [g.spawn(r, m.agent(r)) for r in robots]
        wait_for(lambda: all(stored_keyframes(lost, r) >= 30 for r in robots), 60,
                 "keyframes of every robot", g, [sim, *agents])  # fmt: skip
        time.sleep(1.0)  # their acks too (stored, then acked: a loaded machine once
        base = _kill_and_start(g, base, m.base(new), "basestation2")  # killed it between)
        before = {r: stored_keyframes(lost, r) for r in robots}
        wait_for(lambda: all(stored_keyframes(new, r) >= before[r] + 10 for r in robots), 60,
                 "the mission so far in the new database", g, [sim, *agents])  # fmt: skip
        chain1 = {r: _first_keyframe(new, r) for r in robots}
        in_new = {r: stored_keyframes(new, r) for r in robots}
        base = _kill_and_start(g, base, m.base(lost), "basestation3")  # the old one back
        wait_for(lambda: all(stored_keyframes(lost, r) >= in_new[r] + 10 for r in robots), 60,
                 "the mission so far in the old database", g, [sim, *agents])  # fmt: skip
        end_mission(g, sim, agents, base)
    finally:
        g.terminate_all()
    wall = time.monotonic() - t0

    stats = json.loads((out / "basestation.json").read_text())
    assert stats["persistence"]["starts"] == 2  # the old database's
    with sqlite3.connect(lost) as con:
        seqs = dict(con.execute("SELECT robot_id, group_concat(seq) FROM keyframes GROUP BY 1"))
    for r in robots:
        agent = json.loads((out / "agents" / f"{r}.json").read_text())
        # followed on with chain 1 (some of its first keyframes were still unacknowledged)
        chain = agent["keyframe_chain"]  # or with chain 2 (all sent again on its ack -1)
        assert chain in (1, 2)
        sent = agent["keyframes_sent"]  # of that chain: every keyframe cut (none dropped)
        assert stats["robots"][r]["keyframes_in_graph"] == sent == agent["keyframes_acked"]
        assert sorted(int(s) for s in seqs[r].split(",")) == list(range(sent))  # once each
        first, was = chain1[r], _first_keyframe(lost, r)
        assert (first.chain, was.chain) == (1, 0)
        assert first.stamp == was.stamp  # from the mission's first keyframe on
        np.testing.assert_array_equal(first.pose_odom, was.pose_odom)
        log = (out / "logs" / f"{r}.log").read_text()
        assert re.search(r"sending the \d+ kept as keyframe chain 1 \(0 acknowledged", log)
        again = re.search(r"sending the \d+ kept as keyframe chain 2 \(0 acknowledged", log)
        assert bool(again) == (chain == 2)
        assert stats["robots"][r]["keyframe_chain"] == chain
        assert stats["robots"][r]["chain_drops"]["conflicts"] == 0
    base_log = (out / "logs" / "basestation3.log").read_text()
    for r in robots:  # (once, or again when its ack -1 crossed a chain followed on with)
        assert re.search(rf"robot {r}: its agent sends keyframe chain \d.*followed on", base_log)
    summary = build_summary(out, m.world, robots, wall)
    assert summary["map_accuracy"] >= 0.95
    assert all(x["ate_rmse_m"] < 0.5 for x in summary["robots"])


def _kill_and_start(g: ProcessGroup, base: Child, argv: list[str], name: str) -> Child:
    """SIGKILL the base station and start `argv` in its place 2 s later (the drones
    fly on without one meanwhile)."""
    os.kill(base.proc.pid, signal.SIGKILL)
    base.proc.wait()
    time.sleep(2.0)
    return g.spawn(name, argv)
