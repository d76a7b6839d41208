"""What the base station sends, and when: an ack only for keyframes already in its
database (an ack lets the agent drop a keyframe: one sent ahead of the commit is lost to
a crash in between), and no correction for a robot two agents send as."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
from process_helpers import stored_keyframes, synthetic_keyframe

from basestation.node import BaseStationNode
from common.bus import Bus
from common.config import ZenohConfig, load_config
from common.map_io import GridMap, write_map
from common.scenario import RobotScenario, Scenario
from protocol import KeyframeAck, PoseCorrection


def test_an_ack_goes_out_only_for_keyframes_on_disk(tmp_path, endpoint) -> None:
    write_map(GridMap(np.zeros((100, 100), np.int8), 0.1, (-5.0, -5.0, 0.0)), tmp_path / "w.yaml")
    scenario = Scenario(str(tmp_path / "w.yaml"), [RobotScenario("r0", np.zeros(3))])
    db = tmp_path / "base.db"
    cfg = load_config(
        overrides={
            "exploration.enabled": False,
            "basestation.db_path": str(db),
            "basestation.constraints.enabled": False,
        }
    )
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        node = BaseStationNode(cfg, bus, scenario)
        acks: list[tuple[int, int]] = []  # (acked seq, keyframes on disk when it was sent)
        send = node._send

        def checked_send(topic, msg):
            if isinstance(msg, KeyframeAck):
                acks.append((msg.acked_seq, stored_keyframes(db, "r0")))
            send(topic, msg)

        node._send = checked_send
        key = bus.keys.robot("r0", "keyframe")
        for s in range(4):
            kf = synthetic_keyframe(
                "r0", s, np.array([0.2 * s, 0.0, 0.0]), np.array([0.2 if s else 0.0, 0.0, 0.0])
            )
            node._on_keyframe(kf, key)
            node.step(timeout=0.2)
        node.db.close()
    assert [a for a, _ in acks] == [0, 1, 2, 3]
    assert all(on_disk >= acked + 1 for acked, on_disk in acks), acks


def test_no_correction_for_a_robot_two_agents_send_as(tmp_path, endpoint) -> None:
    write_map(GridMap(np.zeros((100, 100), np.int8), 0.1, (-5.0, -5.0, 0.0)), tmp_path / "w.yaml")
    scenario = Scenario(str(tmp_path / "w.yaml"), [RobotScenario("r0", np.zeros(3))])
    cfg = load_config(
        overrides={"exploration.enabled": False, "basestation.constraints.enabled": False}
    )
    got: list[PoseCorrection] = []
    lock = threading.Lock()
    with Bus(ZenohConfig(listen=[endpoint]), "default") as bus:
        bus.subscribe(
            bus.keys.robot("r0", "correction"),
            PoseCorrection,
            lambda m, k: (lock.acquire(), got.append(m), lock.release()),
        )
        node = BaseStationNode(cfg, bus, scenario)
        key = bus.keys.robot("r0", "keyframe")
        kfs = [
            synthetic_keyframe(
                "r0", s, np.array([0.2 * s, 0.0, 0.0]), np.array([0.2 if s else 0.0, 0.0, 0.0])
            )
            for s in range(3)
        ]
        for kf in kfs:
            node._on_keyframe(kf, key)
        while node.step(timeout=0.2):
            pass
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            time.sleep(0.02)
        assert got, "no correction for r0 at all (the test's set-up is wrong)"
        node._on_keyframe(dataclasses.replace(kfs[1], stamp=1e6), key)  # another r0's seq 1
        node._on_keyframe(kfs[2], key)
        node.step(timeout=0.2)
        assert node.slam.store.robot("r0").foreign
        with lock:
            got.clear()
        node.publish_corrections()
        time.sleep(0.5)
        with lock:
            assert got == [], "a robot two agents send as was sent a correction"
