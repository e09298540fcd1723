"""Navigation state, error-state layout, and the maps between them.

Error state (15, the paper's eq. 2 with position in NED metres instead of radians):

======  ===========  ======================================================
slice   symbol       meaning (all errors are *estimate minus truth*)
======  ===========  ======================================================
0:3     phi          attitude error [rad]: ``C_bn_est = (I - [phi×]) C_bn_true``
3:6     dv           NED velocity error [m/s]
6:9     dr           NED position error [m]: ``(R_M+h) dLat, (R_N+h) cos(Lat) dLon, -dh``
9:12    dbg          gyro bias error [rad/s]
12:15   dba          accelerometer bias error [m/s^2]
======  ===========  ======================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slcp.geo import earth

from .rotation import quat_mul, quat_normalize, quat_to_dcm, rotvec_to_quat

ATT = slice(0, 3)
VEL = slice(3, 6)
POS = slice(6, 9)
BG = slice(9, 12)
BA = slice(12, 15)
N_STATES = 15


@dataclass
class NavState:
    """Nominal (total) navigation state of one IMU.

    Attributes
    ----------
    lat, lon : float
        Geodetic latitude and longitude of the IMU [rad].
    h : float
        Height above the WGS-84 ellipsoid [m].
    v : ndarray, shape (3,)
        Velocity over ground in NED [m/s].
    q : ndarray, shape (4,)
        Body(FRD)-to-NED attitude quaternion, scalar first.
    bg : ndarray, shape (3,)
        Gyro bias estimate [rad/s] (subtracted from measured angular rate).
    ba : ndarray, shape (3,)
        Accelerometer bias estimate [m/s^2] (subtracted from measured specific force).
    """

    lat: float
    lon: float
    h: float
    v: np.ndarray
    q: np.ndarray
    bg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ba: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def copy(self) -> NavState:
        return NavState(self.lat, self.lon, self.h, self.v.copy(), self.q.copy(),
                        self.bg.copy(), self.ba.copy())

    @property
    def dcm(self) -> np.ndarray:
        """Body-to-NED direction cosine matrix, shape (3, 3)."""
        return quat_to_dcm(self.q)

    @property
    def llh(self) -> np.ndarray:
        """``[lat rad, lon rad, h m]``, shape (3,)."""
        return np.array([self.lat, self.lon, self.h])


def apply_error(state: NavState, dx: np.ndarray) -> NavState:
    """State whose error with respect to ``state`` is ``dx`` (``state ⊕ dx``).

    If ``state`` is the truth, the result is an estimate carrying error ``dx``. Used to build
    numerical Jacobians and Monte-Carlo initial errors.
    """
    out = state.copy()
    rm, rn = earth.radii(state.lat)
    out.lat = state.lat + dx[6] / (rm + state.h)
    out.lon = state.lon + dx[7] / ((rn + state.h) * np.cos(state.lat))
    out.h = state.h - dx[8]
    out.v = state.v + dx[VEL]
    # C_est = exp(-[phi×]) C_true  <=>  q_est = q(-phi) ⊗ q_true
    out.q = quat_normalize(quat_mul(rotvec_to_quat(-np.asarray(dx[ATT])), state.q))
    out.bg = state.bg + dx[BG]
    out.ba = state.ba + dx[BA]
    return out


def remove_error(state: NavState, dx: np.ndarray) -> NavState:
    """Closed-loop correction: the estimate ``state`` minus its estimated error ``dx``.

    Exact inverse of :func:`apply_error` to first order (and exactly for attitude, velocity
    and biases).
    """
    d = dx[:N_STATES].tolist()
    lat, h = float(state.lat), float(state.h)
    rm, rn = earth.radii(lat)
    q = quat_mul(rotvec_to_quat(np.array(d[0:3])), state.q)
    return NavState(
        lat - d[6] / (rm + h),
        float(state.lon) - d[7] / ((rn + h) * math.cos(lat)),
        h + d[8],
        state.v - dx[VEL],
        quat_normalize(q),
        state.bg - dx[BG],
        state.ba - dx[BA],
    )


def state_error(est: NavState, truth: NavState) -> np.ndarray:
    """Error vector ``est ⊖ truth``, shape (15,), in the layout of this module."""
    dx = np.zeros(N_STATES)
    rm, rn = earth.radii(truth.lat)
    dx[6] = (est.lat - truth.lat) * (rm + truth.h)
    dx[7] = (est.lon - truth.lon) * (rn + truth.h) * np.cos(truth.lat)
    dx[8] = -(est.h - truth.h)
    dx[VEL] = est.v - truth.v
    # C_est C_true^T = exp(-[phi×])
    from scipy.spatial.transform import Rotation  # deferred: evaluation only, keeps agents small

    c = est.dcm @ truth.dcm.T
    dx[ATT] = -Rotation.from_matrix(c).as_rotvec()
    dx[BG] = est.bg - truth.bg
    dx[BA] = est.ba - truth.ba
    return dx
