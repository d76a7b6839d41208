"""What an agent takes from its inputs: the IMU's roll and pitch reach the projection of
its scans (SPEC §1, roll/pitch compensation), and a correction older than the one it
has is not taken."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from agent.node import AgentNode
from agent.vehicle import NullVehicle
from common.bus import Bus
from common.config import ZenohConfig, load_config
from common.geometry import pose4_to_pose7
from protocol import Imu, PoseCorrection


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
