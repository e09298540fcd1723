"""msgpack codec with a schema version. Decoding validates everything (types, shapes, finite
numbers, sizes) and raises :class:`CodecError` for any bad payload, never another exception, so
that receivers can count and drop it.

Wire form: a msgpack map ``{"v": SCHEMA_VERSION, "type": <name>, <field>: <value>, ...}``;
arrays are raw little-endian float64 bytes (``bin``) of the field's fixed or leading shape.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable
from dataclasses import MISSING, fields
from typing import Any, cast

import msgpack
import numpy as np

from .messages import MESSAGE_TYPES, Message

SCHEMA_VERSION = 1
MAX_PAYLOAD = 256 * 1024  #: bytes; larger payloads are rejected
MAX_SAMPLES = 1000  #: max samples in an IMU batch
MAX_STR = 64  #: max length of ids and method names
MAX_SOURCES = 64  #: max components of a beacon's covariance by source, and labels per component
_TYPE_NAME = {cls: name for name, cls in MESSAGE_TYPES.items()}

#: an array field's shape: fixed, or a leading dimension n (None) and fixed inner dimensions
_Shape = tuple[int, ...] | tuple[None, *tuple[int, ...]]
#: a scalar field's validator: ``check(type name, field name, value)`` -> the checked value
_Validator = Callable[[str, str, Any], object]

#: per-type array fields and their shapes; None = leading dimension n (shared within the message)
_ARRAYS: dict[str, dict[str, _Shape]] = {
    "imu": {"t": (None,), "dt": (None,), "dtheta": (None, 3), "dvel": (None, 3)},
    "gnss": {"llh": (3,), "v_ned": (3,), "sigma_ned": (3,)},
    "lane": {},
    "uwb": {},
    "uwb_round": {"ranges": (None,)},
    "beacon": {"llh": (3,), "v_ned": (3,), "cov_pos": (3, 3)},
    "estimate": {"llh": (3,), "v_ned": (3,), "rpy": (3,), "cov_pos": (3, 3)},
    "diag": {},
}
_STRINGS = {"vehicle", "method", "a", "b", "source"}
_INTS = {"seq", "quality", "left", "right"}
_FLOATS = {"t", "sigma_v", "range_m"}


class CodecError(ValueError):
    """Malformed, truncated, oversized, wrong-typed or wrong-version payload."""


def encode(msg: Message) -> bytes:
    """Serialise a message."""
    name = _TYPE_NAME.get(type(msg))
    if name is None:
        raise CodecError(f"not a wire message: {type(msg).__name__}")
    out: dict[str, Any] = {"v": SCHEMA_VERSION, "type": name}
    for f in fields(msg):
        val = getattr(msg, f.name)
        if f.name in _ARRAYS[name]:
            out[f.name] = np.ascontiguousarray(val, dtype="<f8").tobytes()
        elif f.name == "sources":
            if val:  # absent when empty: beacons without the breakdown stay as they were
                out[f.name] = [[list(lab), np.ascontiguousarray(c, dtype="<f8").tobytes()] for lab, c in val]
        elif f.name == "constants":
            if val:
                out[f.name] = [[lab, np.ascontiguousarray(g, dtype="<f8").tobytes()] for lab, g in val]
        elif isinstance(val, (np.floating, np.integer)):
            out[f.name] = val.item()
        else:
            out[f.name] = val
    packed: bytes = msgpack.packb(out, use_bin_type=True)
    return packed


def _check_str(name: str, fname: str, val: Any) -> str:
    if not isinstance(val, str) or not 0 < len(val) <= MAX_STR:
        raise CodecError(f"{name}.{fname}: must be a string of 1-{MAX_STR} characters")
    return val


def _check_int(name: str, fname: str, val: Any) -> int:
    if val.__class__ is not int or not 0 <= val < 2**63:  # bool is an int subclass: refused
        raise CodecError(f"{name}.{fname}: must be a non-negative integer")
    return val


def _check_float(name: str, fname: str, val: Any) -> float:
    if (val.__class__ is not float and val.__class__ is not int) or not math.isfinite(val):
        raise CodecError(f"{name}.{fname}: must be a finite number")
    return float(val)


def _check_auth(name: str, fname: str, val: Any) -> bytes:
    if not isinstance(val, bytes) or len(val) > 1024:
        raise CodecError(f"{name}.auth: must be bytes (<= 1024)")
    return val


def _check_bool(name: str, fname: str, val: Any) -> bool:
    if not isinstance(val, bool):
        raise CodecError(f"{name}.first_stopped: must be a boolean")
    return val


def _check_counters(name: str, fname: str, val: Any) -> dict[str, int]:
    if not isinstance(val, dict) or not all(isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool)
                                             for k, v in val.items()):
        raise CodecError(f"{name}.counters: must map strings to integers")
    return val


def _check_status(name: str, fname: str, val: Any) -> dict[str, Any]:
    if not isinstance(val, dict) or not all(isinstance(k, str) for k in val):
        raise CodecError(f"{name}.status: must be a map with string keys")
    return val


def _check_peers(name: str, fname: str, val: Any) -> tuple[str, ...]:
    if not isinstance(val, (list, tuple)) or not 0 < len(val) <= MAX_SAMPLES:
        raise CodecError(f"{name}.peers: must be a list of 1-{MAX_SAMPLES} ids")
    return tuple(_check_str(name, fname, v) for v in val)


#: a flattened 3×3 matrix's elements above the diagonal and their mirror images below it
_UPPER, _LOWER = np.array([1, 2, 5]), np.array([3, 6, 7])

#: label tuples already found valid: a beacon's labels recur at every beacon (bounded)
_VALID_LABELS: set[tuple[str, ...]] = set()


def _check_labels(name: str, labels: Any) -> tuple[str, ...]:
    if isinstance(labels, list | tuple):
        key = tuple(labels)
        try:
            if key in _VALID_LABELS:
                return key
        except TypeError:  # an unhashable element: not a label anyway
            pass
    if not isinstance(labels, list | tuple) or not 0 < len(labels) <= MAX_SOURCES:
        raise CodecError(f"{name}.sources: labels must be a list of 1-{MAX_SOURCES} strings")
    if not all(isinstance(lab, str) and 0 < len(lab) <= 2 * MAX_STR + 1 for lab in labels):
        # a link's label joins two ids: "V0|V1"
        raise CodecError(f"{name}.sources: a label must be a string of 1-{2 * MAX_STR + 1} characters")
    if len(_VALID_LABELS) < 4096:
        _VALID_LABELS.add(key)
    return key


def _check_sources(name: str, fname: str, val: Any) -> tuple[tuple[tuple[str, ...], np.ndarray], ...]:
    if not isinstance(val, (list, tuple)) or len(val) > MAX_SOURCES:
        raise CodecError(f"{name}.sources: must be a list of at most {MAX_SOURCES} components")
    out: list[tuple[str, ...]] = []
    covs: list[bytes] = []
    for item in val:
        if not isinstance(item, (list, tuple)) or len(item) != 2:
            raise CodecError(f"{name}.sources: each component must be [labels, covariance]")
        labels, cov = item
        out.append(_check_labels(name, labels))
        if not isinstance(cov, bytes) or len(cov) != 72:
            raise CodecError(f"{name}.sources: expected 9 values of float64 bytes")
        covs.append(cov)
    if not out:
        return ()
    # every component checked at once: a beacon may carry a dozen
    f = np.frombuffer(b"".join(covs), "<f8").reshape(-1, 9).astype(float)
    if not np.isfinite(f).all():
        raise CodecError(f"{name}.sources: non-finite values")
    scale = 1e-12 + 1e-9 * np.abs(f).max(axis=1)
    if (f[:, ::4] < 0.0).any() or (np.abs(f[:, _UPPER] - f[:, _LOWER]).max(axis=1) > scale).any():
        raise CodecError(f"{name}.sources: a covariance must be symmetric with a non-negative diagonal")
    return tuple(zip(out, f.reshape(-1, 3, 3)))


def _check_constants(name: str, fname: str, val: Any) -> tuple[tuple[str, np.ndarray], ...]:
    if not isinstance(val, (list, tuple)) or len(val) > MAX_SOURCES:
        raise CodecError(f"{name}.constants: must be a list of at most {MAX_SOURCES} entries")
    labels: list[str] = []
    values: list[bytes] = []
    for item in val:
        if not isinstance(item, (list, tuple)) or len(item) != 2:
            raise CodecError(f"{name}.constants: each entry must be [name, sensitivity]")
        lab, g = item
        if not isinstance(lab, str) or not 0 < len(lab) <= 2 * MAX_STR + 1:
            raise CodecError(f"{name}.constants: a name must be a string of 1-{2 * MAX_STR + 1} characters")
        if not isinstance(g, bytes) or len(g) != 24:
            raise CodecError(f"{name}.constants: expected 3 values of float64 bytes")
        labels.append(lab)
        values.append(g)
    if not labels:
        return ()
    # every entry checked at once (a beacon carries a dozen): one array, a row per entry
    arr = np.frombuffer(b"".join(values), "<f8").reshape(-1, 3).astype(float)
    if not np.isfinite(arr).all():
        raise CodecError(f"{name}.constants: non-finite values")
    return tuple(zip(labels, arr))


_VALIDATORS: dict[str, _Validator] = {
    "auth": _check_auth,
    "sources": _check_sources,
    "constants": _check_constants,
    "peers": _check_peers,
    "first_stopped": _check_bool,
    "counters": _check_counters,
    "status": _check_status,
}


def _validator(fname: str) -> _Validator:
    if fname in _STRINGS:
        return _check_str
    if fname in _INTS:
        return _check_int
    if fname in _FLOATS:
        return _check_float
    return _VALIDATORS[fname]  # a KeyError here at import: a new field without a validator


#: per type: the class, its fields as (name, required, array shape or None, scalar validator),
#: and the set of allowed keys; built once (dataclasses.fields() per message is slow)
_Row = tuple[str, bool, _Shape | None, _Validator | None]
_SCHEMA: dict[str, tuple[type[Message], tuple[_Row, ...], frozenset[str]]] = {}
for _name, _cls in MESSAGE_TYPES.items():
    _rows: list[_Row] = []
    for _f in fields(_cls):
        _required = _f.default is MISSING and _f.default_factory is MISSING
        _shape = _ARRAYS[_name].get(_f.name)
        _rows.append((_f.name, _required, _shape, None if _shape is not None else _validator(_f.name)))
    _SCHEMA[_name] = (_cls, tuple(_rows), frozenset(["v", "type", *(r[0] for r in _rows)]))


def _unpack(payload: bytes) -> dict[Any, Any]:
    """The payload's msgpack map, within the codec's size limits."""
    if len(payload) > MAX_PAYLOAD:
        raise CodecError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=MAX_PAYLOAD,
                              max_str_len=4096, max_array_len=4096, max_map_len=256)
    except Exception as exc:  # msgpack raises several unrelated types on bad input
        raise CodecError(f"not msgpack: {type(exc).__name__}") from None
    if not isinstance(obj, dict):
        raise CodecError("payload is not a map")
    return obj


#: the latest decoded signed beacons, by id: (the beacon, weakly; the bytes their signature
#: covers, as their senders packed them); messages are unhashable, and a verifier asks soon
_WIRE_SIGNED: dict[int, tuple[weakref.ref[Message], bytes]] = {}
_WIRE_SIGNED_MAX = 1024


def received_signed_bytes(beacon: Message) -> bytes | None:
    """The bytes the signature of a beacon decoded by :func:`decode` covers as its sender
    packed them: its payload with an empty ``auth`` (msgpack repacks what it unpacked byte
    for byte). None for a beacon not decoded here, or unsigned. A verifier tries these first:
    re-encoding the beacon costs several times more, and for a sender that uses this codec
    both are the same bytes."""
    got = _WIRE_SIGNED.get(id(beacon))
    return got[1] if got is not None and got[0]() is beacon else None


def decode(payload: bytes) -> Message:
    """Parse and validate a payload; raises :class:`CodecError` on anything wrong."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise CodecError("payload is not bytes")
    obj = _unpack(payload)
    if obj.get("v") != SCHEMA_VERSION:
        raise CodecError(f"schema version {obj.get('v')!r}, expected {SCHEMA_VERSION}")
    name = obj.get("type")
    if not isinstance(name, str) or (schema := _SCHEMA.get(name)) is None:
        raise CodecError(f"unknown message type {name!r}")
    cls, rows, allowed = schema
    if not allowed.issuperset(obj):
        raise CodecError(f"{name}: unknown fields {sorted(set(obj) - allowed)}")
    kwargs: dict[str, Any] = {}
    n_lead: int | None = None
    arrays: list[tuple[str, bytes, tuple[int, ...]]] = []
    for fname, required, shape, check in rows:
        if fname not in obj:
            if required:
                raise CodecError(f"{name}: missing field {fname!r}")
            continue
        if shape is not None:
            shp, n_lead = _array_shape(name, fname, obj[fname], shape, n_lead)
            arrays.append((fname, obj[fname], shp))
        else:
            kwargs[fname] = cast("_Validator", check)(name, fname, obj[fname])  # a scalar field has one
    if arrays:
        kwargs.update(_arrays(name, arrays))
    if name == "uwb_round" and len(kwargs["peers"]) != len(kwargs["ranges"]):
        raise CodecError(f"uwb_round: {len(kwargs['peers'])} peers but {len(kwargs['ranges'])} ranges")
    msg = cls(**kwargs)
    if name == "beacon" and obj.get("auth"):
        if len(_WIRE_SIGNED) >= _WIRE_SIGNED_MAX:
            try:  # the oldest (another thread's decode may have evicted it first)
                del _WIRE_SIGNED[next(iter(_WIRE_SIGNED))]
            except (KeyError, RuntimeError, StopIteration):
                pass
        _WIRE_SIGNED[id(msg)] = (weakref.ref(msg), msgpack.packb({**obj, "auth": b""}, use_bin_type=True))
    return msg


def peek_beacon(payload: bytes) -> tuple[str, bytes]:
    """The sender and the authenticator of a beacon payload, and nothing else validated: the
    cheap look a receiver takes before it queues, decodes or verifies a beacon (a tenth of
    :func:`decode`'s cost). Raises :class:`CodecError` for a payload that is not a beacon's map."""
    obj = _unpack(payload)
    if obj.get("type") != "beacon":
        raise CodecError("not a beacon")
    vehicle, auth = obj.get("vehicle"), obj.get("auth", b"")
    if not isinstance(vehicle, str) or not isinstance(auth, bytes):
        raise CodecError("beacon: bad vehicle or auth")
    return vehicle, auth


def _array_shape(name: str, fname: str, val: Any, shape: _Shape,
                 n_lead: int | None) -> tuple[tuple[int, ...], int | None]:
    """The shape of array field ``fname`` from the length of its bytes (checked against the
    schema's ``shape`` and the other fields' leading count), and the leading count."""
    if not isinstance(val, bytes) or len(val) % 8:
        raise CodecError(f"{name}.{fname}: must be float64 bytes")
    count = len(val) // 8
    if shape[0] is None:
        inner = math.prod(shape[1:])
        if count % inner:
            raise CodecError(f"{name}.{fname}: length {count} not a multiple of {inner}")
        n = count // inner
        if n_lead is not None and n != n_lead:
            raise CodecError(f"{name}.{fname}: {n} rows, other fields have {n_lead}")
        if not 0 < n <= MAX_SAMPLES:
            raise CodecError(f"{name}.{fname}: {n} rows outside 1-{MAX_SAMPLES}")
        return (n, *shape[1:]), n
    size = math.prod(shape)
    if count != size:
        raise CodecError(f"{name}.{fname}: expected {size} values, got {count}")
    return cast("tuple[int, ...]", tuple(shape)), n_lead


def _arrays(name: str, fields: list[tuple[str, bytes, tuple[int, ...]]]) -> dict[str, np.ndarray]:
    """A message's array fields (name, bytes, shape) from one buffer, checked finite at once
    (numpy's cost is per call: a beacon has three such fields, an estimate four)."""
    flat = np.frombuffer(b"".join(v for _, v, _ in fields), dtype="<f8").astype(float)
    finite = bool(np.isfinite(flat).all())
    out: dict[str, np.ndarray] = {}
    off = 0
    for fname, v, shp in fields:
        k = len(v) // 8
        arr = flat[off:off + k]
        if not finite and not np.isfinite(arr).all():
            raise CodecError(f"{name}.{fname}: non-finite values")
        out[fname] = arr.reshape(shp)
        off += k
    return out
