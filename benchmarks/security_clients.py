"""Clients of a secure base station, for `collabslam bench security` and its tests.

Certificates from `deploy/make_certs.sh`, a probe that tries to open a Zenoh client
session, and `SecureRobot`: our `Bus` on a robot's secure config that streams
keyframes and records its acks and corrections.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from common.bus import Bus
from common.config import ZenohConfig
from common.errors import CollabSlamError
from common.geometry import pose4_to_pose7
from protocol import Keyframe, KeyframeAck, PoseCorrection, Scan2D

REPO = Path(__file__).resolve().parents[1]


def make_certs_script() -> Path:
    """deploy/make_certs.sh of the source checkout: next to the code, or (code installed
    with `pip install .`, which leaves deploy/ out) in the current directory."""
    for base in (REPO, Path.cwd()):
        if (base / "deploy" / "make_certs.sh").is_file():
            return base / "deploy" / "make_certs.sh"
    raise CollabSlamError(
        "deploy/make_certs.sh is neither next to the installed code nor in the current "
        "directory: run this from the source checkout (e.g. cd /opt/collabslam)"
    )


def make_certs(out: Path, robots: list[str], ca_name: str = "collabslam fleet CA") -> Path:
    """Run deploy/make_certs.sh (CA + basestation + one certificate per robot) into `out`."""
    script = make_certs_script()
    env = dict(os.environ, CA_NAME=ca_name, BASE_HOSTS="localhost,127.0.0.1")
    res = subprocess.run(
        ["bash", str(script), str(out), *robots], env=env, capture_output=True, text=True
    )
    if res.returncode != 0:
        raise CollabSlamError(f"{script} failed: {res.stderr.strip()}")
    return out


def make_keyframe(robot: str, seq: int, x0: float = 0.0) -> Keyframe:
    """A valid keyframe: the robot 0.2 m further along x per seq, a wall 2 m ahead."""
    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = 2.0 / np.maximum(np.cos(angles), 0.2)
    return Keyframe(
        robot,
        seq,
        0.5 * seq,
        pose4_to_pose7([x0 + 0.2 * seq, 0.0, 1.0, 0.0]),
        pose4_to_pose7([0.2 if seq else 0.0, 0.0, 0.0, 0.0]),
        np.eye(6) * 1e-4,
        Scan2D.from_ranges(-np.pi / 2, np.pi / 180, 30.0, ranges),
        None,
    )


def try_open(conf: dict[str, Any]) -> str | None:
    """Open a client session with `conf`; None if it opened (then closed), else the error."""
    c = zenoh.Config.from_json5(json.dumps({**conf, "mode": "client"}))
    try:
        session = zenoh.open(c)
    except Exception as exc:  # zenoh raises ZError when no endpoint accepts us
        return str(exc).split(" at ")[0]
    session.close()
    return None


def port_open(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
        return True
    except OSError:
        return False


def wait_for(pred: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return bool(pred())


class SecureRobot:
    """A robot on the secure link: our Bus with its robot config; records its acks/corrections."""

    def __init__(self, rid: str, conf_file: Path, fleet: str) -> None:
        self.rid = rid
        self.bus = Bus(ZenohConfig(mode="peer", config_file=str(conf_file)), fleet)
        self.acks: list[int] = []
        self.corrections = 0
        self._lock = threading.Lock()
        self.bus.subscribe(self.bus.keys.robot(rid, "ack"), KeyframeAck, self._on_ack)
        self.bus.subscribe(self.bus.keys.robot(rid, "correction"), PoseCorrection, self._on_corr)
        self.base_alive = threading.Event()
        self.bus.watch_alive("basestation", lambda n, a: self.base_alive.set() if a else None)

    def _on_ack(self, m: KeyframeAck, key: str) -> None:
        with self._lock:
            self.acks.append(m.acked_seq)

    def _on_corr(self, m: PoseCorrection, key: str) -> None:
        with self._lock:
            self.corrections += 1

    def connected(self) -> bool:
        """True once the session has a link to the base station (router or peer)."""
        info = self.bus.session.info
        return bool(info.routers_zid() or info.peers_zid())

    def last_ack(self) -> int:
        with self._lock:
            return max(self.acks, default=-1)

    def send(self, seqs: range, robot: str | None = None, x0: float = 0.0) -> None:
        """Publish keyframes `seqs`; with `robot`, forged ones on that robot's key."""
        target = robot or self.rid
        for seq in seqs:
            self.bus.publish(
                self.bus.keys.robot(target, "keyframe"), make_keyframe(target, seq, x0)
            )
