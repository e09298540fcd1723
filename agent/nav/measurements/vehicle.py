"""Vehicle-motion pseudo-measurements: zero velocity (ZUPT), zero angular rate (ZARU) and the
non-holonomic constraint (NHC: no lateral or vertical velocity of the body)."""

from __future__ import annotations

import numpy as np

from slcp.geo import earth

from ..kalman import Measurement
from ..rotation import skew
from ..state import ATT, BG, N_STATES, VEL, NavState


def zero_velocity(state: NavState, sigma: float) -> Measurement:
    """ZUPT: the NED velocity is zero, noise ``sigma`` [m/s] per axis."""
    H = np.zeros((3, N_STATES))
    H[:, VEL] = np.eye(3)
    return Measurement(state.v.copy(), H, np.eye(3) * sigma**2, "zupt")


def zero_angular_rate(state: NavState, omega_ib_b_mean: np.ndarray, sigma: float) -> Measurement:
    """ZARU: a stationary body does not rotate w.r.t. the earth.

    Parameters
    ----------
    omega_ib_b_mean : ndarray, shape (3,)
        Mean raw gyro rate over the stationary window [rad/s].
    sigma : float
        Noise of that mean [rad/s] per axis.
    """
    w_ie_b = state.dcm.T @ earth.earth_rate_ned(state.lat)
    z = np.asarray(omega_ib_b_mean, float) - state.bg - w_ie_b
    H = np.zeros((3, N_STATES))
    H[:, BG] = -np.eye(3)
    # the earth-rate term depends on attitude; its Jacobian is ~7e-5 and neglected
    return Measurement(z, H, np.eye(3) * sigma**2, "zaru")


def non_holonomic(state: NavState, sigma_lateral: float, sigma_vertical: float | None = None) -> Measurement:
    """NHC: body-frame velocity has no right (y) or down (z) component.

    Assumes the body frame is aligned with the vehicle (mounting rotation applied) and the
    IMU is close to the rear axle; both are documented limits of the constraint.
    """
    c = state.dcm
    v_b = c.T @ state.v
    H = np.zeros((2, N_STATES))
    H[:, VEL] = c.T[1:3]
    H[:, ATT] = -(c.T @ skew(state.v))[1:3]
    sv = sigma_lateral if sigma_vertical is None else sigma_vertical
    return Measurement(v_b[1:3].copy(), H, np.diag([sigma_lateral**2, sv**2]), "nhc")
