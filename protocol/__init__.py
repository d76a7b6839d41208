"""Messages between collabslam processes, their msgpack codec and the key layout."""

from protocol.codec import DEFAULT_MAX_BYTES, SCHEMA_VERSION, decode, encode
from protocol.keys import Keys
from protocol.messages import (
    Altimeter,
    ClockSync,
    Cloud3D,
    ControlPose,
    GnssFix,
    Goal,
    Imu,
    Keyframe,
    KeyframeAck,
    LaserScan,
    Neighbours,
    Odometry,
    Path,
    PoseCorrection,
    RobotState,
    Scan2D,
    VehicleCommand,
)

__all__ = [
    "DEFAULT_MAX_BYTES",
    "SCHEMA_VERSION",
    "decode",
    "encode",
    "Keys",
    "Altimeter",
    "ClockSync",
    "Cloud3D",
    "ControlPose",
    "GnssFix",
    "Goal",
    "Imu",
    "Keyframe",
    "KeyframeAck",
    "LaserScan",
    "Neighbours",
    "Odometry",
    "Path",
    "PoseCorrection",
    "RobotState",
    "Scan2D",
    "VehicleCommand",
]
