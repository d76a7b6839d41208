"""Round trips for every message type; malformed input raises ProtocolError."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from common.errors import ProtocolError
from common.geometry import pose4_to_pose7
from protocol import (
    SCHEMA_VERSION,
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
    decode,
    encode,
)
from protocol.keyframe_payloads import NO_READING_MM
from protocol.keys import Keys
from protocol.messages import message_types

P7 = pose4_to_pose7([1.0, -2.0, 0.5, 0.3])


def samples() -> list:
    scan = Scan2D.from_ranges(-2.356, 0.00436, 30.0, np.linspace(0.5, 29.0, 1081))
    return [
        LaserScan(
            "r0", 1.25, -2.356, 0.00436, 0.1, 30.0, np.array([1.0, np.nan, np.inf, 3.0], np.float32)
        ),
        Odometry("r0", 1.25, P7, np.array([0.5, 0.0, 0.0, 0.1])),
        Imu("r0", 1.25, np.zeros(3), np.array([0, 0, 9.81]), np.array([0, 0, 0, 1.0])),
        Altimeter("r0", 1.25, 1.02),
        VehicleCommand("r0", 1.25, 0.5, 0.0, 0.1, -0.2),
        Keyframe(
            "r0", 7, 1.25, P7, pose4_to_pose7([0.2, 0, 0, 0.01]), np.eye(6) * 1e-4, scan, None
        ),
        Keyframe(
            "uav-2",
            0,
            3.0,
            P7,
            pose4_to_pose7([0, 0, 0, 0]),
            np.eye(6) * 1e-4,
            None,
            Cloud3D(np.random.default_rng(0).normal(size=(100, 3)).astype("f4")),
        ),
        KeyframeAck("r0", 7),
        PoseCorrection("r0", 3, 10.0, P7),
        Goal("r0", 1, 2.0, "odom", 3, P7),
        Path("r0", 2, 2.0, "odom", 3, np.zeros((5, 4), np.float32)),
        RobotState("r0", 2.0, "flying", 3, 10, 9, 1, P7, P7),
        ClockSync("sim", 12.5),
        Neighbours("r0", 2.0, np.array([1.9]), np.array([[1.0, 2.0]]), np.array([[0.5, 0.0]])),
        ControlPose("r0", 2.025, 4, 0.93, P7, P7, pose4_to_pose7([1.1, -2.0, 0.5, 0.31])),
        GnssFix("r0", 2.0, np.array([45.8118, 16.0106, 160.5]), np.array([1.5, 1.5, 3.0])),
    ]


def assert_same(a, b) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if dataclasses.is_dataclass(x):
            assert_same(x, y)
        elif isinstance(x, np.ndarray):
            assert x.dtype == y.dtype or f.metadata["dtype"] == y.dtype.newbyteorder("<")
            np.testing.assert_array_equal(x.astype(y.dtype), y)
        else:
            assert x == y, f.name


@pytest.mark.parametrize("msg", samples(), ids=lambda m: type(m).__name__)
def test_round_trip(msg) -> None:
    out = decode(encode(msg), type(msg))
    assert_same(msg, out)


def test_every_message_type_has_a_round_trip() -> None:
    assert {type(m).__name__ for m in samples()} == set(message_types())


def test_arrays_travel_as_typed_binary() -> None:
    kf = samples()[5]
    env = msgpack.unpackb(encode(kf), raw=False)
    shape, raw = env["d"]["scan2d"]["ranges_mm"]
    assert shape == [1081] and isinstance(raw, bytes) and len(raw) == 2 * 1081
    assert len(encode(kf)) < 3000  # 1081 beams as uint16 mm, not a list of floats


def test_scan_quantization() -> None:
    s = Scan2D.from_ranges(0.0, 0.1, 30.0, np.array([1.2345, np.nan, 30.0, -1.0, np.inf]))
    r = s.ranges()
    assert r[0] == pytest.approx(1.2345, abs=5e-4)
    assert np.all(np.isnan(r[1:]))
    # ROS's -inf ("too close") is no reading, not a no return that clears 10 m of space
    s = Scan2D.from_ranges(0.0, 0.1, 30.0, np.array([np.nan, np.inf, -np.inf]))
    assert s.ranges_mm.tolist() == [0, 0, NO_READING_MM]


def _env(t: str, d: dict, v: int = SCHEMA_VERSION) -> bytes:
    return msgpack.packb({"v": v, "t": t, "d": d}, use_bin_type=True)


def _good_ack() -> dict:
    return msgpack.unpackb(encode(KeyframeAck("r0", 3)), raw=False)["d"]


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"\xc1\x00\x01", "malformed"),
        (encode(KeyframeAck("r0", 3))[:-2], "malformed"),
        (b"", "malformed"),
        (msgpack.packb([1, 2, 3]), "envelope"),
        (_env("KeyframeAck", _good_ack(), v=99), "schema version"),
        (_env("KeyframeAck", _good_ack(), v=0), "schema version"),
        (_env("KeyframeAck", _good_ack(), v=True), "schema version"),
        (_env("Nope", _good_ack()), "unknown message type"),
        (_env("KeyframeAck", {"robot_id": "r0"}), "missing"),
        (_env("KeyframeAck", {**_good_ack(), "x": 1}), "unknown fields"),
        (_env("KeyframeAck", {"robot_id": "r0", "acked_seq": "7"}), "integer"),
        (_env("KeyframeAck", {"robot_id": "../../x", "acked_seq": 7}), "robot_id"),
    ],
)
def test_bad_payloads_raise_protocol_error(payload: bytes, reason: str) -> None:
    with pytest.raises(ProtocolError, match=reason):
        decode(payload)


def test_nan_and_shape_and_size_rejected() -> None:
    good = encode(Odometry("r0", 1.0, P7, np.zeros(4)))
    d = msgpack.unpackb(good, raw=False)["d"]
    bad = dict(d, twist=[[4], np.array([0, np.nan, 0, 0]).astype("<f8").tobytes()])
    with pytest.raises(ProtocolError, match="NaN"):
        decode(_env("Odometry", bad))
    bad = dict(d, twist=[[3], np.zeros(3).astype("<f8").tobytes()])
    with pytest.raises(ProtocolError, match="shape"):
        decode(_env("Odometry", bad))
    bad = dict(d, twist=[[4], b"\x00" * 5])
    with pytest.raises(ProtocolError, match="bytes"):
        decode(_env("Odometry", bad))
    bad = dict(d, stamp=float("nan"))
    with pytest.raises(ProtocolError, match="finite"):
        decode(_env("Odometry", bad))
    with pytest.raises(ProtocolError, match="exceeds"):
        decode(good, max_bytes=10)


def test_semantic_checks() -> None:
    with pytest.raises(ProtocolError, match="quaternion"):
        decode(encode(PoseCorrection("r0", 1, 0.0, np.array([0, 0, 0, 0, 0, 0, 2.0]))))
    with pytest.raises(ProtocolError, match="ControlPose.alpha"):
        decode(encode(ControlPose("r0", 1.0, 0, 1.5, P7, P7, P7)))
    with pytest.raises(ProtocolError, match="ControlPose.pose_map_raw"):
        decode(encode(ControlPose("r0", 1.0, 0, 0.5, P7, P7, np.zeros(7))))
    with pytest.raises(ProtocolError, match="exactly one"):
        decode(encode(Keyframe("r0", 0, 0.0, P7, P7, np.eye(6), None, None)))
    with pytest.raises(ProtocolError, match="differ in length"):
        decode(encode(Neighbours("r0", 1.0, np.zeros(2), np.zeros((1, 2)), np.zeros((1, 2)))))
    with pytest.raises(ProtocolError, match="sender"):
        decode(encode(ClockSync("intruder", 1.0)))
    with pytest.raises(ProtocolError, match="stamp"):
        decode(encode(ClockSync("sim", -1.0)))
    with pytest.raises(ProtocolError, match="expected a KeyframeAck"):
        decode(encode(Altimeter("r0", 0.0, 1.0)), KeyframeAck)


def test_keys_layout() -> None:
    k = Keys("fleet1")
    assert k.robot("r1", "keyframe") == "collabslam/fleet1/robot/r1/keyframe"
    assert k.robot("r1", "pose/control") == "collabslam/fleet1/robot/r1/pose/control"
    assert k.sensor("r1", "scan") == "collabslam/fleet1/robot/r1/sensor/scan"
    assert k.robot_id_of("collabslam/fleet1/robot/r1/sensor/scan") == "r1"
    assert k.clock("sim") == "collabslam/fleet1/clock/sim"
    assert k.robot_id_of(k.clock("basestation")) is None
    assert k.robot_id_of("collabslam/other/robot/r1/keyframe") is None
    with pytest.raises(Exception, match="invalid"):
        k.robot("a/b", "keyframe")


def test_gnss_fix_validation() -> None:
    sig = np.array([1.5, 1.5, 3.0])
    with pytest.raises(ProtocolError, match="latitude"):
        GnssFix("r0", 1.0, np.array([91.0, 0.0, 0.0]), sig).validate()
    with pytest.raises(ProtocolError, match="sigmas"):
        GnssFix("r0", 1.0, np.array([45.0, 16.0, 0.0]), np.array([1.5, 0.0, 3.0])).validate()
    assert Keys("f").sensor("r0", "gnss") == "collabslam/f/robot/r0/sensor/gnss"


def _keyframe(delta_xy: float = 0.2, cov=None, range_max: float = 30.0) -> Keyframe:
    scan = Scan2D.from_ranges(-2.356, 0.00436, 30.0, np.linspace(0.5, 29.0, 1081))
    scan = dataclasses.replace(scan, range_max=range_max)
    cov = np.eye(6) * 1e-4 if cov is None else cov
    return Keyframe("r0", 1, 1.0, P7, pose4_to_pose7([delta_xy, 0, 0, 0]), cov, scan, None)


def _not_positive_definite() -> np.ndarray:
    cov = np.eye(6) * 1e-4
    cov[0, 1] = cov[1, 0] = 2e-4
    return cov


def _nearly_singular() -> np.ndarray:
    """x and y correlated to 1 - 1e-12: numpy's Cholesky takes it, the graph did not."""
    cov = np.eye(6) * 1e-4
    cov[0, 1] = cov[1, 0] = 1e-4 * (1.0 - 1e-12)
    return cov


def _scan_angles(angle_min: float, increment: float) -> Keyframe:
    kf = _keyframe()
    return dataclasses.replace(
        kf, scan2d=dataclasses.replace(kf.scan2d, angle_min=angle_min, angle_increment=increment)
    )


def _slightly_asymmetric() -> np.ndarray:
    cov = np.eye(6) * 1e-4
    cov[0, 1], cov[1, 0] = 1e-5, 1e-5 + 5e-9  # within allclose's 1e-5 relative
    return cov


@pytest.mark.parametrize(
    "kf, reason",
    [
        (_keyframe(cov=_not_positive_definite()), "not positive definite"),
        (_keyframe(cov=np.eye(6) * 1e-300), "variances"),
        (_keyframe(cov=np.eye(6) * 1e300), "variances"),
        (_keyframe(delta_xy=1e7), "moves"),
        (_keyframe(range_max=-5.0), "range_max"),
        (_keyframe(cov=_slightly_asymmetric()), "symmetric"),  # (graph: "must be symmetric")
        (_keyframe(cov=_nearly_singular()), "nearly singular"),  # at every restart too
        # float32 angles of inf in the map: the base station stopped, at every restart
        (_scan_angles(-2.356, 1e37), "one turn at most"),
        (_scan_angles(1e20, 0.00436), "one turn at most"),
        (_scan_angles(-2.356, 0.0), "angle_increment is 0"),
    ],
)
def test_keyframes_the_pose_graph_cannot_take_are_refused(kf: Keyframe, reason: str) -> None:
    """Each of these, once admitted, had made iSAM2 (or the map) fail and the base
    station exit: now decoding refuses them and the bus drops them with a log line."""
    with pytest.raises(ProtocolError, match=reason):
        decode(encode(kf))
    decode(encode(_keyframe()))  # the same keyframe with sane values passes


def test_states_odometry_and_heights_out_of_bounds_are_refused() -> None:
    """A state's pose of 1e308 m had poisoned the neighbours' relay (velocities NaN, every
    answer refused by the agents) and, with GNSS starts, stopped the base station; an
    odometry twist of 1e155 m/s had raised in the agent's safety guard."""
    far = pose4_to_pose7([1e308, 0.0, 0.0, 0.0])
    for odom, world in ((far, P7), (P7, far)):
        with pytest.raises(ProtocolError, match="RobotState.pose_"):
            decode(encode(RobotState("r1", 1.0, "flying", 3, 1, 1, 0, odom, world)))
    decode(encode(RobotState("r1", 1.0, "flying", 3, 1, 1, 0, P7, P7)))
    with pytest.raises(ProtocolError, match="Odometry.twist"):
        decode(encode(Odometry("r0", 1.0, P7, np.array([1e155, 0.0, 0.0, 0.0]))))
    decode(encode(Odometry("r0", 1.0, P7, np.array([30.0, 0.0, 0.0, 3.0]))))
    with pytest.raises(ProtocolError, match="Altimeter.altitude"):  # (the agent's state
        decode(encode(Altimeter("r0", 1.0, 1e9)))  # had carried it, and been refused)
    with pytest.raises(ProtocolError, match="below the ground"):  # NED's z: it had climbed
        decode(encode(Altimeter("r0", 1.0, -1.0)))  # for good
    decode(encode(Altimeter("r0", 1.0, -0.05)))  # (noise on the ground)


def test_an_attitude_in_w_first_order_is_refused_where_it_shows() -> None:
    """PX4 orders its quaternions w, x, y, z: a level drone yawed 0.3 rad, read as x, y, z,
    w, is rolled 163 degrees (its scans levelled onto the other side, its odometry never
    turning, no line in any log). An attitude beyond 60 degrees of level is refused; a
    real drone's few degrees pass."""
    yaw = 0.3
    xyzw = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    wxyz = np.roll(xyzw, 1)
    with pytest.raises(ProtocolError, match="w, x, y, z order"):
        decode(encode(Imu("r0", 1.0, np.zeros(3), np.zeros(3), wxyz)))
    with pytest.raises(ProtocolError, match="Odometry.pose: the body tilted 163 degrees"):
        decode(encode(Odometry("r0", 1.0, np.r_[0.0, 0.0, 1.0, wxyz], np.zeros(4))))
    tilted = Rotation.from_euler("xyz", [0.5, -0.6, 2.0]).as_quat()  # 29 and 34 degrees
    decode(encode(Imu("r0", 1.0, np.zeros(3), np.zeros(3), tilted)))
    decode(encode(Imu("r0", 1.0, np.zeros(3), np.zeros(3), xyzw)))


def test_positions_beyond_ten_thousand_km_are_refused() -> None:
    """A correction of 1.5e308 m had made every command of the drone NaN, and a path
    waypoint of 1e9 m sent it off toward it."""
    far = pose4_to_pose7([1.5e308, 0.0, 0.0, 0.0])
    with pytest.raises(ProtocolError, match="beyond"):
        decode(encode(PoseCorrection("r0", 1, 0.0, far)))
    wp = np.array([[1.0, 1.0, 1.0, 0.0], [1e9, 1.0, 1.0, 0.0]], dtype=np.float32)
    with pytest.raises(ProtocolError, match="beyond"):
        decode(encode(Path("r0", 1, 0.0, "map", 1, wp)))
    decode(encode(Path("r0", 1, 0.0, "map", 1, wp[:1])))  # a sane one passes
    decode(encode(PoseCorrection("r0", 1, 0.0, pose4_to_pose7([5e6, 0.0, 0.0, 0.0]))))


def test_a_version_1_message_is_read_with_the_fields_added_since_at_their_defaults() -> None:
    """Version 2 only added fields with defaults: an agent, or a database, of version 1
    (before 2026-12-05) is read; refused, such a database had failed its restore."""
    d = msgpack.unpackb(encode(VehicleCommand("r0", 1.25, 0.5, 0.0, 0.1, -0.2)), raw=False)["d"]
    for later in ("keyframes_sent", "state_stamp"):
        d.pop(later, None)
    cmd = decode(_env("VehicleCommand", d, v=1), VehicleCommand)
    assert (cmd.vx, cmd.keyframes_sent, cmd.state_stamp) == (0.5, 0, -1.0)
