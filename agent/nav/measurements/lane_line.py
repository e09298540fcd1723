"""Lane-keeping constraint: the vehicle's distance to its lane's left lane line.

A vehicle driving in a lane keeps its reference point ``d_l`` to the right of the left lane line,
with ``d_l ~ N(m_yb, σ_yb²)`` the same distribution as the stop-line fix's lateral part (paper
§III-B). One row, across the lane: along a single-lane queue the UWB ranges give along-track
information only, and this row is what the map adds across it.

The driver's offset from ``m_yb`` persists while the vehicle stays in the lane, so it is not
white noise: the filter carries it as a state (see :class:`agent.methods.MethodFilter`) and
this model's noise is the map's error alone.
"""

from __future__ import annotations

import numpy as np

from ..kalman import Measurement
from ..state import NavState
from .common import NO_LEVER_ARM
from .stop_line import Line2D, map_position


def lane_line_measurement(state: NavState, left_line: Line2D, m_yb: float, sigma: float,
                          origin_llh: tuple[float, float, float],
                          lever_arm_b: np.ndarray = NO_LEVER_ARM) -> Measurement:
    """Distance right of the left lane line, predicted minus expected (1 row).

    Parameters
    ----------
    state : NavState
        Predicted IMU state.
    left_line : Line2D
        The lane's left lane line where the vehicle is (map frame, directed along travel).
    m_yb : float
        Expected distance of the reference point right of that line [m].
    sigma : float
        Noise of the row [m]: the map error, or the whole spread σ_yb when the offset is not
        carried as a state.
    origin_llh : tuple of float
        Map origin latitude, longitude [rad], ellipsoidal height [m].
    lever_arm_b : ndarray, shape (3,)
        Reference point relative to the IMU (FRD) [m].

    Returns
    -------
    Measurement
        ``z`` (1,) [m] = n_rᵀ (p̂ − line point) − m_yb, ``H`` (1, 15), ``R`` (1, 1) [m²].
    """
    ne, H = map_position(state, origin_llh, lever_arm_b)
    n_r = left_line.right_normal
    z = float(n_r @ (ne - np.asarray(left_line.point))) - m_yb
    return Measurement(np.array([z]), (n_r @ H)[None, :], np.array([[sigma * sigma]]), "lane_line")
