"""The geometry of a range between two uncertain positions: how far the line of sight may
turn, and when two vehicles are too close for a range to tell a direction (pure arithmetic on
2×2 covariances given as lists, for speed)."""

from __future__ import annotations

import math

#: below this horizontal speed [m/s] (own estimate, the neighbour's beacon) a vehicle counts as
#: standing for the UWB link's range track
STANDING_SPEED = 0.3
#: σ [m/s] of a relative velocity from two inertial estimates along a known line of sight
RATE_VELOCITY_SIGMA = 0.3


def rate_variance(u: tuple[float, ...], d: tuple[float, ...], own_cov: list, nb_cov: list, speed2: float) -> float:
    """Variance [m²/s²] of the range rate u·(v_i − v_j) from two estimates: the velocities'
    (``RATE_VELOCITY_SIGMA``) and the line of sight's, whose direction is off by the two
    positions' combined σ across it over the distance (``u`` horizontal unit (3,), ``d`` the
    relative position (3,) [m], ``own_cov``/``nb_cov`` (3, 3) [m²] as rows of floats,
    ``speed2`` the squared horizontal relative speed)."""
    r2 = max(d[0] ** 2 + d[1] ** 2, 1.0)
    return RATE_VELOCITY_SIGMA**2 + speed2 * min(_across(u[0], u[1], own_cov, nb_cov) / r2, 1.0)


def _across(u0: float, u1: float, own_cov: list, nb_cov: list) -> float:
    """The two horizontal covariances' sum (3x3 rows of floats [m²]) across the horizontal
    direction (u0, u1): a·(P_i + P_j)·a with a = (-u1, u0)."""
    c00 = own_cov[0][0] + nb_cov[0][0]
    c01 = own_cov[0][1] + nb_cov[0][1]
    c11 = own_cov[1][1] + nb_cov[1][1]
    return c00 * u1 * u1 - 2.0 * c01 * u0 * u1 + c11 * u0 * u0


def too_near(d: tuple[float, ...], own_cov: list, nb_cov: list, k: float) -> bool:
    """Whether the horizontal distance ``d[:2]`` [m] is below ``k`` σ of the horizontal position
    uncertainty across the line of sight (own plus the neighbour's covariance, (3, 3) m² as rows
    of floats)."""
    rho = math.hypot(d[0], d[1])
    if rho <= 0.0:
        return True
    return rho * rho < k * k * _across(d[0] / rho, d[1] / rho, own_cov, nb_cov)
