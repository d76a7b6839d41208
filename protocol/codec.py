"""msgpack encoding of protocol dataclasses, with strict validation on decode.

Wire format: a msgpack map ``{"v": SCHEMA_VERSION, "t": <type name>, "d": {...}}``.
Numpy array fields travel as ``[shape, raw little-endian bytes]`` of a fixed
dtype declared on the field (float32, uint16, ...), never as lists of floats.
Nested message dataclasses (e.g. ``Scan2D`` inside ``Keyframe``) are maps.

Decoding checks, in order: size limit, msgpack validity, envelope, schema
version, type, every field's presence (a field with a default may be absent: added
later, an older peer's message has none) and type, array dtype/shape, finiteness
of floats (unless the field allows non-finite values), then the message's own
``validate()``. Any failure raises ``ProtocolError`` saying what was wrong.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any, TypeVar

import msgpack
import numpy as np

from common.errors import ProtocolError

SCHEMA_VERSION = 2
# the oldest version read: 2 only added fields with defaults (and a message type), so a
# version-1 message (an agent, or a database, from before 2026-12-05) decodes as one of
# 2 without them; refused, a database of that age had failed its restore
OLDEST_READ_VERSION = 1
DEFAULT_MAX_BYTES = 8 * 1024 * 1024

T = TypeVar("T")
_REGISTRY: dict[str, type] = {}
_HINTS: dict[type, dict[str, Any]] = {}


def array_field(dtype: str, shape: tuple[int | None, ...], *, finite: bool = True) -> Any:
    """Declare an ndarray field: fixed dtype, shape with None for free dimensions."""
    return dataclasses.field(
        metadata={"dtype": np.dtype(dtype).newbyteorder("<"), "shape": shape, "finite": finite}
    )


def later_field(default: Any) -> Any:
    """Declare a field added to a message after peers that do not know it were out: left
    out of the encoding while it holds `default`, so those peers still read the message
    (they refuse fields they do not know)."""
    return dataclasses.field(default=default, metadata={"later": True})


def message(cls: type[T]) -> type[T]:
    """Class decorator: make a frozen dataclass and register it by name."""
    dc = dataclasses.dataclass(frozen=True, eq=False)(cls)
    _REGISTRY[cls.__name__] = dc
    return dc


def registered_types() -> dict[str, type]:
    return dict(_REGISTRY)


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _to_wire(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        out = {}
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if not (f.metadata.get("later") and _is_default(v, f)):
                out[f.name] = _field_to_wire(f, v)
        return out
    if isinstance(obj, (list, tuple)):
        return [_to_wire(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _is_default(value: Any, f: dataclasses.Field) -> bool:
    return value is None if f.default is None else bool(value == f.default)


def _field_to_wire(f: dataclasses.Field, value: Any) -> Any:
    if "dtype" in f.metadata:
        arr = np.ascontiguousarray(np.asarray(value, dtype=f.metadata["dtype"]))
        return [list(arr.shape), arr.tobytes()]
    return _to_wire(value)


def encode(msg: Any) -> bytes:
    """Encode a registered message dataclass to msgpack bytes."""
    name = type(msg).__name__
    if _REGISTRY.get(name) is not type(msg):
        raise ProtocolError(f"cannot encode {name}: not a registered protocol message")
    return msgpack.packb({"v": SCHEMA_VERSION, "t": name, "d": _to_wire(msg)}, use_bin_type=True)


def decode(
    payload: bytes | bytearray | memoryview,
    expected: type[T] | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> T:
    """Decode and validate one message; `expected` restricts the accepted type."""
    cls, data = _envelope(payload, expected, max_bytes)
    msg = _from_wire(cls, data, cls.__name__)
    try:
        msg.validate()
    except ProtocolError:
        raise
    except Exception as exc:
        raise ProtocolError(f"{cls.__name__}: invalid content: {exc}") from None
    return msg


def decode_field(payload: bytes | bytearray | memoryview, expected: type, name: str) -> Any:
    """Field `name` of an `expected` message, the other fields left undecoded: for
    payloads this program validated before it stored them (~30 us for a keyframe's
    scan, a whole keyframe ~400 us). Envelope and field are checked as by `decode`;
    the message's `validate()` is not run."""
    cls, data = _envelope(payload, expected, len(payload))
    f = {f.name: f for f in dataclasses.fields(cls)}.get(name)
    if f is None:
        raise ProtocolError(f"{cls.__name__} has no field {name!r}")
    if not isinstance(data, dict) or name not in data:
        raise ProtocolError(f"{cls.__name__}: missing field {name!r}")
    return _field_from_wire(f, _hints(cls)[name], data[name], f"{cls.__name__}.{name}")


def relabel(payload: bytes, expected: type, **values: Any) -> bytes:
    """A payload this program encoded (and validated) with some top-level fields
    replaced, the others left as they are, without decoding it (~4 us for a keyframe,
    a whole decode ~100 us). The new values are not validated."""
    cls, data = _envelope(payload, expected, len(payload))
    if not isinstance(data, dict):
        raise ProtocolError(f"{cls.__name__}: expected a map")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if unknown := set(values) - set(fields):
        raise ProtocolError(f"{cls.__name__} has no fields {sorted(unknown)}")
    data.update({k: _field_to_wire(fields[k], v) for k, v in values.items()})
    return msgpack.packb({"v": SCHEMA_VERSION, "t": cls.__name__, "d": data}, use_bin_type=True)


def _envelope(
    payload: bytes | bytearray | memoryview, expected: type | None, max_bytes: int
) -> tuple[type, Any]:
    """The message class and its undecoded fields, after the size, msgpack, envelope,
    version and type checks."""
    n = len(payload)
    if n > max_bytes:
        raise ProtocolError(f"message of {n} bytes exceeds the limit of {max_bytes} bytes")
    try:
        env = msgpack.unpackb(
            bytes(payload),
            raw=False,
            strict_map_key=True,
            max_bin_len=max_bytes,
            max_str_len=1 << 16,
            max_array_len=1 << 20,
            max_map_len=1 << 10,
        )
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise ProtocolError(f"malformed msgpack: {exc}") from None
    if not isinstance(env, dict) or set(env) != {"v", "t", "d"}:
        raise ProtocolError("malformed envelope: expected a map with keys v, t, d")
    v = env["v"]
    if not (type(v) is int and OLDEST_READ_VERSION <= v <= SCHEMA_VERSION):
        raise ProtocolError(f"unsupported schema version {v!r} (this build reads "
                            f"{OLDEST_READ_VERSION} to {SCHEMA_VERSION})")  # fmt: skip
    name = env["t"]
    cls = _REGISTRY.get(name) if isinstance(name, str) else None
    if cls is None:
        raise ProtocolError(f"unknown message type {name!r}")
    if expected is not None and cls is not expected:
        raise ProtocolError(f"expected a {expected.__name__} message, got {name}")
    return cls, env["d"]


def _from_wire(cls: type, data: Any, path: str) -> Any:
    if not isinstance(data, dict):
        raise ProtocolError(f"{path}: expected a map")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    missing = {n for n, f in fields.items() if n not in data and _required(f)}
    extra = set(data) - set(fields)
    if missing:
        raise ProtocolError(f"{path}: missing fields {sorted(missing)}")
    if extra:  # names may be bytes as well as str: sort their reprs
        raise ProtocolError(f"{path}: unknown fields {sorted(map(repr, extra))}")
    hints = _hints(cls)
    kwargs = {
        name: _field_from_wire(f, hints[name], data[name], f"{path}.{name}")
        for name, f in fields.items()
        if name in data
    }
    return cls(**kwargs)


def _required(f: dataclasses.Field) -> bool:
    """A field without a default must be on the wire; one with a default (added later,
    e.g. `Keyframe.chain`) may be missing from an older peer's message or database."""
    return f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING


def _field_from_wire(f: dataclasses.Field, hint: Any, value: Any, path: str) -> Any:
    if "dtype" in f.metadata:
        return _array_from_wire(f.metadata, value, path)
    return _value_from_wire(hint, value, path)


def _value_from_wire(hint: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _value_from_wire(inner[0], value, path)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ProtocolError(f"{path}: expected a number, got {type(value).__name__}")
        if not math.isfinite(value):
            raise ProtocolError(f"{path}: expected a finite number, got {value}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ProtocolError(f"{path}: expected an integer, got {type(value).__name__}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ProtocolError(f"{path}: expected a boolean, got {type(value).__name__}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise ProtocolError(f"{path}: expected a string, got {type(value).__name__}")
        return value
    if dataclasses.is_dataclass(hint):
        return _from_wire(hint, value, path)
    raise ProtocolError(f"{path}: unsupported field type {hint!r}")  # pragma: no cover


def _array_from_wire(meta: dict, value: Any, path: str) -> np.ndarray:
    if (
        not isinstance(value, list)
        or len(value) != 2
        or not isinstance(value[0], list)
        or not isinstance(value[1], bytes)
    ):
        raise ProtocolError(f"{path}: expected [shape, bytes] for an array")
    shape, raw = value
    spec: tuple[int | None, ...] = meta["shape"]
    if len(shape) != len(spec) or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape
    ):
        raise ProtocolError(f"{path}: expected an array of {len(spec)} dims, got shape {shape}")
    for got, want in zip(shape, spec, strict=True):
        if want is not None and got != want:
            raise ProtocolError(f"{path}: expected shape {spec}, got {tuple(shape)}")
    dtype: np.dtype = meta["dtype"]
    count = math.prod(shape)
    if len(raw) != count * dtype.itemsize:
        raise ProtocolError(
            f"{path}: {len(raw)} bytes do not hold a {dtype} array of shape {tuple(shape)}"
        )
    arr = np.frombuffer(raw, dtype=dtype).reshape(shape).astype(dtype.newbyteorder("="))
    if meta["finite"] and arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise ProtocolError(f"{path}: contains NaN or infinite values")
    return arr
