"""`collabslam bench security`: the base station under the secure deploy config, attacked.

A real `collabslam basestation` process runs with the Zenoh config that
`deploy/make_zenoh_configs.py` would write (mutual TLS listener on
`tls/127.0.0.1:<port>`, access control keyed by certificate common name), in router
mode so that it would forward traffic between robots if the rules allowed it.
Certificates are made at run time by `deploy/make_certs.sh` (fleet CA with r0, r1 and
r9; a second, unrelated CA with its own r0). Robots r0 and r1 connect through our
`Bus` with their robot configs and stream real `Keyframe` messages; they must all
be acknowledged and end up in the graph (`legitimate_ok`). When the shared Intel
log is there, a real `collabslam agent` process (robot r2, its own certificate)
also replays its first `agent_seconds` through the secure link, and every keyframe
it sends must be acknowledged (`agent_process`).

Attempts (each `rejected` is decided by what the base station or the robots saw):

- `client_without_certificate`: a client that trusts the fleet CA but has no client
  certificate. Rejected if the TLS handshake fails (Zenoh refuses to open the session).
- `certificate_from_other_ca`: a client presenting "r0" signed by another CA.
  Rejected if the session cannot open.
- `robot_A_publishes_keyframes_as_robot_B`: r0 puts keyframes (robot_id r1, r1's next
  seqs) on r1's keyframe key. Rejected if r1's ack never moves past its own keyframes
  and the base station's graph holds exactly r1's own keyframes at the end.
- `robot_A_subscribes_to_robot_B_paths`: r0 subscribes to everything under
  `robot/r1/**` (r1's keyframes and its ack/correction/goal/path downlink) from the
  start. Rejected if r0 gets no sample while r1 receives its acks and corrections.
- `unlisted_robot_certificate`: a valid fleet certificate (CN r9) that no ACL policy
  names publishes keyframes on its own key. Rejected if the base station never saw
  them (its unknown-robot counter stays 0; r9 is not in the scenario roster).
"""

from __future__ import annotations

import json
import logging
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agent.carmen_log import read_carmen
from benchmarks.security_clients import SecureRobot, make_certs, port_open, try_open, wait_for
from collabslam.supervisor import ProcessGroup, free_port
from common.config import Config
from common.errors import CollabSlamError
from common.scenario import RobotScenario, Scenario, write_scenario
from common.zenoh_security import basestation_config, robot_config, write_json5

log = logging.getLogger(__name__)
ROBOTS = ("r0", "r1")  # the legitimate robots driven by this process
AGENT_ROBOT = "r2"  # a real `collabslam agent` process, when the log is there
AGENT_LOG = Path("carmen") / "intel.clf.bz2"


@dataclass
class _Setup:
    """Certificates, configs and the scenario of one bench run, under `work`."""

    work: Path
    port: int
    certs: Path
    other_ca: Path
    base_file: Path
    robot_files: dict[str, Path]

    @property
    def endpoint(self) -> str:
        return f"tls/127.0.0.1:{self.port}"


def _setup(work: Path, fleet: str, legit: list[str], access_control: bool) -> _Setup:
    certs = make_certs(work / "certs", [*legit, "r9"])
    other = make_certs(work / "other_ca", ["r0"], ca_name="another CA")
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    zdir = work / "zenoh"
    base_conf = basestation_config(certs, fleet, legit, [ep])
    base_conf["access_control"]["enabled"] = access_control
    files = {r: write_json5(robot_config(certs, r, [ep]), zdir / f"{r}.json5") for r in legit}
    files["r9"] = write_json5(robot_config(certs, "r9", [ep]), zdir / "r9.json5")
    starts = [RobotScenario(r, np.array([0.0, 3.0 * i, 0.0])) for i, r in enumerate(legit)]
    write_scenario(work / "scenario.json", Scenario("none", starts))
    return _Setup(
        work, port, certs, other, write_json5(base_conf, zdir / "basestation.json5"), files
    )


def _agent_args(st: _Setup, fleet: str, log_path: Path, seconds: float) -> list[str]:
    """`collabslam agent` replaying the first `seconds` of a CARMEN log as robot r2."""
    first = next(iter(read_carmen(log_path))).stamp
    return [
        "agent", "--robot-id", AGENT_ROBOT,
        "--replay", str(log_path), "--segment", f"{first}:{first + seconds}",
        "--zenoh-config", str(st.robot_files[AGENT_ROBOT]),
        "--out", str(st.work / f"agent-{AGENT_ROBOT}"),
        "--set", f"fleet={fleet}",
    ]  # fmt: skip


def run(
    cfg: Config,
    out_prefix: Path,
    data_dir: Path,
    keyframes: int = 5,
    base_mode: str = "router",
    access_control: bool = True,
    agent_seconds: float = 45.0,
) -> dict[str, Any]:
    """Run the attacks against a secure base station; returns the bench JSON.

    With `data_dir/carmen/intel.clf.bz2` present (and `agent_seconds` > 0), a real
    `collabslam agent` process (robot r2, its own certificate) replays the log's first
    `agent_seconds` through the same secure link; all its keyframes must be acked.
    `access_control=False` (a control run, not a CLI option) keeps mTLS but turns the
    ACL off: the robot-level attempts must then succeed, showing the checks can fail.
    """
    work = Path(out_prefix)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    log_path = Path(data_dir) / AGENT_LOG
    with_agent = agent_seconds > 0 and log_path.is_file()
    legit_ids = [*ROBOTS, AGENT_ROBOT] if with_agent else list(ROBOTS)
    st = _setup(work, cfg.fleet, legit_ids, access_control)
    ep = st.endpoint
    group = ProcessGroup(work)
    base = group.spawn(
        "basestation",
        [
            "basestation",
            "--out", str(work / "basestation"),
            "--scenario", str(work / "scenario.json"),
            "--zenoh-config", str(st.base_file),
            "--set", f"fleet={cfg.fleet}",
            "--set", f"zenoh.mode={base_mode}",
        ],
    )  # fmt: skip
    attempts: list[dict[str, Any]] = []
    robots: dict[str, SecureRobot] = {}
    agent = None
    try:
        if not wait_for(lambda: port_open(st.port), 60.0):
            group.check([base])
            raise CollabSlamError(f"the base station never listened on {ep}")
        log.info("base station listening after %.1f s", time.monotonic() - t0)
        if with_agent:
            agent = group.spawn("agent-r2", _agent_args(st, cfg.fleet, log_path, agent_seconds))
        robots = {r: SecureRobot(r, st.robot_files[r], cfg.fleet) for r in ROBOTS}
        r0, r1 = robots["r0"], robots["r1"]
        # Robot A's spy: its own session (another process holding r0's certificate).
        spy = SecureRobot("r0", st.robot_files["r0"], cfg.fleet)
        robots["r0-spy"] = spy
        spied: list[str] = []
        spy.bus.session.declare_subscriber(
            f"{spy.bus.keys.root}/robot/r1/**", lambda s: spied.append(str(s.key_expr))
        )  # undeclared when the spy's session closes
        for r in robots.values():
            if not r.base_alive.wait(60.0):
                group.check([base])
                raise CollabSlamError(f"robot {r.rid} never saw the secure base station alive")
        log.info("robots connected after %.1f s", time.monotonic() - t0)
        # Legitimate traffic: every keyframe acknowledged.
        for r in (r0, r1):
            r.send(range(keyframes))
        acked = wait_for(lambda: all(r.last_ack() == keyframes - 1 for r in (r0, r1)), 30.0)

        # Unauthenticated or foreign-CA clients (each trusts the fleet CA as server).
        ca = {"root_ca_certificate": str(st.certs / "ca.pem")}
        err = try_open({"connect": {"endpoints": [ep]}, "transport": {"link": {"tls": ca}}})
        attempts.append(_attempt("client_without_certificate", err is not None, err or "opened"))
        foreign = robot_config(st.other_ca, "r0", [ep])
        foreign["transport"]["link"]["tls"].update(ca)
        err = try_open(foreign)
        attempts.append(_attempt("certificate_from_other_ca", err is not None, err or "opened"))

        # r0 forges r1's next keyframes on r1's key; an unlisted certificate publishes.
        r0.send(range(keyframes, keyframes + 3), robot="r1", x0=50.0)
        r9 = SecureRobot("r9", st.robot_files["r9"], cfg.fleet)
        r9_connected = wait_for(r9.connected, 10.0)  # its TLS handshake succeeds...
        r9.send(range(3))  # ...but it is no ACL subject: it may not even see the base
        # r1 keeps going: its downlink keeps flowing while r0's spy listens.
        r1.send(range(keyframes, keyframes + 2))
        r1_more = wait_for(lambda: r1.last_ack() >= keyframes + 1, 20.0)
        time.sleep(1.0)  # any forged/spied sample in flight arrives by now
        r9.bus.close()
        r1_acks_ok = max(r1.acks, default=-1) <= keyframes + 1
        spy_ok = not spied and r1.corrections > 0 and r1_more
        if agent is not None:
            group.wait([agent], 120.0)  # it ends by itself: replay done, outbox drained
        log.info("attempts done after %.1f s", time.monotonic() - t0)
    finally:
        for r in robots.values():
            r.bus.close()
        if base.proc.poll() is None:
            base.proc.send_signal(signal.SIGINT)
        try:
            base.proc.wait(60)
        except subprocess.TimeoutExpired:
            pass
        group.terminate_all()
    if base.proc.returncode != 0:
        raise CollabSlamError(group.died(base, base.proc.returncode))
    stats = json.loads((work / "basestation" / "basestation.json").read_text())
    in_graph = {r: stats["robots"].get(r, {}).get("keyframes_in_graph", 0) for r in legit_ids}
    attempts.append(
        _attempt(
            "robot_A_publishes_keyframes_as_robot_B",
            r1_acks_ok and in_graph["r1"] == keyframes + 2,
            f"r1 acked up to {r1.last_ack()}; {in_graph['r1']} r1 keyframes in graph",
        )
    )
    attempts.append(
        _attempt(
            "robot_A_subscribes_to_robot_B_paths",
            spy_ok,
            f"r0 got {len(spied)} samples of r1's keys, r1 {r1.corrections} corrections",
        )
    )
    drops = stats["unknown_robot_drops"]
    attempts.append(
        _attempt(
            "unlisted_robot_certificate",
            r9_connected and drops == 0 and "r9" not in stats["robots"],
            f"r9 connected: {r9_connected}; base station unknown-robot drops: {drops}",
        )
    )
    legit = acked and r1_more and in_graph["r0"] == keyframes and in_graph["r1"] == keyframes + 2
    result: dict[str, Any] = {"attempts": attempts}
    if with_agent:
        a = json.loads(
            (work / f"agent-{AGENT_ROBOT}" / "agents" / f"{AGENT_ROBOT}.json").read_text()
        )
        sent, acked_n = a["keyframes_sent"], a["keyframes_acked"]
        legit = legit and sent > 0 and acked_n == sent == in_graph[AGENT_ROBOT]
        result["agent_process"] = {
            "robot": AGENT_ROBOT,
            "keyframes_sent": sent,
            "keyframes_acked": acked_n,
        }
    return result | {
        "legitimate_ok": bool(legit),
        "all_rejected": all(a["rejected"] for a in attempts),
        "keyframes_in_graph": in_graph,
        "base_mode": base_mode,
        "endpoint": ep,
        "wall_time_s": round(time.monotonic() - t0, 2),
    }


def _attempt(name: str, rejected: bool, detail: str) -> dict[str, Any]:
    return {"name": name, "rejected": bool(rejected), "detail": detail}
