"""Mutual TLS and per-robot access control with real Zenoh sessions on loopback.

Certificates are made at test time by deploy/make_certs.sh (a fleet CA with r0 and r1,
and an unrelated CA with its own "r0"). The base station side is our `Bus` opened on
the generated secure config (`tls/127.0.0.1:<port>`, mTLS, ACL keyed by CN); robots
are `Bus`es on their robot configs. Each refusal has a control that succeeds, so the
tests cannot pass for an unrelated reason.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
import zenoh

from benchmarks.security_clients import make_certs, make_keyframe, try_open, wait_for
from collabslam.cli import build_parser
from collabslam.cli_options import load_cfg
from collabslam.supervisor import free_port
from common.bus import Bus, zenoh_config
from common.config import ZenohConfig
from common.errors import CollabSlamError, ConfigError
from common.zenoh_security import (
    basestation_config,
    check_certificate_name,
    robot_config,
    write_json5,
)
from protocol import GnssFix, Keyframe, KeyframeAck

REPO = Path(__file__).resolve().parents[1]
FLEET = "default"


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("certs")
    return make_certs(root / "fleet", ["r0", "r1"]), make_certs(root / "other", ["r0"], "evil CA")


def _secure_base(
    stack: ExitStack, tmp: Path, certs: Path, topology: str = "peer", acl: bool = True
) -> tuple[Bus, str]:
    """The base station's Bus on the secure config; returns it and the robots' endpoint.

    topology: "peer" or "router" (the base station's own session listens, as
    collabslam-basestation.service runs it), or "zenohd" (the router option: a router
    session on router.json5's content holds the ACL, the base station is its client
    with the CN=basestation certificate).
    """
    ep = f"tls/127.0.0.1:{free_port()}"
    conf = basestation_config(certs, FLEET, ["r0", "r1"], [ep])
    conf["access_control"]["enabled"] = acl
    if topology == "zenohd":
        router = zenoh.open(zenoh.Config.from_json5(json.dumps({"mode": "router", **conf})))
        stack.callback(router.close)
        path = write_json5(robot_config(certs, "basestation", [ep]), tmp / "base-client.json5")
        zc = ZenohConfig(mode="client", config_file=str(path))
    else:
        zc = ZenohConfig(mode=topology, config_file=str(write_json5(conf, tmp / "base.json5")))
    bus = stack.enter_context(Bus(zc, FLEET))
    bus.declare_alive("basestation", "base")
    return bus, ep


def _robot(tmp: Path, certs: Path, rid: str, ep: str) -> Bus:
    path = write_json5(robot_config(certs, rid, [ep]), tmp / f"{rid}-{free_port()}.json5")
    bus = Bus(ZenohConfig(mode="peer", config_file=str(path)), FLEET)
    seen = threading.Event()
    bus.watch_alive("basestation", lambda n, a: seen.set() if a else None)
    if not seen.wait(10.0):
        bus.close()
        raise AssertionError(f"robot {rid} never connected to the secure base station")
    return bus


def test_make_certs_chains_and_common_names(certs: tuple[Path, Path]) -> None:
    fleet, other = certs
    for name in ("basestation", "r0", "r1"):
        assert (fleet / f"{name}.key").stat().st_mode & 0o077 == 0  # private keys: owner only
        subject = subprocess.run(
            ["openssl", "x509", "-in", str(fleet / f"{name}.pem"), "-noout", "-subject"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        assert f"CN = {name}" in subject or f"CN={name}" in subject
    verify = ["openssl", "verify", "-CAfile", str(fleet / "ca.pem")]
    assert subprocess.run([*verify, str(fleet / "r0.pem")], capture_output=True).returncode == 0
    assert subprocess.run([*verify, str(other / "r0.pem")], capture_output=True).returncode != 0


def test_unknown_clients_are_refused(tmp_path: Path, certs: tuple[Path, Path]) -> None:
    fleet, other = certs
    with ExitStack() as stack:
        _, ep = _secure_base(stack, tmp_path, fleet)
        tls_root = {"root_ca_certificate": str(fleet / "ca.pem")}
        no_cert = {"connect": {"endpoints": [ep]}, "transport": {"link": {"tls": tls_root}}}
        assert try_open(no_cert) is not None, "a client without a certificate got in"
        foreign = robot_config(other, "r0", [ep])
        foreign["transport"]["link"]["tls"].update(tls_root)  # it trusts our server...
        assert try_open(foreign) is not None, "a certificate from another CA got in"
        plain_tcp = {"connect": {"endpoints": [ep.replace("tls/", "tcp/")]}}
        assert try_open(plain_tcp) is not None, "a plain TCP client got in"
        # Control: the fleet's own r0 certificate opens a session.
        assert try_open(robot_config(fleet, "r0", [ep])) is None


@pytest.mark.parametrize(
    ("topology", "acl"), [("peer", True), ("router", True), ("zenohd", True), ("router", False)]
)
def test_robot_cannot_write_or_read_another_robots_keys(
    tmp_path: Path, certs: tuple[Path, Path], topology: str, acl: bool
) -> None:
    """r0's put on r1's key is dropped while its own arrives; r0's subscription to r1's
    downlink gets nothing while r1's own does. With the ACL off (control) both leak."""
    fleet = certs[0]
    got: list[tuple[str, int]] = []
    spied: list[str] = []
    with ExitStack() as stack:
        base, ep = _secure_base(stack, tmp_path, fleet, topology, acl)
        base.subscribe(
            base.keys.all_robots("keyframe"), Keyframe, lambda m, k: got.append((m.robot_id, m.seq))
        )
        r0, r1, spy = (
            stack.enter_context(_robot(tmp_path, fleet, rid, ep))
            for rid in ("r0", "r1", "r0")  # spy: another process of robot A
        )
        agents: set[str] = set()
        base.watch_alive("agent", lambda n, a: agents.add(n) if a else agents.discard(n))
        spy.declare_alive("agent", "r1")  # robot A claims to be robot B (sent first)...
        r0.declare_alive("agent", "r0")
        assert wait_for(lambda: "r0" in agents, 10.0), agents  # ...so it would be here now
        r0_acks: list[int] = []
        r1_acks: list[int] = []
        spy.subscribe(spy.keys.robot("r1", "ack"), KeyframeAck, lambda m, k: spied.append(k))
        spy.subscribe(spy.keys.robot("r0", "ack"), KeyframeAck, lambda m, k: r0_acks.append(1))
        r1.subscribe(r1.keys.robot("r1", "ack"), KeyframeAck, lambda m, k: r1_acks.append(1))
        # Same session, same priority: Zenoh keeps the order, so once r0's own keyframe
        # (sent second) has arrived, the forged one would have arrived before it.
        r0.publish(r0.keys.robot("r1", "keyframe"), make_keyframe("r1", 100))
        r0.publish(r0.keys.robot("r0", "keyframe"), make_keyframe("r0", 0))
        r1.publish(r1.keys.robot("r1", "keyframe"), make_keyframe("r1", 0))
        assert wait_for(lambda: {("r0", 0), ("r1", 0)} <= set(got), 10.0), got
        # The base answers r1 first, then r0: the spy's r1 ack would precede its own.
        base.publish(base.keys.robot("r1", "ack"), KeyframeAck("r1", 0))
        base.publish(base.keys.robot("r0", "ack"), KeyframeAck("r0", 0))
        assert wait_for(lambda: bool(r0_acks) and bool(r1_acks), 10.0)
        alive = set(agents)
    if acl:
        assert ("r1", 100) not in got, "r0's forged keyframe for r1 reached the base station"
        assert spied == [], "r0 received r1's downlink"
        assert alive == {"r0"}, "r0's liveliness token for r1 reached the base station"
    else:
        assert ("r1", 100) in got and spied, "control without ACL: the attack should work"
        assert alive == {"r0", "r1"}


@pytest.mark.e2e
def test_bench_security_end_to_end(tmp_path: Path) -> None:
    """`collabslam bench security` with a real base-station process: every attempt
    rejected, the legitimate robots' keyframes all in the graph."""
    out = tmp_path / "sec.json"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "collabslam.cli",
            "bench",
            "security",
            "--json",
            str(out),
            "--agent-seconds",
            "0",  # the agent-process leg is left to the bench run itself
        ],  # fmt: skip
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    result = json.loads(out.read_text())
    names = {a["name"] for a in result["attempts"]}
    assert {
        "client_without_certificate",
        "certificate_from_other_ca",
        "robot_A_publishes_keyframes_as_robot_B",
        "robot_A_subscribes_to_robot_B_paths",
    } <= names
    assert all(a["rejected"] for a in result["attempts"]), result["attempts"]
    assert result["legitimate_ok"] is True
    assert result["keyframes_in_graph"] == {"r0": 5, "r1": 7} and "agent_process" not in result


def test_deploy_configs_match_the_generator_and_load(tmp_path: Path) -> None:
    """deploy/zenoh/*.json5 are what make_zenoh_configs.py writes, and Zenoh reads them."""
    subprocess.run(
        [
            sys.executable,
            str(REPO / "deploy" / "make_zenoh_configs.py"),
            "--certs", "/etc/collabslam/certs",
            "--out", str(tmp_path),
            "--base-host", "basestation.local",
            "r0", "r1", "r2",
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    shipped = sorted(p.name for p in (REPO / "deploy" / "zenoh").glob("*.json5"))
    assert shipped == sorted(p.name for p in tmp_path.glob("*.json5"))
    for name in shipped:
        assert (REPO / "deploy" / "zenoh" / name).read_text() == (tmp_path / name).read_text()
        zenoh.Config.from_file(str(tmp_path / name))


def test_configs_for_a_base_host_its_certificate_does_not_name_are_refused(
    tmp_path: Path, certs: tuple[Path, Path]
) -> None:
    """The drones check the base station's certificate against the host they connect to:
    configs for another host had been written without a word, and every TLS link was
    then refused in silence."""
    cmd = [sys.executable, str(REPO / "deploy" / "make_zenoh_configs.py"), "--certs",
           str(certs[0]), "--out", str(tmp_path), "r0"]  # fmt: skip
    bad = subprocess.run([*cmd, "--base-host", "192.168.8.1"], capture_output=True, text=True)
    assert bad.returncode == 2 and "not among the names" in bad.stderr
    assert "BASE_HOSTS=192.168.8.1 deploy/make_certs.sh" in bad.stderr
    assert not list(tmp_path.glob("*.json5"))
    subprocess.run([*cmd, "--base-host", "127.0.0.1"], check=True, capture_output=True)
    assert (tmp_path / "robot-r0.json5").is_file()


def test_a_config_made_for_another_fleet_is_refused_at_start(tmp_path: Path) -> None:
    """Configs made with another --fleet than the processes run: the base station had
    dropped every keyframe, counting no rejection."""
    path = write_json5(basestation_config(Path("/nowhere"), "other", ["r0"], ["tls/0.0.0.0:7447"]),
                       tmp_path / "base.json5")  # fmt: skip
    conf = zenoh.Config.from_file(str(path))
    from common.zenoh_security import check_acl_fleet

    check_acl_fleet(conf, "other", "base.json5")
    with pytest.raises(ConfigError, match="fleet 'default'.*another --fleet"):
        check_acl_fleet(conf, "default", "base.json5")


def test_zenoh_config_cli_option_and_merge(tmp_path: Path, certs: tuple[Path, Path]) -> None:
    """--zenoh-config sets zenoh.config_file; its endpoints stay unless --listen is given."""
    path = write_json5(robot_config(certs[0], "r0", ["tls/127.0.0.1:7447"]), tmp_path / "r.json5")
    args = build_parser().parse_args(["agent", "--robot-id", "r0", "--zenoh-config", str(path)])
    zc = load_cfg(args).zenoh
    assert zc.config_file == str(path)
    conf = zenoh_config(zc)
    assert json.loads(conf.get_json("connect/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(conf.get_json("listen/endpoints")) == []  # not Zenoh's tcp/[::]:0
    # the file's scouting stays off (zenoh.gossip_scouting's default, on, is for no file)
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    zc.connect = ["tcp/127.0.0.1:9999"]
    assert json.loads(zenoh_config(zc).get_json("connect/endpoints")) == ["tcp/127.0.0.1:9999"]


def test_missing_certificate_file_is_a_clear_config_error(tmp_path: Path) -> None:
    conf = robot_config(tmp_path / "nowhere", "r0", ["tls/127.0.0.1:7447"])
    path = write_json5(conf, tmp_path / "r0.json5")
    with pytest.raises(ConfigError, match="root_ca_certificate .*nowhere/ca.pem"):
        Bus(ZenohConfig(config_file=str(path)), FLEET)


def test_an_expired_certificate_is_refused_at_start_and_one_not_yet_valid_named(
    tmp_path: Path, certs: tuple[Path, Path], caplog: pytest.LogCaptureFixture
) -> None:
    """An expired certificate (the whole fleet's at once: the CA and the robots share a
    lifetime) had every TLS link refused with only "no base station seen" in any log."""
    import time as _time

    import zenoh

    from common.zenoh_security import check_tls_files

    path = write_json5(robot_config(certs[0], "r0", ["tls/127.0.0.1:7447"]), tmp_path / "r.json5")
    conf = zenoh.Config.from_file(str(path))
    check_tls_files(conf, "now")  # made today: valid
    with pytest.raises(ConfigError, match="root_ca_certificate .*expired on"):
        check_tls_files(conf, "in 30 years", now=_time.time() + 30 * 365 * 86400)
    check_tls_files(conf, "a drone's clock at boot", now=0.0)  # (Zenoh retries: a warning)
    assert "valid only from" in caplog.text and "Jan 01 00:00:00 1970" in caplog.text


def test_secure_base_station_refuses_a_plain_tcp_listener(
    tmp_path: Path, certs: tuple[Path, Path]
) -> None:
    """With the secure config, `--listen tcp/...` fails instead of opening a hole."""
    conf = basestation_config(certs[0], FLEET, ["r0"], [f"tls/127.0.0.1:{free_port()}"])
    path = write_json5(conf, tmp_path / "base.json5")
    zc = ZenohConfig(config_file=str(path), listen=[f"tcp/127.0.0.1:{free_port()}"])
    with pytest.raises(ConfigError, match="(?i)unsupported protocol: tcp"):
        Bus(zc, FLEET)


def test_a_new_drone_with_the_ca_key_offline_makes_no_new_ca(tmp_path: Path) -> None:
    """operations.md keeps ca.key off the base station host. Re-running make_certs.sh for
    a new drone without it had made a new CA over ca.pem: no certificate signed before
    verified any more, and every drone failed its handshake after the restart. It now
    refuses; with ca.key back, the new drone's certificate is signed by the same CA."""
    out = make_certs(tmp_path / "fleet", ["r0"])
    ca = (out / "ca.pem").read_bytes()
    (out / "ca.key").rename(tmp_path / "ca.key.offline")
    with pytest.raises(CollabSlamError, match="ca.key is missing"):
        make_certs(out, ["r0", "r1"])
    assert (out / "ca.pem").read_bytes() == ca and not (out / "r1.pem").exists()
    (tmp_path / "ca.key.offline").rename(out / "ca.key")
    make_certs(out, ["r0", "r1"])
    assert (out / "ca.pem").read_bytes() == ca
    for name in ("r0", "r1", "basestation"):
        res = subprocess.run(
            ["openssl", "verify", "-CAfile", str(out / "ca.pem"), str(out / f"{name}.pem")],
            capture_output=True, text=True,
        )  # fmt: skip
        assert res.returncode == 0, res.stderr


@pytest.mark.parametrize("topology", ["peer", "router"])
def test_a_drones_relayed_gnss_fixes_reach_the_base_station_under_the_acl(
    tmp_path: Path, certs: tuple[Path, Path], topology: str
) -> None:
    """`agent.relay_gnss` puts a drone's fixes on robot/<id>/sensor/gnss; the base
    station's subscription to robot/*/sensor/gnss must be declared to the robot (an
    egress rule: a wildcard is never under robot/<id>/**), or none reaches it."""
    fleet = certs[0]
    fixes: list[float] = []
    kfs: list[int] = []
    with ExitStack() as stack:
        base, ep = _secure_base(stack, tmp_path, fleet, topology)
        base.subscribe(
            base.keys.all_robots("sensor/gnss"), GnssFix, lambda m, k: fixes.append(m.stamp)
        )
        base.subscribe(base.keys.all_robots("keyframe"), Keyframe, lambda m, k: kfs.append(m.seq))
        r0 = stack.enter_context(_robot(tmp_path, fleet, "r0", ep))
        time.sleep(1.0)
        for k in range(5):
            r0.publish(
                r0.keys.robot("r0", "sensor/gnss"),
                GnssFix("r0", float(k), np.array([45.81, 16.01, 160.0]), np.array([1.5, 1.5, 3.0])),
            )
            r0.publish(r0.keys.robot("r0", "keyframe"), make_keyframe("r0", k))
            time.sleep(0.1)
        wait_for(lambda: len(fixes) == 5 and len(kfs) == 5, 5.0)
    assert len(kfs) == 5, kfs  # control
    assert fixes == [0.0, 1.0, 2.0, 3.0, 4.0], fixes


def test_a_drone_given_another_drones_config_is_refused_at_start(
    tmp_path: Path, certs: tuple[Path, Path]
) -> None:
    """r1 started on r0's config (a copy to the wrong drone) had connected, had every
    keyframe dropped by the access control, and flown the mission mapping nothing with no
    line in any log. Now the agent (and a base station on a robot's config) refuses."""
    from collabslam.cli import main

    path = write_json5(robot_config(certs[0], "r0", ["tls/127.0.0.1:7447"]), tmp_path / "r0.json5")
    check_certificate_name(str(path), "r0")  # its own: taken
    with pytest.raises(ConfigError, match="certificate .*r0.pem is 'r0''s, not 'r1''s"):
        check_certificate_name(str(path), "r1")
    argv = ["agent", "--robot-id", "r1", "--zenoh-config", str(path), "--out", str(tmp_path)]
    assert main(argv) != 0
    assert main(["basestation", "--zenoh-config", str(path), "--out", str(tmp_path)]) != 0
