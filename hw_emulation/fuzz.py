"""Bad payloads for robustness tests: what a broken or hostile publisher could put on a topic.

Two families:

* **malformed** (every receiver must count it as a codec error): random bytes, a valid payload
  cut short, oversized, a field of the wrong type, NaN/inf in a number or an array, a wrong
  schema version, an unknown message type, a missing or an unknown field, a wrong array length;
* **semantic** (well-formed, but wrong in time): an exact duplicate, an old message delivered
  again (out of order), and a time jump (the message's time moved by 10 s to 10⁶ s, forwards
  or backwards).

All draws come from a seeded ``numpy.random.Generator``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import msgpack
import numpy as np

from slcp.transport.codec import MAX_PAYLOAD, SCHEMA_VERSION, encode
from slcp.transport.messages import Message

MALFORMED = ("random_bytes", "truncated", "oversized", "wrong_type", "nan_inf", "wrong_version",
             "unknown_type", "missing_field", "unknown_field", "bad_array")
SEMANTIC = ("duplicate", "replayed_old", "time_jump")
_WRONG_VALUES: tuple[Any, ...] = ("x", b"\x00", [1, 2], {"a": 1}, None, True, -1, 2**64 - 1, 1.5)


def malformed(rng: np.random.Generator, valid: Message, kind: str) -> bytes:
    """A payload of ``kind`` (one of :data:`MALFORMED`) derived from the valid message ``valid``;
    no receiver may accept it."""
    good = encode(valid)
    obj = msgpack.unpackb(good, raw=False)
    names = [k for k in obj if k not in ("v", "type")]
    if kind == "random_bytes":
        return rng.bytes(int(rng.integers(0, 512)))
    if kind == "truncated":
        return good[: int(rng.integers(0, len(good)))]
    if kind == "oversized":
        return good + bytes(MAX_PAYLOAD)
    if kind == "wrong_type":
        name = names[int(rng.integers(len(names)))]
        choices = [v for v in _WRONG_VALUES if type(v) is not type(obj[name])]
        obj[name] = choices[int(rng.integers(len(choices)))]
        if _still_valid(obj, name, valid):
            obj[name] = {"not": "valid"}
    elif kind == "nan_inf":
        bad = float(rng.choice([np.nan, np.inf, -np.inf]))
        arrays = [k for k in names if isinstance(obj[k], bytes) and k != "auth" and len(obj[k]) >= 8]
        floats = [k for k in names if isinstance(obj[k], float)]
        if arrays and (not floats or rng.random() < 0.5):
            name = arrays[int(rng.integers(len(arrays)))]
            arr = np.frombuffer(obj[name], dtype="<f8").copy()
            arr[int(rng.integers(arr.size))] = bad
            obj[name] = arr.tobytes()
        elif floats:
            obj[floats[int(rng.integers(len(floats)))]] = bad
        else:  # a message with no numbers: wrong type instead
            obj[names[0]] = bad
    elif kind == "wrong_version":
        obj["v"] = int(rng.choice([0, SCHEMA_VERSION + 1, 99]))
    elif kind == "unknown_type":
        obj["type"] = "teleport"
    elif kind == "missing_field":
        required = [f.name for f in dataclasses.fields(valid)
                    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        del obj[required[int(rng.integers(len(required)))]]
    elif kind == "unknown_field":
        obj["payload_of_a_future_version"] = 1
    elif kind == "bad_array":
        arrays = [k for k in names if isinstance(obj[k], bytes) and k != "auth" and len(obj[k]) >= 8]
        if not arrays:
            obj["type"] = 7
        else:
            name = arrays[int(rng.integers(len(arrays)))]
            obj[name] = obj[name][:-8] if rng.random() < 0.5 else obj[name][:-3]
    else:
        raise ValueError(f"unknown malformed kind {kind!r}")
    return msgpack.packb(obj, use_bin_type=True)


def _still_valid(obj: dict, name: str, valid: Message) -> bool:
    """Whether the substituted value happens to be acceptable (any integer for a float field)."""
    v = obj[name]
    return isinstance(getattr(valid, name), float) and isinstance(v, (int, float)) and not isinstance(v, bool)


def time_jumped(rng: np.random.Generator, valid: Message) -> Message:
    """``valid`` with its time ``t`` moved by ±10..10⁶ s (a clock jump at the source), kept >= 0."""
    jump = float(rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(1.0, 6.0))
    t = valid.t
    return dataclasses.replace(valid, t=np.abs(t + jump) if isinstance(t, np.ndarray) else abs(t + jump))
