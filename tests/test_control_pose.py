"""The agent publishes its smoothed control pose on robot/<id>/pose/control every
scan, over real Zenoh; a correction jump reaches it blended (seed 000 §II)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from agent.control_log import correction_steps, read_control_log
from agent.node import AgentNode
from agent.pose_smoother import blend_alpha, pose7_compose
from agent.vehicle import NullVehicle
from common.bus import Bus
from common.config import Config, ZenohConfig
from common.geometry import pose4_to_pose7
from protocol import (
    Altimeter,
    ControlPose,
    Keyframe,
    LaserScan,
    Neighbours,
    Odometry,
    PoseCorrection,
    decode,
)


def _wait(cond, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)
    return bool(cond())


def test_agent_publishes_blended_control_pose(cfg: Config, endpoint: str, tmp_path: Path) -> None:
    cfg.agent.local_slam.enabled = False  # odometry integration: fast, exact local poses
    start = np.array([1.0, 2.0, 0.0, 0.3])  # T_map_odom known at start
    jumped = pose4_to_pose7([2.0, 2.0, 0.0, 0.3])  # a loop closure moves it by 1 m
    received: list[ControlPose] = []
    lock = threading.Lock()

    def on_pose(msg: ControlPose, key: str) -> None:
        with lock:
            received.append(msg)

    with (
        Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus_agent,
        Bus(ZenohConfig(connect=[endpoint]), cfg.fleet) as bus_base,
    ):
        node = AgentNode(cfg, "r0", bus_agent, np.zeros((0, 2)), start, NullVehicle())
        node.start()
        bus_base.subscribe(bus_base.keys.robot("r0", "pose/control"), ControlPose, on_pose)
        tick = [0]

        def step() -> None:
            k = tick[0]
            t = 0.025 * k
            pose = pose4_to_pose7([0.5 * t, 0.0, 0.0, 0.0])  # 0.5 m/s along x
            node.handle(Odometry("r0", t, pose, np.array([0.5, 0.0, 0.0, 0.0])))
            node.handle(LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, np.ones(201, np.float32)))
            tick[0] += 1

        assert _wait(lambda: (step(), bool(received))[1]), "no ControlPose arrived"
        bus_base.publish(
            bus_base.keys.robot("r0", "correction"), PoseCorrection("r0", 1, 0.0, jumped)
        )
        assert _wait(lambda: node.epoch == 1)
        t_corr = 0.025 * tick[0]  # the next scan applies it
        for _ in range(int(8.0 / 0.025)):
            step()
        node.write_outputs(tmp_path)
        assert _wait(lambda: received[-1].stamp >= 0.025 * (tick[0] - 1))

    ctl = read_control_log(tmp_path / "control_poses" / "r0.csv")
    assert len(ctl) == tick[0]
    raw_t, _ = correction_steps(ctl.T_map_odom_raw, ctl.T_odom_base)
    fil_t, _ = correction_steps(ctl.T_map_odom_applied, ctl.T_odom_base)
    k = int(np.argmax(raw_t)) + 1
    assert abs(ctl.stamps[k] - t_corr) < 1e-6
    assert raw_t.max() == np.float64(raw_t[k - 1]) and abs(raw_t.max() - 1.0) < 1e-6
    assert abs(fil_t[k - 1] - (1.0 - blend_alpha(0.0))) < 1e-6  # 7 % of the jump at once
    assert fil_t.max() <= 0.1 * raw_t.max()
    np.testing.assert_allclose(ctl.T_map_odom_applied[-1], jumped, atol=1e-8)  # settled
    # Every message matches the log: pose_map = applied · T_odom_base, raw likewise.
    with lock:
        msgs = list(received)
    assert len(msgs) > 0.9 * len(ctl)  # best effort on loopback: practically all arrive
    for m in msgs:
        i = int(np.argmin(np.abs(ctl.stamps - m.stamp)))
        np.testing.assert_allclose(m.pose_odom, ctl.T_odom_base[i], atol=1e-8)
        want = pose7_compose(ctl.T_map_odom_applied[i], ctl.T_odom_base[i])
        np.testing.assert_allclose(m.pose_map, want, atol=1e-8)
        raw = pose7_compose(ctl.T_map_odom_raw[i], ctl.T_odom_base[i])
        np.testing.assert_allclose(m.pose_map_raw, raw, atol=1e-8)
        assert (m.epoch == 1) == (m.stamp >= t_corr - 1e-9)
        assert 0.0 <= m.alpha <= 1.0


def test_agent_holds_back_an_epoch_or_relay_far_ahead(cfg: Config, endpoint: str) -> None:
    """A correction of epoch 2^63 - 1 had every later correction ignored (now held until
    the next follows it), and a relay stamped 1e9 s every later relay (one answering a
    state not sent yet is dropped)."""
    pose = pose4_to_pose7([1.0, 0.0, 0.0, 0.0])
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        node._on_correction(PoseCorrection("r0", 2**63 - 1, 0.0, pose), "")
        assert node.epoch == -1
        node._on_correction(PoseCorrection("r0", 1, 0.0, pose), "")
        assert node.epoch == 1 and node.T_map_odom[0] == 1.0
        node._on_correction(PoseCorrection("r0", 5001, 0.0, pose), "")  # a restart's block
        assert node.epoch == 5001
        empty = (np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)))
        for stamp in (1e9, 0.2, 0.4):
            node.last_state_stamp = min(stamp, 0.4)  # a state of 1e9 s was never sent
            node._on_neighbours(Neighbours("r0", stamp, *empty), "")
        assert [m.stamp for m in node._neighbours] == [0.2, 0.4]


def test_a_scan_that_sees_nothing_goes_on_with_the_odometry(cfg: Config, endpoint: str) -> None:
    """A laser dropout (all NaN) neither stops the pose (it had stood still while the
    drone flew on) nor the keyframes, which follow the odometry through it (the base
    station draws none of their empty scans: tests/test_map_builder.py)."""
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        room = (2.0 + np.abs(np.sin(np.linspace(0.0, 9.0, 201)))).astype(np.float32)
        for k in range(60):  # 0.5 m/s along x: a keyframe every 0.2 m
            t = 0.1 * k
            node.handle(Altimeter("r0", t, 1.0))
            pose = pose4_to_pose7([0.5 * t, 0.0, 0.0, 0.0])
            node.handle(Odometry("r0", t, pose, np.array([0.5, 0.0, 0.0, 0.0])))
            ranges = np.full(201, np.nan, np.float32) if 20 <= k < 40 else room
            node.handle(LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, ranges))
        sent = [decode(p, Keyframe) for p in node.outbox._pending.values()]
    blind = [kf for kf in sent if 2.0 <= kf.stamp < 4.0]
    assert len(blind) >= 3 and node.frontend.few_point_scans == 20
    dx, dt = blind[-1].pose_odom[0] - blind[0].pose_odom[0], blind[-1].stamp - blind[0].stamp
    assert abs(dx / dt - 0.5) < 0.02  # the odometry's 0.5 m/s through the dropout


def test_agent_sends_no_keyframe_the_base_station_would_refuse(cfg: Config, endpoint: str) -> None:
    """An altimeter reading of 1e9 m put a keyframe's height out of the pose graph's
    reach: refused by the base station, it held back every later keyframe of the robot
    for good. Such a keyframe is not sent; the next one spans from the last one sent."""
    cfg.agent.local_slam.enabled = False  # odometry integration: exact local poses
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        for k in range(60):  # 0.5 m/s along x: a keyframe every 0.2 m
            t = 0.1 * k
            node.handle(Altimeter("r0", t, 1e9 if 10 <= k < 14 else 1.0))
            pose = pose4_to_pose7([0.5 * t, 0.0, 0.0, 0.0])
            node.handle(Odometry("r0", t, pose, np.array([0.5, 0.0, 0.0, 0.0])))
            node.handle(LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, np.ones(201, np.float32)))
        sent = [decode(p, Keyframe) for p in node.outbox._pending.values()]
    assert node.uplink.refused >= 2
    assert [kf.seq for kf in sent] == list(range(len(sent))) and len(sent) >= 12
    steps = np.array([kf.delta[:3] for kf in sent[1:]])
    assert np.all(np.abs(steps[:, 2]) < 1e-9) and np.all(steps[:, 0] > 0.0)
    travel = sent[-1].pose_odom[0] - sent[0].pose_odom[0]
    assert abs(steps[:, 0].sum() - travel) < 1e-9  # the keyframe after the gap spans it
