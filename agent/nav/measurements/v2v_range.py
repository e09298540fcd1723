"""V2V (UWB) range between this vehicle and a neighbour whose beacon gives its position and
covariance (paper eq. 26-28), with an optional second-order correction.

``z = ||p_i - p_j|| - r_ij``, ``H = u^T`` on i's position error (plus the lever-arm attitude
term), ``R = σ_uwb² + u^T P_j u``. When the position uncertainty is comparable to the range, the
first-order model is overconfident and biased: the second-order term adds
``½ tr((M P)²)`` to R and ``½ tr(M P)`` to the predicted range, with ``M = (I - u u^T)/ρ`` the
Hessian of the range and ``P = P_i + P_j`` (Bar-Shalom et al. §10.3, second-order EKF).

Road vehicles share a ground surface: the height difference of two UWB antennas a few tens of
metres apart is known far better (same mounting height, locally flat road) than the difference
of their GNSS/INS heights, whose vertical errors are metres. With ``height_offset`` given, the
model takes the antennas' vertical offset from it instead of from the two estimated heights:
``ρ = ||(d_n, d_e, Δh)||``, ``H`` acts on the horizontal position only, and the offset's σ
enters R. The vertical estimates then neither bias the range (the second-order term of a 10 m
vertical σ at 30 m is +1.7 m) nor drain its information.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from slcp.geo import earth

from ..kalman import Measurement
from ..state import N_STATES, POS, NavState
from .common import NO_LEVER_ARM, point_llh, point_position_jacobian


def relative_position(state: NavState, lever_arm_b: np.ndarray, neighbour_llh: np.ndarray) -> np.ndarray:
    """NED vector [m] from the neighbour's antenna to this vehicle's antenna, shape (3,)."""
    if lever_arm_b.any():
        lat, lon, h = point_llh(state, lever_arm_b)
    else:
        lat, lon, h = state.lat, state.lon, state.h
    return earth.ned_offset(lat, lon, h, neighbour_llh[0], neighbour_llh[1], neighbour_llh[2])


def range_measurement(
    state: NavState,
    measured_range: float,
    sigma_range: float,
    neighbour_llh: np.ndarray,
    neighbour_cov_ned: np.ndarray,
    lever_arm_b: np.ndarray = NO_LEVER_ARM,
    own_cov_ned: np.ndarray | None = None,
    second_order: bool = False,
    relative: np.ndarray | None = None,
    height_offset: tuple[float, float] | None = None,
) -> Measurement:
    """Range to a neighbour (1 row).

    Parameters
    ----------
    state : NavState
        Predicted state of this vehicle (i).
    measured_range : float
        UWB range between the antennas [m].
    sigma_range : float
        UWB range noise standard deviation [m].
    neighbour_llh : ndarray, shape (3,)
        Neighbour's antenna position (lat, lon rad; h m), extrapolated to the range time.
    neighbour_cov_ned : ndarray, shape (3, 3)
        Neighbour's position covariance from its beacon [m²].
    lever_arm_b : ndarray, shape (3,)
        This vehicle's UWB antenna relative to its IMU (FRD) [m].
    own_cov_ned : ndarray, shape (3, 3), optional
        This vehicle's position covariance; required for ``second_order``.
    second_order : bool
        Add the second-order noise and bias terms.
    relative : ndarray, shape (3,), optional
        :func:`relative_position` of the same arguments, if the caller has it already.
    height_offset : (float, float), optional
        ``(Δh, σ)`` [m]: this vehicle's antenna height minus the neighbour's and its standard
        deviation, known from the road (e.g. ``(0, 0.3)`` on a flat road). None: from the two
        estimated heights (a 3-D range).
    """
    d = relative_position(state, lever_arm_b, neighbour_llh) if relative is None else relative
    # 3-vectors and 3x3 matrices as Python floats: a range is fused up to 80 times a second
    # per vehicle, and a dozen numpy calls on such small arrays cost more than the arithmetic
    d0, d1, d2 = float(d[0]), float(d[1]), float(d[2])
    pj = np.asarray(neighbour_cov_ned, float).tolist()
    pi = None if own_cov_ned is None else np.asarray(own_cov_ned, float).tolist()
    r = sigma_range**2
    if height_offset is not None:
        dh, sdh = height_offset
        d2 = -float(dh)  # NED: down = minus the height difference
        pj = _horizontal_rows(pj)
        pi = None if pi is None else _horizontal_rows(pi)
    rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if rho < 1e-3:
        raise ValueError("vehicles coincide: range direction undefined")
    u = (d0 / rho, d1 / rho, d2 / rho)
    if height_offset is not None:
        r += (u[2] * sdh) ** 2
    r += quadratic_rows(pj, u)
    predicted = rho
    if second_order:
        if pi is None:
            raise ValueError("second_order range model needs own_cov_ned")
        # with M = Π/ρ, Π = I - u uᵀ and Q = P_i + P_j (symmetric): tr(MQ) = (tr Q - uᵀQu)/ρ,
        # tr((MQ)²) = (tr(Q²) - 2 |Qu|² + (uᵀQu)²)/ρ² (Π² = Π)
        Q = [[a + b for a, b in zip(ra, rb)] for ra, rb in zip(pj, pi)]
        if height_offset is not None:
            Q[2][2] += sdh**2
        Qu = [row[0] * u[0] + row[1] * u[1] + row[2] * u[2] for row in Q]
        uQu = Qu[0] * u[0] + Qu[1] * u[1] + Qu[2] * u[2]
        predicted += 0.5 * (Q[0][0] + Q[1][1] + Q[2][2] - uQu) / rho
        r += 0.5 * (sum(q * q for row in Q for q in row) - 2.0 * (Qu[0] ** 2 + Qu[1] ** 2 + Qu[2] ** 2)
                    + uQu * uQu) / (rho * rho)
    if height_offset is not None:
        u = (u[0], u[1], 0.0)  # the vertical offset comes from the road, not the state
    if lever_arm_b.any():
        H = np.array(u) @ point_position_jacobian(state, lever_arm_b)
    else:  # only the position columns
        H = np.zeros(N_STATES)
        H[POS] = u
    return Measurement(np.array([predicted - measured_range]), H[None, :], np.array([[r]]), "v2v_range")


def quadratic_rows(P: list[list[float]], u: Sequence[float]) -> float:
    """``uᵀ P u`` for a 3x3 ``P`` given as rows of floats and a 3-vector ``u`` (a sequence of
    floats): without numpy, for the per-range arithmetic."""
    return sum(u[i] * (P[i][0] * u[0] + P[i][1] * u[1] + P[i][2] * u[2]) for i in range(3))


def _horizontal_rows(P: list[list[float]]) -> list[list[float]]:
    """``P`` (3x3 rows of floats) with its vertical row and column zeroed (a copy)."""
    return [[P[0][0], P[0][1], 0.0], [P[1][0], P[1][1], 0.0], [0.0, 0.0, 0.0]]
