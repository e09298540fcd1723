"""Stop-line aided position fix of the first stopped vehicle (paper §III-B, corrected).

The paper writes the stop line and the left lane line as ``y = k x + b`` in NED, which cannot
represent a line of constant north (a stop line across a north-south road). Here every line is a
point plus a unit direction in the local NED plane of the map origin (north, east in metres).

The reference point of the vehicle (origin O_b of its body frame) lies ``d_e = d_s + l_0``
*behind* the stop line, measured along the stop line's normal that points in the direction of
travel, and ``d_l`` to the *right* of the left lane line. With signed distances the two
conditions are linear in the position, so of the paper's four solutions of its eq. 13-14 only the
one behind the stop line and inside the lane is produced. Its covariance is ``J Σ Jᵀ`` with
``J = ∂p/∂(d_e, d_l)`` and ``Σ = diag(σ_xb², σ_yb²)``; for a stop line perpendicular to the lane
this is the paper's ``T Σ Tᵀ`` with ``T`` the rotation by the road angle.

Because position errors are NED metres (not the paper's δL, δλ), the east scaling the paper gets
wrong (``R_N`` instead of ``(R_N + h) cos L``) is done exactly in the geodetic-to-NED conversion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymap3d

from slcp.geo import earth

from ..kalman import Measurement
from ..state import NavState
from .common import NO_LEVER_ARM, point_llh, point_position_jacobian


@dataclass(frozen=True)
class Line2D:
    """Infinite line in the local horizontal plane: ``point + s * direction``.

    Attributes
    ----------
    point : tuple of float
        A point on the line, (north, east) [m] in the map frame.
    direction : tuple of float
        Unit direction (north, east); normalised on construction.
    """

    point: tuple[float, float]
    direction: tuple[float, float]

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, float)
        n = float(np.hypot(*d))
        if not np.isfinite(n) or n < 1e-12:
            raise ValueError(f"line direction must be a non-zero finite vector, got {self.direction}")
        object.__setattr__(self, "direction", (float(d[0] / n), float(d[1] / n)))
        object.__setattr__(self, "point", (float(self.point[0]), float(self.point[1])))

    @classmethod
    def from_points(cls, p0: tuple[float, float], p1: tuple[float, float]) -> Line2D:
        """Line through two points (north, east) [m], directed from ``p0`` to ``p1``."""
        return cls(p0, (p1[0] - p0[0], p1[1] - p0[1]))

    @classmethod
    def from_heading(cls, point: tuple[float, float], heading: float) -> Line2D:
        """Line through ``point`` with direction ``heading`` [rad] clockwise from north."""
        return cls(point, (math.cos(heading), math.sin(heading)))

    @classmethod
    def from_slope_intercept(cls, k: float, b: float) -> Line2D:
        """The paper's ``y = k x + b`` (x north, y east). Cannot express ``x = const``."""
        return cls((0.0, b), (1.0, k))

    @property
    def right_normal(self) -> np.ndarray:
        """Unit normal pointing to the right of the direction (north, east)."""
        dn, de = self.direction
        return np.array([-de, dn])

    def signed_distance(self, p: np.ndarray) -> float:
        """Distance [m] of ``p`` (north, east) from the line, positive on the right side."""
        return float(self.right_normal @ (np.asarray(p, float) - np.asarray(self.point)))


@dataclass(frozen=True)
class StopLineApproach:
    """One approach lane: its stop line and its left lane line.

    ``left_lane_line.direction`` is the direction of travel; ``stop_line`` may be directed
    either way and need not be perpendicular to the lane.
    """

    stop_line: Line2D
    left_lane_line: Line2D

    def __post_init__(self) -> None:
        s = np.asarray(self.stop_line.direction)
        u = np.asarray(self.left_lane_line.direction)
        if abs(float(s[0] * u[1] - s[1] * u[0])) < 0.1:
            raise ValueError("stop line is (nearly) parallel to the lane line: no unique fix")

    @property
    def travel_direction(self) -> np.ndarray:
        return np.asarray(self.left_lane_line.direction)

    def stop_line_normal(self) -> np.ndarray:
        """Unit normal of the stop line pointing in the direction of travel."""
        n = self.stop_line.right_normal
        return n if n @ self.travel_direction > 0 else -n


@dataclass(frozen=True)
class StopGapModel:
    """Where a first stopped vehicle stands, learned from data (paper §III-B).

    Attributes
    ----------
    m_xb, sigma_xb : float
        Mean and standard deviation of d_s, vehicle front to stop line [m].
    m_yb, sigma_yb : float
        Mean and standard deviation of d_l, reference point to the left lane line [m].
    l0 : float
        Distance from the reference point O_b back from the vehicle front [m].
    """

    m_xb: float
    sigma_xb: float
    m_yb: float
    sigma_yb: float
    l0: float

    def __post_init__(self) -> None:
        for name in ("m_xb", "sigma_xb", "m_yb", "sigma_yb", "l0"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"StopGapModel.{name} must be a finite number, got {value!r}")
        for name in ("sigma_xb", "sigma_yb", "l0"):
            if getattr(self, name) < 0:
                raise ValueError(f"StopGapModel.{name} must be >= 0, got {getattr(self, name)!r}")


def stop_line_fix(approach: StopLineApproach, d_e: float, d_l: float) -> tuple[np.ndarray, np.ndarray]:
    """Solve the reference point from its distances to the two lines.

    Parameters
    ----------
    approach : StopLineApproach
    d_e : float
        Distance behind the stop line [m] (``d_s + l_0``).
    d_l : float
        Distance right of the left lane line [m].

    Returns
    -------
    p : ndarray, shape (2,)
        (north, east) of the reference point [m] in the map frame.
    J : ndarray, shape (2, 2)
        ``∂p / ∂(d_e, d_l)``.
    """
    n_s = approach.stop_line_normal()
    n_r = approach.left_lane_line.right_normal
    A = np.vstack([n_s, n_r])
    b = np.array(
        [n_s @ np.asarray(approach.stop_line.point) - d_e,
         n_r @ np.asarray(approach.left_lane_line.point) + d_l]
    )
    Ainv = np.linalg.inv(A)
    return Ainv @ b, Ainv @ np.diag([-1.0, 1.0])


def stop_line_position(approach: StopLineApproach, gap: StopGapModel) -> tuple[np.ndarray, np.ndarray]:
    """Expected reference-point position (north, east) [m] and its covariance Σ_sl [m²]."""
    p, J = stop_line_fix(approach, gap.m_xb + gap.l0, gap.m_yb)
    sigma = np.diag([gap.sigma_xb**2, gap.sigma_yb**2])
    return p, J @ sigma @ J.T


def map_position(state: NavState, origin_llh: tuple[float, float, float],
                 lever_arm_b: np.ndarray = NO_LEVER_ARM) -> tuple[np.ndarray, np.ndarray]:
    """Map-frame position of a body-fixed point and its Jacobian.

    Parameters
    ----------
    state : NavState
    origin_llh : tuple of float
        Map origin latitude, longitude [rad], ellipsoidal height [m].
    lever_arm_b : ndarray, shape (3,)
        The point relative to the IMU (FRD) [m].

    Returns
    -------
    ne : ndarray, shape (2,)
        (north, east) [m] in the local NED frame of the map origin.
    H : ndarray, shape (2, 15)
        ``∂ne / ∂(error state)``: the vehicle's NED errors rotated into the map's NED (they
        differ by about distance / R rad).
    """
    lat, lon, h = point_llh(state, lever_arm_b)
    n, e, _ = pymap3d.geodetic2ned(lat, lon, h, *origin_llh, deg=False)
    c_map = earth.ned_to_ecef_dcm(origin_llh[0], origin_llh[1]).T @ earth.ned_to_ecef_dcm(lat, lon)
    return np.array([n, e]), (c_map @ point_position_jacobian(state, lever_arm_b))[:2]


def stop_line_measurement(
    state: NavState,
    approach: StopLineApproach,
    gap: StopGapModel,
    origin_llh: tuple[float, float, float],
    lever_arm_b: np.ndarray = NO_LEVER_ARM,
    along_only: bool = False,
) -> Measurement:
    """Horizontal position fix of the reference point from the stop line (2 rows).

    With ``along_only`` only the component along the stop-line normal is used (1 row, noise
    σ_xb): for a vehicle whose lane is ambiguous among lanes sharing the stop line.

    Parameters
    ----------
    state : NavState
        Predicted IMU state.
    approach : StopLineApproach
        The lane the vehicle stands first in (map frame).
    gap : StopGapModel
    origin_llh : tuple of float
        Map origin latitude, longitude [rad], ellipsoidal height [m].
    lever_arm_b : ndarray, shape (3,)
        Reference point O_b relative to the IMU (FRD) [m].
    """
    p_sl, cov = stop_line_position(approach, gap)
    ne, H = map_position(state, origin_llh, lever_arm_b)
    z = ne - p_sl
    if along_only:
        n = approach.stop_line_normal()
        return Measurement(np.array([n @ z]), (n @ H)[None, :], np.array([[gap.sigma_xb**2]]), "stop_line_along")
    return Measurement(z, H, cov, "stop_line")

