"""Key expressions of the slcp bus (Zenoh syntax: ``*`` one chunk, ``**`` any number).

=============================================  =================================================
key                                            payload
=============================================  =================================================
``slcp/v1/sensor/<vehicle>/imu``               :class:`ImuBatch` from the emulator or a driver
``slcp/v1/sensor/<vehicle>/gnss``              :class:`GnssFix`
``slcp/v1/sensor/<vehicle>/lane``              :class:`LaneMarkings` from the forward camera
``slcp/v1/uwb/<vehicle>``                      :class:`UwbRound` (its ranges of one round) or a
                                               :class:`UwbRange` delivered to one end of a pair
``slcp/v1/radio/tx/<vehicle>``                 :class:`Beacon` sent by an agent to the V2V radio
``slcp/v1/radio/rx/<vehicle>``                 :class:`Beacon` delivered by the radio to a receiver
``slcp/v1/estimate/<vehicle>/<method>``        :class:`Estimate` for the recorder
``slcp/v1/diag/<source>``                      :class:`Diagnostics`
``slcp/v1/alive/<role>/<name>``                liveliness token of a process
=============================================  =================================================
"""

from __future__ import annotations

import functools
import re

ROOT = "slcp/v1"
_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def check_name(name: str) -> str:
    """A vehicle, method or process name usable as one key chunk (letters, digits, ``_.-``)."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"invalid name {name!r}: use 1-64 letters, digits, '_', '.', '-'")
    return name


def imu(vehicle: str) -> str:
    return f"{ROOT}/sensor/{check_name(vehicle)}/imu"


def gnss(vehicle: str) -> str:
    return f"{ROOT}/sensor/{check_name(vehicle)}/gnss"


def lane(vehicle: str) -> str:
    return f"{ROOT}/sensor/{check_name(vehicle)}/lane"


def uwb(vehicle: str) -> str:
    return f"{ROOT}/uwb/{check_name(vehicle)}"


def radio_tx(vehicle: str) -> str:
    return f"{ROOT}/radio/tx/{check_name(vehicle)}"


def radio_rx(vehicle: str) -> str:
    return f"{ROOT}/radio/rx/{check_name(vehicle)}"


def estimate(vehicle: str, method: str) -> str:
    return f"{ROOT}/estimate/{check_name(vehicle)}/{check_name(method)}"


def diag(source: str) -> str:
    return f"{ROOT}/diag/{check_name(source)}"


def alive(role: str, name: str) -> str:
    return f"{ROOT}/alive/{check_name(role)}/{check_name(name)}"


@functools.lru_cache(maxsize=65536)
def matches(expr: str, key: str) -> bool:
    """Whether concrete ``key`` matches key expression ``expr`` (``*`` and ``**`` wildcards).

    Memoised: the in-memory bus asks it for every subscription and message, with few
    distinct pairs."""
    e, k = expr.split("/"), key.split("/")

    def rec(i: int, j: int) -> bool:
        if i == len(e):
            return j == len(k)
        if e[i] == "**":
            return any(rec(i + 1, jj) for jj in range(j, len(k) + 1))
        if j == len(k):
            return False
        return (e[i] == "*" or e[i] == k[j]) and rec(i + 1, j + 1)

    return rec(0, 0)
