"""Every message that crosses a process boundary, as versioned dataclasses.

Units: metres, radians, seconds. Stamps are sensor/sim time in seconds.
Poses travel as "pose7" arrays `[x, y, z, qx, qy, qz, qw]` (float64).
Frames (REP-105): each robot's local frame is `odom`; the global frame is
`map`; `base` is the vehicle body. `T_a_b` maps points from b into a.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from common.errors import ProtocolError
from protocol.checks import (
    check_covariance,
    check_frame,
    check_pose7,
    check_position,
    check_robot_id,
    check_scan_angles,
    check_upright,
)
from protocol.codec import array_field, later_field, message
from protocol.keyframe_payloads import Cloud3D, OdomOrigin, Scan2D

# What one keyframe may carry and the pose graph still solves (iSAM2 failed on a step of
# 2e4 m, on a variance of 1e4 m^2 or 1e3 rad^2, and on one of 1e-12): keyframes come
# every 0.2 m, and one spanning an outage of the link is still far inside these.
KEYFRAME_MAX_STEP_M = 1000.0  # m
KEYFRAME_VAR_RANGE = (1e-10, 100.0)  # m^2 or rad^2, each diagonal entry of delta_cov
MAX_CHAIN = 2**31 - 1  # keyframe chains (an agent starts one per base station that lost its)
# `session`, to and from an agent: its run, random when it starts afresh, kept when it
# resumes (0: it does not say); one trajectory segment each (basestation/robot_segments.py)
MAX_SESSION = 2**32 - 1
# m: a run whose odom frame begins this far from its odometry source's origin began in
# flight, in the source's frame of the robot's run before it (`OdomOrigin`)
IN_FLIGHT_M = 1.0
GNSS_ALTITUDE_RANGE_M = (-1000.0, 100_000.0)  # m above the ellipsoid
MAX_TWIST = 1000.0  # m/s or rad/s in an odometry's twist
# "stopped": an agent's last state as it stops (the base station logs a stop, not a loss)
ROBOT_STATUSES = (
    "starting", "waiting", "flying", "blocked", "hovering", "done", "landed", "stopped",
)  # fmt: skip


class Message:
    """Base of all messages: common validation hooks."""

    robot_id: str

    def validate(self) -> None:
        check_robot_id(self.robot_id)
        session = getattr(self, "session", 0)
        if not 0 <= session <= MAX_SESSION:
            raise ProtocolError(f"session must be in 0..{MAX_SESSION}, got {session}")


# --- simulator / driver sensor messages -------------------------------------------------


@message
class LaserScan(Message):
    """A planar laser scan in the sensor frame (beam i at angle_min + i*angle_increment).

    Ranges may hold NaN/inf (a driver's "no return"); the agent's preprocessing
    drops them. Values >= range_max mean no return.
    """

    robot_id: str
    stamp: float
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: np.ndarray = array_field("f4", (None,), finite=False)

    def validate(self) -> None:
        super().validate()
        if self.ranges.size == 0:
            raise ProtocolError("LaserScan.ranges is empty")
        if not (0.0 <= self.range_min < self.range_max):
            raise ProtocolError("LaserScan: expected 0 <= range_min < range_max")
        check_scan_angles("LaserScan", self.angle_min, self.angle_increment, self.ranges.size)


@message
class Odometry(Message):
    """Dead-reckoned pose of the vehicle in the odometry source's own frame, plus twist.

    twist: body-frame [vx, vy, vz, yaw_rate] (m/s, rad/s).
    """

    robot_id: str
    stamp: float
    pose: np.ndarray = array_field("f8", (7,))
    twist: np.ndarray = array_field("f8", (4,))

    def validate(self) -> None:
        super().validate()
        check_pose7("Odometry.pose", self.pose)
        check_upright("Odometry.pose", self.pose[3:7])
        if float(np.abs(self.twist).max()) > MAX_TWIST:  # (1e155 had raised in the guard)
            raise ProtocolError(f"Odometry.twist beyond {MAX_TWIST:g} m/s or rad/s")


@message
class Imu(Message):
    """Body-frame angular velocity (rad/s), specific force (m/s^2), attitude quaternion."""

    robot_id: str
    stamp: float
    angular_velocity: np.ndarray = array_field("f8", (3,))
    linear_acceleration: np.ndarray = array_field("f8", (3,))
    orientation: np.ndarray = array_field("f8", (4,))

    def validate(self) -> None:
        super().validate()
        norm = float(np.linalg.norm(self.orientation))
        if abs(norm - 1.0) > 1e-3:
            raise ProtocolError(f"Imu.orientation norm is {norm:.6f}, expected 1")
        check_upright("Imu.orientation", self.orientation)


# m: an altimeter reading below this is not a height above the ground (NED's z, down)
MIN_ALTITUDE_M = -0.5


@message
class Altimeter(Message):
    """Height (m) of the drone above the ground below it, up positive (not NED's z, not
    above sea level)."""

    robot_id: str
    stamp: float
    altitude: float

    def validate(self) -> None:
        super().validate()
        check_position("Altimeter.altitude", np.array([self.altitude]))  # (1e9 m: every
        # state and keyframe of the drone refused downstream)
        if self.altitude < MIN_ALTITUDE_M:  # (a NED z: the drone had climbed for good)
            raise ProtocolError(f"Altimeter.altitude {self.altitude:.2f} m: below the ground "
                                "(expected the height above the ground, up positive)")  # fmt: skip


@message
class GnssFix(Message):
    """A GNSS receiver fix: WGS84 position and its reported 1-sigma east, north, up
    (seed 000 eq. 4). lla = [lat deg, lon deg, alt m above the WGS84 ellipsoid]."""

    robot_id: str
    stamp: float
    lla: np.ndarray = array_field("f8", (3,))
    sigmas_enu: np.ndarray = array_field("f8", (3,))  # m

    def validate(self) -> None:
        super().validate()
        if abs(self.lla[0]) > 90.0 or abs(self.lla[1]) > 180.0:
            raise ProtocolError(f"GnssFix.lla: latitude/longitude out of range: {self.lla}")
        if self.lla[0] == 0.0 and self.lla[1] == 0.0:  # (had set the map's origin there)
            raise ProtocolError("GnssFix.lla at (0, 0): a receiver's output without a fix "
                                "(send fixes only once it has one)")  # fmt: skip
        if not GNSS_ALTITUDE_RANGE_M[0] <= self.lla[2] <= GNSS_ALTITUDE_RANGE_M[1]:
            # one of 1e9 m scaled east/north by ~158x
            raise ProtocolError(f"GnssFix.lla: altitude {self.lla[2]:g} m out of range")
        if np.any(self.sigmas_enu <= 0.0):
            raise ProtocolError(f"GnssFix.sigmas_enu must be > 0, got {self.sigmas_enu}")


@message
class VehicleCommand(Message):
    """Body-frame velocity set-point for the autopilot.

    `stamp` is the sensor stamp the command answers: in lock-step simulation it
    is the handshake that lets the simulator advance. `keyframes_sent` (the next
    keyframe's seq) and `state_stamp` (the latest RobotState's, -1: none) say what the
    agent has sent the base station by then: a lock-step base station waits for those
    before it answers the clock at `stamp` (basestation/lockstep.py).
    """

    robot_id: str
    stamp: float
    vx: float
    vy: float
    vz: float
    yaw_rate: float
    keyframes_sent: int = 0
    state_stamp: float = -1.0

    def validate(self) -> None:
        super().validate()
        if self.keyframes_sent < 0:
            raise ProtocolError(
                f"VehicleCommand.keyframes_sent must be >= 0, got {self.keyframes_sent}"
            )


# --- agent <-> base station ---------------------------------------------------------------


@message
class Keyframe(Message):
    """One keyframe streamed from an agent to the base station.

    pose_odom: T_odom_base at `stamp` (pose7). delta: motion since the previous
    keyframe, expressed in the previous keyframe's body frame (pose7); identity
    for seq 0. delta_cov: 6x6 covariance of delta, order [x, y, z, roll, pitch,
    yaw]. Exactly one of scan2d / cloud3d is set.

    chain: the agent's keyframe chain, 0 from its start. An agent whose keyframes were
    acknowledged by a base station that has since lost them (a new one, without the
    database) starts a new chain: what it kept, renumbered from seq 0 (agent/node.py).
    """

    robot_id: str
    seq: int
    stamp: float
    pose_odom: np.ndarray = array_field("f8", (7,))
    delta: np.ndarray = array_field("f8", (7,))
    delta_cov: np.ndarray = array_field("f8", (6, 6))
    scan2d: Scan2D | None = None
    cloud3d: Cloud3D | None = None
    chain: int = 0
    session: int = later_field(0)  # the agent's run (MAX_SESSION)
    odom_origin: OdomOrigin | None = later_field(None)  # None: no odometry (yet), older agent

    def validate(self) -> None:
        super().validate()
        if self.seq < 0:
            raise ProtocolError(f"Keyframe.seq must be >= 0, got {self.seq}")
        if not 0 <= self.chain <= MAX_CHAIN:
            raise ProtocolError(f"Keyframe.chain must be in 0..{MAX_CHAIN}, got {self.chain}")
        check_pose7("Keyframe.pose_odom", self.pose_odom)
        check_pose7("Keyframe.delta", self.delta)
        if (o := self.odom_origin) is not None:
            check_position("Keyframe.odom_origin", np.array([o.x, o.y]))
        if (self.scan2d is None) == (self.cloud3d is None):
            raise ProtocolError("Keyframe: exactly one of scan2d / cloud3d must be set")
        step = float(np.linalg.norm(self.delta[:3]))
        if step > KEYFRAME_MAX_STEP_M:
            raise ProtocolError(
                f"Keyframe.delta moves {step:.3g} m (> {KEYFRAME_MAX_STEP_M:g} m from one keyframe)"
            )
        check_covariance("Keyframe.delta_cov", cov := self.delta_cov)
        var = np.diag(cov)
        if var.min() < KEYFRAME_VAR_RANGE[0] or var.max() > KEYFRAME_VAR_RANGE[1]:
            raise ProtocolError(
                f"Keyframe.delta_cov variances {var.min():.3g}..{var.max():.3g} outside "
                f"{KEYFRAME_VAR_RANGE[0]:g}..{KEYFRAME_VAR_RANGE[1]:g}"
            )
        if (scan := self.scan2d) is not None:
            if not 0.0 < scan.range_max:
                raise ProtocolError(f"Keyframe.scan2d.range_max must be > 0, got {scan.range_max}")
            n = scan.ranges_mm.size
            check_scan_angles("Keyframe.scan2d", scan.angle_min, scan.angle_increment, n)


@message
class KeyframeAck(Message):
    """Cumulative acknowledgement: every keyframe of `chain` with seq <= acked_seq is
    safe. -1 with keyframes held: the base station has none of this chain's (an agent
    that had some acknowledged starts a new chain with what it kept)."""

    robot_id: str
    acked_seq: int
    chain: int = later_field(0)  # (sent always, agents before it refused every ack)
    session: int = later_field(0)


@message
class PoseCorrection(Message):
    """T_map_odom for one robot after a graph optimization; epoch increases."""

    robot_id: str
    epoch: int
    stamp: float
    T_map_odom: np.ndarray = array_field("f8", (7,))
    session: int = later_field(0)

    def validate(self) -> None:
        super().validate()
        check_pose7("PoseCorrection.T_map_odom", self.T_map_odom)


@message
class Goal(Message):
    """A navigation goal; `frame` is 'odom' (already in the robot's frame), 'map', or
    'wgs84': then pose is [lat_deg, lon_deg, alt_m, qx, qy, qz, qw] with the
    orientation in ENU (`common.geodesy.wgs84_pose_to_enu` converts it to `map`)."""

    robot_id: str
    goal_id: int
    stamp: float
    frame: str
    epoch: int
    pose: np.ndarray = array_field("f8", (7,))

    def validate(self) -> None:
        super().validate()
        check_frame(self.frame, ("odom", "map", "wgs84"))
        check_pose7("Goal.pose", self.pose)


@message
class Path(Message):
    """A path of [x, y, z, yaw] waypoints in `frame`; an empty path means stop and
    wait; an empty path with `path_id` 0 means the mission (exploration) is over."""

    robot_id: str
    path_id: int
    stamp: float
    frame: str
    epoch: int
    waypoints: np.ndarray = array_field("f4", (None, 4))
    session: int = later_field(0)

    def validate(self) -> None:
        super().validate()
        check_frame(self.frame)
        check_position("Path.waypoints", self.waypoints[:, :3])


@message
class RobotState(Message):
    """Periodic status an agent publishes for the base station, simulator and viewers."""

    robot_id: str
    stamp: float
    status: str
    correction_epoch: int
    keyframes_sent: int
    keyframes_acked: int
    outbox_len: int
    pose_odom: np.ndarray = array_field("f8", (7,))
    pose_map: np.ndarray = array_field("f8", (7,))
    chain: int = 0  # the keyframe chain keyframes_sent / keyframes_acked count in
    session: int = later_field(0)

    def validate(self) -> None:
        super().validate()
        if self.status not in ROBOT_STATUSES:
            raise ProtocolError(f"RobotState.status {self.status!r} not in {ROBOT_STATUSES}")
        check_pose7("RobotState.pose_odom", self.pose_odom)  # (relayed to the others, and
        check_pose7("RobotState.pose_map", self.pose_map)  # a GNSS start's local pose)


@message
class Neighbours(Message):
    """The other robots where they last said they were (`map` frame), relayed by the
    base station to `robot_id` in answer to each of its RobotStates, for its
    neighbour guard: one row per other robot with its state's stamp, position and
    velocity (from its last two states' odometry, turned into `map`)."""

    robot_id: str
    stamp: float  # the recipient's state this answers
    stamps: np.ndarray = array_field("f8", (None,))
    xy: np.ndarray = array_field("f8", (None, 2))
    velocity: np.ndarray = array_field("f8", (None, 2))
    session: int = later_field(0)

    def validate(self) -> None:
        super().validate()
        if not len(self.stamps) == len(self.xy) == len(self.velocity):
            raise ProtocolError("Neighbours: stamps, xy and velocity differ in length")


@message
class DownlinkMark(Message):
    """Lock-step simulation: what the base station has sent a robot by its answer to the
    clock at `stamp`: `paths` Path messages in all and the latest correction `epoch`
    (-1: none). The robot's next tick waits for those (agent/downlink_gate.py)."""

    robot_id: str
    stamp: float
    paths: int
    epoch: int
    session: int = later_field(0)


@message
class ClockSync:
    """Lock-step handshake between the simulator and the base station (sim time, s).

    The simulator puts `stamp` T on `clock/sim` and holds the clock; the base
    station answers T on `clock/basestation` once it has taken every keyframe it
    has, refreshed its map and run its exploration step for T.
    """

    sender: str  # "sim" or "basestation"
    stamp: float
    gnss_fixes: int = 0  # sim: GnssFix messages it published so far (the base station waits)

    def validate(self) -> None:
        if self.sender not in ("sim", "basestation"):
            raise ProtocolError(f"ClockSync.sender {self.sender!r} not in ('sim', 'basestation')")
        if self.stamp < 0.0:
            raise ProtocolError(f"ClockSync.stamp must be >= 0, got {self.stamp}")


@message
class ControlPose(Message):
    """The agent's pose for the flight controller, one per control tick (seed 000 §II).

    pose_map: smoothed T_map_base = blended T_map_odom · T_odom_base; pose_map_raw:
    the same with the latest correction applied at once; pose_odom: T_odom_base
    (never filtered). alpha: weight of the previous correction in the blend, eq. 2
    (0 when no blend runs); epoch: the latest correction's epoch (-1: none yet).
    """

    robot_id: str
    stamp: float
    epoch: int
    alpha: float
    pose_odom: np.ndarray = array_field("f8", (7,))
    pose_map: np.ndarray = array_field("f8", (7,))
    pose_map_raw: np.ndarray = array_field("f8", (7,))

    def validate(self) -> None:
        super().validate()
        if not 0.0 <= self.alpha <= 1.0:
            raise ProtocolError(f"ControlPose.alpha: expected a value in [0, 1], got {self.alpha}")
        for name in ("pose_odom", "pose_map", "pose_map_raw"):
            check_pose7(f"ControlPose.{name}", getattr(self, name))


def message_types() -> dict[str, Any]:
    """All top-level messages (for tests and docs)."""
    return {
        c.__name__: c
        for c in (
            LaserScan,
            Odometry,
            Imu,
            Altimeter,
            GnssFix,
            VehicleCommand,
            Keyframe,
            KeyframeAck,
            PoseCorrection,
            Goal,
            Path,
            RobotState,
            Neighbours,
            ClockSync,
            ControlPose,
        )
    }
