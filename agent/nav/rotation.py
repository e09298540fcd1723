"""Rotation helpers: skew matrices, rotation vectors, quaternions, Euler angles.

Quaternions are scalar-first ``[w, x, y, z]`` and represent the rotation from the body frame
(FRD) to the navigation frame (NED): ``v_n = C_bn @ v_b``. Euler angles are roll, pitch, yaw
(z-y-x intrinsic, aerospace convention) in radians. The hot-path helpers are hand-written for
speed on 3-vectors; conversions at the edges use :class:`scipy.spatial.transform.Rotation`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v×]`` of a 3-vector, shape (3, 3): ``skew(a) @ b == cross(a, b)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotvec_to_quat(phi: np.ndarray) -> np.ndarray:
    """Quaternion, shape (4,), of the rotation vector ``phi`` [rad], shape (3,)."""
    angle = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    half = 0.5 * angle
    if angle < 1e-8:
        # series expansion of sin(a/2)/a
        s = 0.5 - angle * angle / 48.0
    else:
        s = math.sin(half) / angle
    return np.array([math.cos(half), s * phi[0], s * phi[1], s * phi[2]])


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` of scalar-first quaternions, shape (4,)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """DCM, shape (3, 3), of a unit scalar-first quaternion."""
    w, x, y, z = q.tolist() if isinstance(q, np.ndarray) else q
    return np.array(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ]
    ).reshape(3, 3)


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with non-negative scalar part."""
    q = q / math.sqrt(float(q @ q))
    return -q if q[0] < 0 else q


def euler_to_dcm(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body-to-NED DCM from roll, pitch, yaw [rad] (z-y-x), shape (3, 3)."""
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()


def euler_to_quat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body-to-NED scalar-first quaternion from roll, pitch, yaw [rad]."""
    x, y, z, w = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
    return quat_normalize(np.array([w, x, y, z]))


def dcm_to_quat(c: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternion of a DCM."""
    x, y, z, w = Rotation.from_matrix(c).as_quat()
    return quat_normalize(np.array([w, x, y, z]))


def quat_to_euler(q: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw [rad], shape (3,), of a body-to-NED quaternion (closed form)."""
    w, x, y, z = q.tolist()
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array([roll, pitch, yaw])


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Wrap angle(s) [rad] to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi
