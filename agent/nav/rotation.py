"""Rotation helpers: skew matrices, rotation vectors, quaternions, Euler angles.

Quaternions are scalar-first ``[w, x, y, z]`` and represent the rotation from the body frame
(FRD) to the navigation frame (NED): ``v_n = C_bn @ v_b``. Euler angles are roll, pitch, yaw
(z-y-x intrinsic, aerospace convention) in radians. Everything here is closed form on plain
floats: fast on 3-vectors, and it keeps an agent process from importing ``scipy.spatial``
(about 30 MB of resident memory). The tests check each conversion against
:class:`scipy.spatial.transform.Rotation`.
"""

from __future__ import annotations

import math

import numpy as np


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
    """Body-to-NED DCM from roll, pitch, yaw [rad] (z-y-x), shape (3, 3) (Groves eq. 2.22, transposed)."""
    sr, cr = math.sin(roll), math.cos(roll)
    sp, cp = math.sin(pitch), math.cos(pitch)
    sy, cy = math.sin(yaw), math.cos(yaw)
    return np.array([
        [cp * cy, -cr * sy + sr * sp * cy, sr * sy + cr * sp * cy],
        [cp * sy, cr * cy + sr * sp * sy, -sr * cy + cr * sp * sy],
        [-sp, sr * cp, cr * cp],
    ])


def euler_to_quat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body-to-NED scalar-first quaternion from roll, pitch, yaw [rad] (Groves eq. 2.39)."""
    sr, cr = math.sin(0.5 * roll), math.cos(0.5 * roll)
    sp, cp = math.sin(0.5 * pitch), math.cos(0.5 * pitch)
    sy, cy = math.sin(0.5 * yaw), math.cos(0.5 * yaw)
    return quat_normalize(np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]))


def dcm_to_quat(c: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternion of a DCM (Shepperd's method: the largest of the four
    candidates is taken as the pivot, so it is accurate for every rotation)."""
    c = np.asarray(c, float)
    tr = c[0, 0] + c[1, 1] + c[2, 2]
    k = int(np.argmax([tr, c[0, 0], c[1, 1], c[2, 2]]))
    if k == 0:
        w = 0.5 * math.sqrt(max(1.0 + tr, 0.0))
        q = [w, (c[2, 1] - c[1, 2]) / (4 * w), (c[0, 2] - c[2, 0]) / (4 * w), (c[1, 0] - c[0, 1]) / (4 * w)]
    elif k == 1:
        x = 0.5 * math.sqrt(max(1.0 + c[0, 0] - c[1, 1] - c[2, 2], 0.0))
        q = [(c[2, 1] - c[1, 2]) / (4 * x), x, (c[0, 1] + c[1, 0]) / (4 * x), (c[0, 2] + c[2, 0]) / (4 * x)]
    elif k == 2:
        y = 0.5 * math.sqrt(max(1.0 - c[0, 0] + c[1, 1] - c[2, 2], 0.0))
        q = [(c[0, 2] - c[2, 0]) / (4 * y), (c[0, 1] + c[1, 0]) / (4 * y), y, (c[1, 2] + c[2, 1]) / (4 * y)]
    else:
        z = 0.5 * math.sqrt(max(1.0 - c[0, 0] - c[1, 1] + c[2, 2], 0.0))
        q = [(c[1, 0] - c[0, 1]) / (4 * z), (c[0, 2] + c[2, 0]) / (4 * z), (c[1, 2] + c[2, 1]) / (4 * z), z]
    return quat_normalize(np.array(q))


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
