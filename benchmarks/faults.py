"""`collabslam bench faults`: a simulated team mission under faults, vs. the same
mission undisturbed.

Processes as in `collabslam run` (simulator, base station with `--db`, one agent
per robot), but every agent reaches the base station through its own
`simulation.link_relay.LinkRelay`, and Zenoh gossip is off everywhere so the
relays are the only way. Faults, on a wall-clock schedule after the sim clock
starts:

(a) the base station is SIGKILLed and restarted on the same database `restarts`
    times, every `restart_period_s` (each kill waits until the current one has
    recovered and serves; `base_recoveries` counts restarts that resumed);
(b) each agent's link is cut for `cut_s` (staggered starts, 8 s apart);
(c) throughout, `dup_fraction` of the keyframes are put to the base station
    again, half at once (duplicates), half 0.2-2 s late (out of order), by
    `fault_injection.Replayer` in this process;
(d) after the last restart, this process puts `malformed` bad payloads
    (`fault_injection.bad_payloads`: garbage, truncated, wrong version,
    oversized, NaN, wrong type, robot mismatch, unknown robot);
(e) the agents of the first `agent_kills` robots are SIGKILLed (10 s after the clock
    starts, 8 s apart: the first while its link is cut, keyframes unacknowledged) and
    restarted 1 s later on their state folders (`agent.state_dir`, as the systemd unit
    does): each must go on in the same trajectory (`agent_restarts`);
(f) the agents of the next `fresh_kills` robots are restarted as `systemctl restart`
    does, 4 s after their link cut ends: SIGINT (the agent sends what is unacknowledged,
    then forgets its state), and a new agent 1 s after it exited: each maps on as a new
    segment of its robot (basestation/robot_segments.py); both runs' keyframes count.

The mission ends (SIGINT to the simulator) `settle_s` after the last fault; the
undisturbed run then flies the same scenario for the same sim time, so ground
truth is identical and the maps compare. Keys: `keyframes_sent`,
`keyframes_in_graph`, `keyframes_lost` (sent and not in the graph),
`duplicates_in_graph` (graph nodes beyond the distinct seqs stored),
`base_restarts`, `malformed_injected` / `malformed_rejected`, `crashes` (a child
that died or exited non-zero unasked), `map_accuracy` and
`map_accuracy_undisturbed`.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sqlite3
import time
from pathlib import Path
from typing import Any

from basestation.robot_segments import robot_of
from benchmarks.fault_injection import Replayer, bad_payloads
from collabslam.launcher import Launcher, agent_command, make_scenario
from collabslam.summary import build_summary
from collabslam.supervisor import Child, ProcessGroup, free_ports
from common.bus import Bus, endpoint
from common.config import Config, ZenohConfig, dump_config
from common.errors import ProcessError
from common.scenario import write_scenario
from simulation.link_relay import LinkRelay
from simulation.world import resolve_world

log = logging.getLogger(__name__)


class _Mission:
    def __init__(self, cfg: Config, out: Path, world: Path, n_robots: int) -> None:
        self.cfg, self.out, self.world = cfg, out, world
        self.scenario = make_scenario(cfg, world, n_robots)
        write_scenario(out / "scenario.json", self.scenario)
        dump_config(cfg, out / "config.toml")
        self.db = out / "base.db"
        self.common = ["--config", str(out / "config.toml"), "--scenario"]
        self.common += [str(out / "scenario.json"), "--out", str(out)]
        ports = free_ports(3 + n_robots)
        self.base_port, self.sim_ep, self.tap_port = ports[0], endpoint(ports[1]), ports[2]
        self.group = ProcessGroup(out)
        self.relays = {
            r.robot_id: LinkRelay(("127.0.0.1", self.base_port), port)
            for r, port in zip(self.scenario.robots, ports[3:], strict=True)
        }
        self.base: Child | None = None
        self.restarts = 0
        self.agent_restarts = 0
        self.fresh_sent: dict[str, int] = {}  # robot -> keyframes its killed fresh run sent
        self.crashes: list[str] = []

    def spawn_base(self) -> None:
        name = "basestation" if self.base is None else f"basestation{self.restarts + 1}"
        args = ["basestation", *self.common, "--listen", endpoint(self.base_port)]
        self.base = self.group.spawn(name, [*args, "--db", str(self.db)])

    def kill_base(self) -> None:
        assert self.base is not None
        os.kill(self.base.proc.pid, signal.SIGKILL)
        self.base.proc.wait()
        self.restarts += 1

    def wait_running(self, others: list[Child]) -> None:
        """Until the current base station has recovered and serves."""
        assert self.base is not None
        path = self.out / "logs" / f"{self.base.name}.log"
        while not _log_has(path, "base station running"):
            self.watch([self.base, *others])
            time.sleep(0.2)

    def watch(self, children: list[Child]) -> None:
        """Record children that exited on their own (crashes) and raise."""
        for c in children:
            rc = c.proc.poll()
            if rc is not None:
                self.crashes.append(f"{c.name} exited with {rc}")
                raise ProcessError(self.group.died(c, rc))


def _stored(db: Path) -> dict[str, list[int]]:
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10) as con:
        rows = con.execute("SELECT robot_id, seq FROM keyframes").fetchall()
    out: dict[str, list[int]] = {}
    for r, s in rows:
        out.setdefault(r, []).append(int(s))
    return out


def _log_has(path: Path, text: str) -> bool:
    return path.is_file() and text in path.read_text()


def _sleep_until(t_end: float, m: _Mission, children: list[Child]) -> None:
    while time.monotonic() < t_end:
        m.watch(children)
        time.sleep(0.1)


def run_faulted(
    cfg: Config,
    out: Path,
    world: Path,
    n_robots: int,
    restarts: int,
    restart_period_s: float,
    cut_s: float,
    dup_fraction: float,
    malformed: int,
    settle_s: float,
    agent_kills: int = 1,
    fresh_kills: int = 1,
) -> dict[str, Any]:
    out.mkdir(parents=True, exist_ok=True)
    m = _Mission(cfg, out, world, n_robots)
    g = m.group
    injected = 0
    timeline: list[dict[str, Any]] = []
    t_start = time.monotonic()
    tap = push = replayer = None
    try:
        m.spawn_base()
        m.wait_running([])  # connect only to a listener
        tap_port = m.tap_port  # the replayer hears the agents here ...
        tap = Bus(ZenohConfig(listen=[endpoint(tap_port)], gossip_scouting=False), cfg.fleet)
        push = Bus(  # ... and puts to the base station on a separate session
            ZenohConfig(connect=[endpoint(m.base_port)], gossip_scouting=False), cfg.fleet
        )
        replayer = Replayer(tap, push, dup_fraction, lambda r: m.relays[r].is_cut, cfg.sim.seed)
        sim = g.spawn("sim", ["sim", *m.common, "--listen", m.sim_ep, "--max-sim-time", "100000"])

        def agent_args(rid: str) -> list[str]:
            eps = (m.sim_ep, m.relays[rid].endpoint, endpoint(tap_port))
            state = f"agent.state_dir={out / 'state' / rid}"
            return [*agent_command(m.common, rid, *eps), "--set", state]

        ids = m.scenario.robot_ids
        agents = [g.spawn(rid, agent_args(rid)) for rid in ids]
        sim_log = out / "logs" / "sim.log"
        deadline = time.monotonic() + 120
        while not _log_has(sim_log, "starting the"):
            m.watch([sim, *agents])
            if time.monotonic() > deadline:
                raise ProcessError("the simulator never started its clock")
            time.sleep(0.2)
        t0 = time.monotonic()
        events: list[tuple[float, str, str]] = []
        for k in range(restarts):
            events.append((8.0 + k * restart_period_s, "kill", ""))
        for i, r in enumerate(m.scenario.robots):
            events.append((6.0 + 8.0 * i, "cut", r.robot_id))
            events.append((6.0 + 8.0 * i + cut_s, "restore", r.robot_id))
        for i, rid in enumerate(ids[:agent_kills]):
            events.append((10.0 + 8.0 * i, "agent_kill", rid))
        for i, rid in enumerate(ids[agent_kills : agent_kills + fresh_kills], agent_kills):
            events.append((6.0 + 8.0 * i + cut_s + 4.0, "agent_fresh", rid))
        last = max(t for t, _, _ in events)
        events.append((max(last, 8.0 + (restarts - 1) * restart_period_s + 6.0), "inject", ""))
        events.sort()
        for t, what, who in events:
            _sleep_until(t0 + t, m, [sim, *agents, m.base])
            timeline.append({"t_s": round(time.monotonic() - t0, 1), "event": what, "robot": who})
            log.info("fault t=%.1f s: %s %s", time.monotonic() - t0, what, who)
            if what == "kill":
                m.wait_running([sim, *agents])  # kill a serving base station, not a starting one
                m.kill_base()
                time.sleep(2.0)
                m.spawn_base()
            elif what in ("agent_kill", "agent_fresh"):  # a crash, or a clean restart
                a = agents[ids.index(who)]
                if what == "agent_kill":
                    os.kill(a.proc.pid, signal.SIGKILL)
                    a.proc.wait()
                else:
                    a.proc.send_signal(signal.SIGINT)
                    g.wait_all_or_fail([a], [sim, m.base], cfg.agent.drain_timeout_s + 60)
                    # it drained and forgot its state (else the next one resumes): its sent
                    if not (out / "state" / who / "state.json").exists():
                        stats = json.loads((out / "agents" / f"{who}.json").read_text())
                        m.fresh_sent[who] = int(stats["keyframes_sent"])
                time.sleep(1.0)
                agents[ids.index(who)] = g.spawn(f"{who}-restarted", agent_args(who))
                m.agent_restarts += what == "agent_kill"
            elif what == "cut":
                m.relays[who].cut()
            elif what == "restore":
                m.relays[who].restore()
            else:
                m.wait_running([sim, *agents])  # the last base station must be up
                time.sleep(1.0)
                for key, payload, _ in bad_payloads(
                    malformed, push.keys, m.scenario.robot_ids, cfg.protocol.max_message_bytes
                ):
                    push.put_raw(key, payload)
                    injected += 1
        _sleep_until(time.monotonic() + settle_s, m, [sim, *agents, m.base])
        sim.proc.send_signal(signal.SIGINT)
        g.wait_all_or_fail([sim], [m.base, *agents], 60)
        for a in agents:
            a.proc.send_signal(signal.SIGINT)
        g.wait_all_or_fail(agents, [m.base], cfg.agent.drain_timeout_s + 60)
        m.base.proc.send_signal(signal.SIGINT)
        g.wait_all_or_fail([m.base], [], cfg.basestation.drain_timeout_s + 120)
    except ProcessError as exc:
        if not m.crashes:
            m.crashes.append(str(exc))
        log.error("faulted run: %s", exc)
    finally:
        if replayer is not None:
            replayer.close()
        g.terminate_all()
        for relay in m.relays.values():
            relay.close()
        for bus in (tap, push):
            if bus is not None:
                bus.close()
    wall = time.monotonic() - t_start
    summary = build_summary(out, world, m.scenario.robot_ids, wall)
    stats = out / "basestation.json"
    base = json.loads(stats.read_text()) if stats.is_file() else {}
    stored = _stored(m.db) if m.db.is_file() else {}
    per_robot, lost, dup_graph = {}, 0, 0
    for r in summary["robots"]:
        segments = [s for s in stored if robot_of(s) == r["id"]]  # one per run of its agent
        seqs = [s for seg in segments for s in stored[seg]]
        in_graph = r["keyframes_in_graph"]
        r["keyframes_sent"] += m.fresh_sent.get(r["id"], 0)  # both runs' (segments')
        per_robot[r["id"]] = {
            "keyframes_sent": r["keyframes_sent"],
            "keyframes_in_graph": in_graph,
            "segments": len(segments),
            "stored_contiguous": all(
                sorted(stored[seg]) == list(range(len(stored[seg]))) for seg in segments
            ),
            "duplicates_received": base.get("robots", {}).get(r["id"], {}).get("duplicates", 0),
            "keyframes_resent": r["keyframes_resent"],
            "another_source": base.get("robots", {}).get(r["id"], {}).get("another_source"),
            "ate_rmse_m": r["ate_rmse_m"],
        }
        lost += max(0, r["keyframes_sent"] - in_graph)
        distinct = sum(len(set(stored[seg])) for seg in segments)
        dup_graph += max(0, in_graph - distinct) + (len(seqs) - distinct)
    rejected = sum(base.get("rejected_messages", {}).values()) + base.get("unknown_robot_drops", 0)
    return {
        "keyframes_sent": sum(r["keyframes_sent"] for r in summary["robots"]),
        "keyframes_in_graph": sum(r["keyframes_in_graph"] for r in summary["robots"]),
        "keyframes_lost": lost,
        "duplicates_in_graph": dup_graph,
        "base_restarts": m.restarts,
        "agent_restarts": m.agent_restarts,
        "agent_fresh_restarts": len(m.fresh_sent),
        "base_recoveries": max(0, (base.get("persistence") or {}).get("starts", 1) - 1),
        "malformed_injected": injected,
        "malformed_rejected": rejected,
        "rejected_by_reason": base.get("rejected_messages", {}),
        "keyframes_duplicated": 0 if replayer is None else replayer.duplicated,
        "keyframes_reordered": 0 if replayer is None else replayer.reordered,
        "link_cuts": sum(r.cuts for r in m.relays.values()),
        "crashes": len(m.crashes),
        "crash_details": m.crashes,
        "map_accuracy": summary["map_accuracy"],
        "map_coverage": summary["map_coverage"],
        "sim_time_s": summary["sim_time_s"],
        "wall_time_s": wall,
        "robots": per_robot,
        "timeline": timeline,
    }


def run(
    cfg: Config,
    out: Path,
    data_dir: Path,
    world: str = "bshape",
    robots: int = 3,
    restarts: int = 3,
    restart_period_s: float = 15.0,
    cut_s: float = 30.0,
    dup_fraction: float = 0.1,
    malformed: int = 10000,
    settle_s: float = 10.0,
    agent_kills: int = 1,
    fresh_kills: int = 1,
) -> dict[str, Any]:
    """The faulted mission, then the undisturbed one for the same sim time."""
    cfg.exploration.enabled = False  # scripted tours: robots fly on while the base is down
    cfg.sim.tour_length_m = max(cfg.sim.tour_length_m, 2000.0)  # fly until stopped
    # On a loaded machine the base station ingests slower than 3 robots at several
    # times real time produce: at the end, agents wait for every ack (both runs), so
    # `keyframes_lost` counts losses, not a shutdown timeout.
    cfg.agent.drain_timeout_s = max(cfg.agent.drain_timeout_s, 300.0)
    cfg.zenoh.gossip_scouting = False
    cfg.protocol.max_message_bytes = min(cfg.protocol.max_message_bytes, 65536)
    world_yaml = resolve_world(world)
    faulted = run_faulted(
        cfg, out / "faulted", world_yaml, robots, restarts, restart_period_s, cut_s,
        dup_fraction, malformed, settle_s, agent_kills, fresh_kills,
    )  # fmt: skip
    sim_time = float(faulted["sim_time_s"] or 60.0)
    cfg.zenoh.gossip_scouting = True
    t0 = time.monotonic()
    undisturbed = Launcher(cfg, world, robots, out / "undisturbed", sim_time).run()
    acc, acc0 = faulted["map_accuracy"], undisturbed["map_accuracy"]
    return {
        **faulted,
        "map_accuracy_undisturbed": acc0,
        "map_accuracy_diff_pct": None if acc is None or acc0 is None else 100 * (acc - acc0) / acc0,
        "undisturbed": {
            "keyframes_sent": sum(r["keyframes_sent"] for r in undisturbed["robots"]),
            "keyframes_in_graph": sum(r["keyframes_in_graph"] for r in undisturbed["robots"]),
            "ate_rmse_m": {r["id"]: r["ate_rmse_m"] for r in undisturbed["robots"]},
            "sim_time_s": undisturbed["sim_time_s"],
            "wall_time_s": time.monotonic() - t0,
        },
        "targets_met": {
            "keyframes_lost == 0": faulted["keyframes_lost"] == 0,
            "duplicates_in_graph == 0": faulted["duplicates_in_graph"] == 0,
            "crashes == 0": faulted["crashes"] == 0,
            "map accuracy within 1 %": acc is not None
            and acc0 is not None
            and abs(acc - acc0) <= 0.01 * acc0,
        },
        "settings": {
            "world": world,
            "robots": robots,
            "restarts": restarts,
            "restart_period_s": restart_period_s,
            "cut_s": cut_s,
            "dup_fraction": dup_fraction,
            "malformed": malformed,
            "agent_kills": agent_kills,
            "fresh_kills": fresh_kills,
        },  # fmt: skip
    }
