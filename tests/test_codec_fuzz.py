"""Fuzz the protocol decoder: whatever the bytes, `decode` returns a valid registered
message or raises `ProtocolError`, never another exception.

Four generators, several thousand cases in all (seeded: `derandomize=True`):
arbitrary bytes; byte-level mutations of valid encodings of every message type
(flips, truncations, insertions, splices); structure-level mutations (a field of a
valid envelope replaced by an arbitrary msgpack value, or dropped, or an extra one
added); and msgpack of random nested structures, bare or inside a well-formed
envelope of a registered type.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common.errors import ProtocolError
from common.geometry import pose4_to_pose7
from protocol import (
    Altimeter,
    Cloud3D,
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
from protocol.codec import SCHEMA_VERSION, registered_types

FUZZ = settings(
    max_examples=900,
    derandomize=True,
    database=None,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
P7 = pose4_to_pose7([1.0, -2.0, 0.5, 0.3])


def _valid_messages() -> list:
    scan = Scan2D.from_ranges(-2.356, 0.0436, 30.0, np.linspace(0.5, 29.0, 109))
    return [
        LaserScan("r0", 1.25, -2.356, 0.0436, 0.1, 30.0, np.array([1.0, np.nan, 3.0], "f4")),
        Odometry("r0", 1.25, P7, np.array([0.5, 0.0, 0.0, 0.1])),
        Imu("r0", 1.25, np.zeros(3), np.array([0, 0, 9.81]), np.array([0, 0, 0, 1.0])),
        Altimeter("r0", 1.25, 1.02),
        VehicleCommand("r0", 1.25, 0.5, 0.0, 0.1, -0.2),
        Keyframe("r0", 7, 1.25, P7, pose4_to_pose7([0.2, 0, 0, 0.01]), np.eye(6), scan, None),
        Keyframe("r1", 0, 3.0, P7, P7, np.eye(6), None, Cloud3D(np.ones((5, 3), np.float32))),
        KeyframeAck("r0", 7),
        PoseCorrection("r0", 3, 2.0, P7),
        Goal("r0", 1, 2.0, "map", 3, P7),
        Path("r0", 1, 2.0, "odom", 3, np.zeros((4, 4), np.float32)),
        RobotState("r0", 2.0, "flying", 3, 10, 9, 1, P7, P7),
        Neighbours("r0", 2.0, np.array([1.9]), np.array([[1.0, 2.0]]), np.array([[0.5, 0.0]])),
    ]


VALID = [encode(m) for m in _valid_messages()]
ENVELOPES = [msgpack.unpackb(b, raw=False) for b in VALID]
TYPES = list(registered_types().values())

# Any value msgpack can carry (including ext types, big ints, NaN, bytes map keys).
SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.binary(max_size=64),
    st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=8)),
)
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.one_of(
        st.lists(inner, max_size=6),
        st.dictionaries(st.one_of(st.text(max_size=8), st.binary(max_size=4)), inner, max_size=6),
    ),
    max_leaves=20,
)


def _check(payload: bytes, expected: type | None = None, max_bytes: int = 1 << 20) -> None:
    try:
        msg = decode(payload, expected, max_bytes)
    except ProtocolError:
        return
    # Accepted: it must be a registered, valid message that re-encodes and decodes equal.
    assert type(msg) in TYPES
    again = decode(encode(msg), type(msg))
    assert type(again) is type(msg)


def _pack(obj: object) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


@settings(FUZZ, max_examples=1500)
@given(st.binary(max_size=512), st.sampled_from([None, *TYPES]))
def test_arbitrary_bytes_raise_only_protocol_error(data: bytes, expected: type | None) -> None:
    _check(data, expected)


@FUZZ
@given(
    st.sampled_from(VALID),
    st.lists(
        st.tuples(
            st.sampled_from(["flip", "truncate", "insert", "delete", "splice"]),
            st.integers(min_value=0, max_value=10_000),
            st.binary(min_size=1, max_size=8),
        ),
        min_size=1,
        max_size=4,
    ),
    st.sampled_from([None, Keyframe, LaserScan]),
    st.sampled_from([1 << 20, 64]),
)
def test_mutated_encodings_raise_only_protocol_error(
    payload: bytes, edits: list[tuple[str, int, bytes]], expected: type | None, max_bytes: int
) -> None:
    buf = bytearray(payload)
    for op, pos, blob in edits:
        i = pos % (len(buf) + 1)
        if op == "flip" and buf:
            buf[i % len(buf)] ^= blob[0] or 0xFF
        elif op == "truncate":
            del buf[i:]
        elif op == "insert":
            buf[i:i] = blob
        elif op == "delete":
            del buf[i : i + len(blob)]
        else:  # splice in a piece of another valid message
            other = VALID[pos % len(VALID)]
            buf[i:] = other[len(other) // 2 :]
    _check(bytes(buf), expected, max_bytes)


def _fields_of(env: dict) -> list[tuple[str, ...]]:
    """Paths to every field of the envelope's data, nested messages included."""
    out: list[tuple[str, ...]] = []

    def walk(d: dict, path: tuple[str, ...]) -> None:
        for k, v in d.items():
            out.append((*path, k))
            if isinstance(v, dict):
                walk(v, (*path, k))

    walk(env["d"], ())
    return out


@FUZZ
@given(
    st.integers(min_value=0, max_value=len(ENVELOPES) - 1),
    st.integers(min_value=0, max_value=1000),
    st.sampled_from(["replace", "drop", "extra", "envelope"]),
    VALUES,
    st.one_of(st.text(max_size=4), st.binary(max_size=4)),
)
def test_mutated_fields_raise_only_protocol_error(
    which: int, field_pick: int, op: str, value: object, key: str | bytes
) -> None:
    env = msgpack.unpackb(VALID[which], raw=False)
    paths = _fields_of(env)
    path = paths[field_pick % len(paths)]
    parent = env["d"]
    for k in path[:-1]:
        parent = parent[k]
    if op == "replace":
        parent[path[-1]] = value
    elif op == "drop":
        del parent[path[-1]]
    elif op == "extra":  # unknown fields, possibly with non-string names
        parent[key] = value
        parent[f"x{field_pick}"] = value
    else:
        env[("v", "t", "d")[field_pick % 3]] = value
    _check(_pack(env))


@settings(FUZZ, max_examples=700)
@given(
    VALUES,
    st.sampled_from([None, *[t.__name__ for t in TYPES]]),
    st.sampled_from([None, *TYPES]),
)
def test_random_structures_raise_only_protocol_error(
    obj: object, type_name: str | None, expected: type | None
) -> None:
    if type_name is None:
        _check(_pack(obj), expected)
    else:  # a well-formed envelope of a registered type around random data
        _check(_pack({"v": SCHEMA_VERSION, "t": type_name, "d": obj}), expected)


def test_fuzz_inputs_do_reach_the_decoder_checks() -> None:
    """The generators are not trivially rejected: valid encodings decode, and a single
    field replaced by a wrong type is reported by name."""
    for payload in VALID:
        assert type(decode(payload)) in TYPES
    env = msgpack.unpackb(VALID[5], raw=False)
    env["d"]["seq"] = math.pi
    try:
        decode(_pack(env))
    except ProtocolError as exc:
        assert "Keyframe.seq" in str(exc)
    else:
        raise AssertionError("a float seq was accepted")
