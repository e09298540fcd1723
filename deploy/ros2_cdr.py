"""The ROS 2 messages a recording writes for every estimate, ``sensor_msgs/msg/NavSatFix``
and ``nav_msgs/msg/Odometry``, and for every IMU sample, ``sensor_msgs/msg/Imu``, serialised
in CDR (little-endian, as ``ros2 bag`` stores them) with one :func:`struct.pack` each.

rosbags' generic serialiser builds a Python object per field and takes about 60 µs a message,
and a 50-vehicle fleet's recorder writes a few thousand a second. The layouts here are the same
bytes (a test compares them with rosbags' for random messages): CDR aligns every primitive to its
own size, counted from the end of the 4-byte encapsulation header; a string is its length (with
the terminating NUL) as a uint32, then its bytes and the NUL.
"""

from __future__ import annotations

import functools
import math
import struct

#: CDR, little-endian (the encapsulation header of every message)
ENCAPSULATION = b"\x00\x01\x00\x00"


def _layout(fields: list[tuple[str, int]]) -> struct.Struct:
    """A struct for ``fields`` (struct code, count; ``"s"``: that many bytes), padded as CDR aligns them."""
    fmt, off = ["<"], 0
    for code, n in fields:
        size = 1 if code == "s" else struct.calcsize("<" + code)
        pad = (-off) % size
        if pad:
            fmt.append(f"{pad}x")
        fmt.append(f"{n}{code}")
        off += pad + size * n
    return struct.Struct("".join(fmt))


def _string(s: str) -> tuple[list[tuple[str, int]], bytes]:
    b = s.encode() + b"\x00"
    return [("I", 1), ("s", len(b))], b


@functools.lru_cache(maxsize=4096)
def _fix_layout(frame: str) -> tuple[struct.Struct, bytes]:
    sf, fb = _string(frame)
    return _layout([("i", 1), ("I", 1), *sf, ("b", 1), ("H", 1), ("d", 3), ("d", 9), ("B", 1)]), fb


@functools.lru_cache(maxsize=4096)
def _odom_layout(frame: str, child: str) -> tuple[struct.Struct, bytes, bytes]:
    sf, fb = _string(frame)
    sc, cb = _string(child)
    return _layout([("i", 1), ("I", 1), *sf, *sc, ("d", 3), ("d", 4), ("d", 36), ("d", 3), ("d", 3), ("d", 36)]), fb, cb


@functools.lru_cache(maxsize=4096)
def _imu_layout(frame: str) -> tuple[struct.Struct, bytes]:
    sf, fb = _string(frame)
    return _layout([("i", 1), ("I", 1), *sf, ("d", 4), ("d", 9), ("d", 3), ("d", 9), ("d", 3), ("d", 9)]), fb


#: an IMU without an orientation (ROS: element 0 of its covariance -1), its other covariances unknown (zeros)
_NO_ORIENTATION = (0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_UNKNOWN9 = (0.0,) * 9


def _stamp(ns: int) -> tuple[int, int]:
    return ns // 1_000_000_000, ns % 1_000_000_000


def nav_sat_fix(ns: int, frame: str, lat_deg: float, lon_deg: float, alt: float, cov9: list[float],
                cov_type: int, status: int = 0, service: int = 1) -> bytes:
    """A ``sensor_msgs/msg/NavSatFix`` stamped ``ns`` [ns] (covariance row-major, east, north, up)."""
    st, fb = _fix_layout(frame)
    return ENCAPSULATION + st.pack(*_stamp(ns), len(fb), fb, status, service, lat_deg, lon_deg, alt, *cov9, cov_type)


def odometry(ns: int, frame: str, child: str, position: tuple[float, float, float],
             quaternion_xyzw: tuple[float, float, float, float], pose_cov36: list[float],
             linear: tuple[float, float, float], angular: tuple[float, float, float],
             twist_cov36: list[float]) -> bytes:
    """A ``nav_msgs/msg/Odometry`` stamped ``ns`` [ns] (covariances row-major, 6×6)."""
    st, fb, cb = _odom_layout(frame, child)
    return ENCAPSULATION + st.pack(*_stamp(ns), len(fb), fb, len(cb), cb, *position, *quaternion_xyzw, *pose_cov36,
                                   *linear, *angular, *twist_cov36)


def imu(ns: int, frame: str, angular_velocity: tuple[float, float, float],
        linear_acceleration: tuple[float, float, float]) -> bytes:
    """A ``sensor_msgs/msg/Imu`` stamped ``ns`` [ns] without an orientation."""
    st, fb = _imu_layout(frame)
    return ENCAPSULATION + st.pack(*_stamp(ns), len(fb), fb, *_NO_ORIENTATION, *angular_velocity, *_UNKNOWN9,
                                   *linear_acceleration, *_UNKNOWN9)


class LocalEnu:
    """East, north, up [m] of geodetic points in the tangent plane at ``origin`` (latitude,
    longitude [rad], height [m]) on WGS-84: :func:`pymap3d.geodetic2enu`, in scalar arithmetic."""

    A = 6378137.0
    E2 = 1.0 - (6356752.31424518 / 6378137.0) ** 2  #: pymap3d's WGS-84 (semi-major and semi-minor axes)

    def __init__(self, origin: tuple[float, float, float]) -> None:
        lat, lon, _ = origin
        self.x0, self.y0, self.z0 = self.ecef(*origin)
        self.sl, self.cl, self.so, self.co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)

    @classmethod
    def ecef(cls, lat: float, lon: float, h: float) -> tuple[float, float, float]:
        s, c = math.sin(lat), math.cos(lat)
        n = cls.A / math.sqrt(1.0 - cls.E2 * s * s)
        return (n + h) * c * math.cos(lon), (n + h) * c * math.sin(lon), (n * (1.0 - cls.E2) + h) * s

    def __call__(self, lat: float, lon: float, h: float) -> tuple[float, float, float]:
        x, y, z = self.ecef(lat, lon, h)
        dx, dy, dz = x - self.x0, y - self.y0, z - self.z0
        t = self.co * dx + self.so * dy
        return -self.so * dx + self.co * dy, -self.sl * t + self.cl * dz, self.cl * t + self.sl * dz
