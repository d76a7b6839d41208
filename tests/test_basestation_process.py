"""A real base-station process over real Zenoh on loopback: it acknowledges valid
keyframes, logs and drops malformed/oversized/wrong-version/NaN payloads and
unknown robots, keeps running, and writes its outputs on SIGINT."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
from process_helpers import poll_until

from common.bus import Bus
from common.config import ZenohConfig
from common.geometry import pose4_to_pose7
from common.scenario import RobotScenario, Scenario, write_scenario
from protocol import Keyframe, KeyframeAck, PoseCorrection, RobotState, Scan2D, encode


def _keyframe(seq: int, robot: str = "r0", x: float | None = None) -> Keyframe:
    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    ranges = 2.0 / np.maximum(np.cos(angles), 0.2)  # a wall 2 m ahead
    x = 0.2 * seq if x is None else x
    return Keyframe(
        robot,
        seq,
        0.5 * seq,
        pose4_to_pose7([x, 0, 1, 0]),
        pose4_to_pose7([0.2 if seq else 0.0, 0, 0, 0]),
        np.eye(6) * 1e-4,
        Scan2D.from_ranges(-np.pi / 2, np.pi / 180, 30.0, ranges),
        None,
    )


@pytest.mark.e2e
def test_basestation_survives_bad_input_and_acks_valid(tmp_path: Path, endpoint: str) -> None:
    write_scenario(
        tmp_path / "scenario.json",
        Scenario("none", [RobotScenario("r0", np.array([1.0, 2.0, 0.0]))]),
    )
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "collabslam.cli",
            "basestation",
            "--scenario",
            str(tmp_path / "scenario.json"),
            "--out",
            str(tmp_path),
            "--listen",
            endpoint,
            "--set",
            "protocol.max_message_bytes=100000",
            "--set",
            "basestation.map_update_period_s=0.1",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    acks: list[int] = []
    corrections: list[PoseCorrection] = []
    lock = threading.Lock()
    try:
        with Bus(ZenohConfig(connect=[endpoint]), "default") as bus:
            bus.subscribe(
                bus.keys.robot("r0", "ack"),
                KeyframeAck,
                lambda m, k: (lock.acquire(), acks.append(m.acked_seq), lock.release()),
            )
            bus.subscribe(
                bus.keys.robot("r0", "correction"),
                PoseCorrection,
                lambda m, k: corrections.append(m),
            )
            alive: list[str] = []
            bus.watch_alive("basestation", lambda n, a: alive.append(n) if a else None)
            assert poll_until(lambda: alive), "base station never came alive"
            key = bus.keys.robot("r0", "keyframe")
            good = encode(_keyframe(0))
            env = msgpack.unpackb(good, raw=False)
            bad_payloads = [
                b"\x00\xff garbage",
                good[: len(good) // 2],
                msgpack.packb({**env, "v": 999}, use_bin_type=True),
                b"\x00" * 200_000,  # oversized
            ]
            nan_env = dict(env)
            nan_env["d"] = dict(env["d"], stamp=float("nan"))
            bad_payloads.append(msgpack.packb(nan_env, use_bin_type=True))
            for p in bad_payloads:
                bus.put_raw(key, p)
            # a keyframe claiming to be another robot on r0's key, and an unknown robot
            bus.put_raw(key, encode(_keyframe(0, robot="r9")))
            bus.put_raw(bus.keys.robot("r9", "keyframe"), encode(_keyframe(0, robot="r9")))
            p7 = pose4_to_pose7([0.0, 0.0, 1.0, 0.0])
            bus.publish(
                bus.keys.robot("r9", "state"), RobotState("r9", 1.0, "flying", -1, 0, 0, 0, p7, p7)
            )
            # valid keyframes, out of order and duplicated
            for seq in (0, 2, 1, 1, 3, 4):
                bus.publish(key, _keyframe(seq))
            assert poll_until(lambda: acks and acks[-1] == 4), f"acks seen: {acks}"
            assert poll_until(lambda: len(corrections) > 0)
            T = corrections[-1].T_map_odom
            assert np.allclose(T[:2], [1.0, 2.0], atol=1e-3)  # known start pose
            assert proc.poll() is None, "base station died on bad input"
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    log = out.decode()
    assert proc.returncode == 0, log
    assert "dropped bad message" in log and "keyframe from unknown robot 'r9'" in log
    assert "state from unknown robot 'r9'" in log
    stats = json.loads((tmp_path / "basestation.json").read_text())
    assert stats["robots"]["r0"]["keyframes_in_graph"] == 5
    assert stats["robots"]["r0"]["duplicates"] >= 1
    assert sum(stats["rejected_messages"].values()) == len(bad_payloads) + 1
    assert stats["unknown_robot_drops"] == 2
    assert (tmp_path / "map.pgm").is_file() and (tmp_path / "trajectories" / "r0.tum").is_file()
