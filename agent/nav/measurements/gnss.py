"""Loosely coupled GNSS position and velocity measurements with antenna lever arm."""

from __future__ import annotations

import numpy as np

from slcp.geo import earth

from ..kalman import Measurement
from ..rotation import skew
from ..state import ATT, BG, N_STATES, VEL, NavState
from .common import NO_LEVER_ARM, point_llh, point_position_jacobian


def gnss_position(
    state: NavState,
    llh_measured: np.ndarray,
    cov_ned: np.ndarray,
    lever_arm_b: np.ndarray = NO_LEVER_ARM,
) -> Measurement:
    """GNSS antenna position fix.

    Parameters
    ----------
    state : NavState
        Predicted IMU state.
    llh_measured : ndarray, shape (3,)
        Measured antenna latitude, longitude [rad] and ellipsoidal height [m].
    cov_ned : ndarray, shape (3, 3)
        Fix covariance in NED [m^2].
    lever_arm_b : ndarray, shape (3,)
        Antenna position relative to the IMU in the body frame (FRD) [m].
    """
    lat, lon, h = point_llh(state, lever_arm_b)
    z = earth.ned_offset(lat, lon, h, llh_measured[0], llh_measured[1], llh_measured[2])
    return Measurement(z, point_position_jacobian(state, lever_arm_b), np.asarray(cov_ned, float), "gnss_pos")


def gnss_velocity(
    state: NavState,
    v_measured: np.ndarray,
    cov_ned: np.ndarray,
    omega_ib_b: np.ndarray,
    lever_arm_b: np.ndarray = NO_LEVER_ARM,
) -> Measurement:
    """GNSS antenna velocity (NED) with the lever-arm rotation term.

    Parameters
    ----------
    v_measured : ndarray, shape (3,)
        Measured antenna velocity in NED [m/s].
    cov_ned : ndarray, shape (3, 3)
        Velocity covariance [m^2/s^2].
    omega_ib_b : ndarray, shape (3,)
        Raw (uncorrected) gyro angular rate at the epoch [rad/s]; the bias estimate in
        ``state`` is removed here. Earth and transport rates are neglected (< 1e-4 rad/s).
    lever_arm_b : ndarray, shape (3,)
        Antenna position relative to the IMU (FRD) [m].
    """
    c = state.dcm
    w = np.asarray(omega_ib_b, float) - state.bg
    v_rot = c @ (skew(w) @ np.asarray(lever_arm_b, float))  # np.cross is ~10x slower on 3-vectors
    z = state.v + v_rot - np.asarray(v_measured, float)
    H = np.zeros((3, N_STATES))
    H[:, VEL] = np.eye(3)
    H[:, ATT] = skew(v_rot)
    H[:, BG] = c @ skew(lever_arm_b)
    return Measurement(z, H, np.asarray(cov_ned, float), "gnss_vel")
