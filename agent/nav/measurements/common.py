"""Shared pieces of the measurement models: lever-arm points and their Jacobians."""

from __future__ import annotations

import numpy as np

from slcp.geo import earth

from ..rotation import skew
from ..state import ATT, N_STATES, POS, NavState

#: the default lever arm: the point is the IMU itself (read-only, shared)
NO_LEVER_ARM = np.zeros(3)
NO_LEVER_ARM.setflags(write=False)


def point_llh(state: NavState, lever_arm_b: np.ndarray) -> tuple[float, float, float]:
    """Geodetic position of a point fixed to the body at ``lever_arm_b`` (FRD, metres).

    Returns latitude, longitude [rad] and ellipsoidal height [m].
    """
    off = state.dcm @ lever_arm_b
    rm, rn = earth.radii(state.lat)
    return (
        state.lat + off[0] / (rm + state.h),
        state.lon + off[1] / ((rn + state.h) * np.cos(state.lat)),
        state.h - off[2],
    )


def point_position_jacobian(state: NavState, lever_arm_b: np.ndarray) -> np.ndarray:
    """Jacobian, shape (3, 15), of a body-fixed point's NED position w.r.t. the error state."""
    H = np.zeros((3, N_STATES))
    H[:, ATT] = skew(state.dcm @ lever_arm_b)
    H[:, POS] = np.eye(3)
    return H
