"""What an agent takes from its inputs: the IMU's roll and pitch reach the projection of
its scans (SPEC §1, roll/pitch compensation), and a correction older than the one it
has is not taken."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from agent.node import AgentNode
from agent.vehicle import NullVehicle
from collabslam.launcher import Launcher
from common.bus import Bus
from common.config import ZenohConfig, load_config
from common.errors import ConfigError
from common.geometry import pose4_to_pose7
from protocol import Altimeter, Imu, LaserScan, Odometry, PoseCorrection


def test_the_imu_attitude_reaches_the_scan_projection(endpoint: str) -> None:
    cfg = load_config()
    q = Rotation.from_euler("xyz", [0.05, -0.12, 0.3]).as_quat()  # roll, pitch, yaw
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        node.handle(Imu("r0", 0.0, np.zeros(3), np.zeros(3), q))
        assert np.allclose([node.frontend.roll, node.frontend.pitch], [0.05, -0.12], atol=1e-9)


def test_an_older_correction_is_not_taken(endpoint: str) -> None:
    cfg = load_config()
    new, old = pose4_to_pose7([2.0, 0.0, 0.0, 0.0]), pose4_to_pose7([-3.0, 0.0, 0.0, 0.0])
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        node._on_correction(PoseCorrection("r0", 7, 0.0, new), "")
        node._on_correction(PoseCorrection("r0", 6, 0.0, old), "")  # late, superseded
        node._on_correction(PoseCorrection("r0", 7, 0.0, old), "")  # same epoch again
        assert node.epoch == 7 and node.T_map_odom[0] == 2.0


class _Recorder:
    def __init__(self) -> None:
        self.commands: list[tuple[float, ...]] = []

    def command(self, stamp: float, *args: float) -> None:
        self.commands.append((stamp, *args))


@contextlib.contextmanager
def _touring_agent(endpoint: str, vehicle: _Recorder) -> Iterator[AgentNode]:
    """An agent on a scripted tour 20 m ahead, its commands to `vehicle`."""
    cfg = load_config()
    cfg.exploration.enabled = False
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        yield AgentNode(cfg, "r0", bus, np.array([[20.0, 0.0]]), np.zeros(4), vehicle)


def test_a_scan_stamped_like_the_last_is_not_flown_on(endpoint: str) -> None:
    """A driver stamping whole seconds: its scans after the first of each second had been
    taken as a lock-step tick sent again, and answered from a pose up to 1 s old (the
    drone flew 0.12 m from a wall). Now such a scan is not used and the drone hovers; a
    tick sent again (the same ranges) is still answered as before."""
    vehicle = _Recorder()
    ranges = np.full(360, 8.0, np.float32)
    with _touring_agent(endpoint, vehicle) as node:
        for k, t in enumerate((0.0, 0.025, 0.05, 0.075, 0.1)):
            pose = pose4_to_pose7([0.01 * k, 0.0, 1.0, 0.0])
            node.handle(Odometry("r0", t, pose, np.array([0.4, 0.0, 0.0, 0.0])))
            node.handle(Altimeter("r0", t, 1.0))
            node.handle(LaserScan("r0", t, -np.pi, np.pi / 180, 0.1, 30.0, ranges))
        flying = vehicle.commands[-1]
        node.handle(LaserScan("r0", 0.1, -np.pi, np.pi / 180, 0.1, 30.0, ranges.copy()))
        assert vehicle.commands[-1] == flying  # the tick sent again: the same answer
        node.handle(LaserScan("r0", 0.1, -np.pi, np.pi / 180, 0.1, 30.0, ranges * 0.99))
    assert flying[1] > 0.0 and vehicle.commands[-1][1:5] == (0.0, 0.0, 0.0, 0.0)
    assert node.stats()["scans_stale_stamp"] == 1


def test_an_altimeter_that_stopped_gives_no_vertical_speed(endpoint: str) -> None:
    """A rangefinder out of range, or a driver hang, during the take-off: its last
    reading (0.18 m) stood for the height, and the drone climbed on at 0.5 m/s for good
    (5.2 m in 10 s). A reading older than 0.5 s counts as none: no vertical speed."""
    vehicle = _Recorder()
    ranges = np.full(360, 8.0, np.float32)
    with _touring_agent(endpoint, vehicle) as node:
        for k in range(40):  # 1 s at 40 Hz; the altimeter stops after 0.1 s
            t = 0.025 * k
            node.handle(Odometry("r0", t, pose4_to_pose7([0.0, 0.0, 0.18, 0.0]), np.zeros(4)))
            if t <= 0.1:
                node.handle(Altimeter("r0", t, 0.18))
            node.handle(LaserScan("r0", t, -np.pi, np.pi / 180, 0.1, 30.0, ranges * (1 + k * 1e-3)))
    vz = {round(stamp, 3): c[2] for stamp, *c in vehicle.commands}
    assert vz[0.1] > 0.4 and vz[0.6] == 0.0 and vz[0.975] == 0.0


def test_a_placement_come_during_a_tick_is_taken_at_once_on_the_next(endpoint: str) -> None:
    """An in-flight start's placement arriving between a tick's control pose and its
    command had set it placed: the next tick blended the placement in over seconds from
    the start pose it knew was wrong (8.8 m off). It holds one more tick instead."""
    cfg = load_config()
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        node = AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle())
        node.fresh.in_flight = True
        node._on_correction(PoseCorrection("r0", 0, 0.0, pose4_to_pose7([9, 0, 0, 0])), "")
        assert node._hold_for_placement(1.0) and not node.fresh.placed
        node._publish_control_pose(1.025, np.zeros(4))  # the next tick's control pose
        assert not node._hold_for_placement(1.025) and node.fresh.placed
        assert node.smoother.applied(1.025)[0] == 9.0  # taken at once


def test_a_live_agent_does_not_wait_for_a_base_station_out_of_reach(
    endpoint: str,
    caplog,  # noqa: ANN001
) -> None:
    """A run's config.toml (lock-step sim clock, exploration on) copied to a drone, as
    operations.md says: a live agent restarted out of radio range had waited 10 s for the
    base station before flying on. Only an exploring simulator's agent (`--await-base`,
    which `collabslam run` sets) waits for it."""
    cfg = load_config(overrides={"sim.sync_wait_s": 0.3})
    for await_base in (False, True):
        with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
            AgentNode(cfg, "r0", bus, np.zeros((0, 2)), np.zeros(4), NullVehicle()).start(
                await_base=await_base
            )
        assert ("no base station after" in caplog.text) == await_base


def test_a_run_refuses_zenoh_endpoints_of_its_own(tmp_path) -> None:  # noqa: ANN001
    """`collabslam run` gives each process its own endpoints: one from the config had
    every process listen on it, the second died ("address in use"), the run was lost."""
    cfg = load_config(overrides={"zenoh.listen": ["tcp/127.0.0.1:7511"]})
    with pytest.raises(ConfigError, match="zenoh.listen"):
        Launcher(cfg, "rooms15", 2, tmp_path, 10.0)
