"""WGS-84 earth model: radii of curvature, normal gravity, earth and transport rates.

All angles in radians, lengths in metres, heights above the ellipsoid, rates in rad/s.
Vectors are resolved in the local-level NED frame. Reference: Groves (2013), ch. 2.
"""

from __future__ import annotations

import math

import numpy as np

#: WGS-84 semi-major axis [m]
A = 6378137.0
#: WGS-84 flattening [-]
F = 1.0 / 298.257223563
#: first eccentricity squared [-]
E2 = F * (2.0 - F)
#: semi-minor axis [m]
B = A * (1.0 - F)
#: earth rotation rate [rad/s]
OMEGA_E = 7.292115e-5
#: earth gravitational constant [m^3/s^2]
GM = 3.986004418e14
#: Somigliana normal gravity at the equator and the poles [m/s^2]
GAMMA_E = 9.7803253359
GAMMA_P = 9.8321849378
_K_SOMIGLIANA = (B * GAMMA_P) / (A * GAMMA_E) - 1.0
_M = OMEGA_E**2 * A**2 * B / GM


def radii(lat: float) -> tuple[float, float]:
    """Meridian and transverse radii of curvature.

    Parameters
    ----------
    lat : float
        Geodetic latitude [rad].

    Returns
    -------
    rm, rn : float
        Meridian radius R_M (north-south) and transverse radius R_N (east-west) [m].
    """
    s2 = math.sin(lat) ** 2
    w = 1.0 - E2 * s2
    rn = A / math.sqrt(w)
    rm = A * (1.0 - E2) / (w * math.sqrt(w))
    return rm, rn


def gravity(lat: float, h: float) -> float:
    """Down component of normal gravity (gravitation plus centrifugal) [m/s^2].

    Somigliana's formula on the ellipsoid with the second-order free-air height
    correction (Groves eq. 2.134/2.139).

    Parameters
    ----------
    lat : float
        Geodetic latitude [rad].
    h : float
        Height above the ellipsoid [m].
    """
    s2 = math.sin(lat) ** 2
    g0 = GAMMA_E * (1.0 + _K_SOMIGLIANA * s2) / math.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A * (1.0 + F + _M - 2.0 * F * s2) * h + 3.0 * h * h / (A * A))


def gravity_height_gradient(lat: float, h: float) -> float:
    """d(gravity)/dh [1/s^2] (negative: gravity weakens with height)."""
    s2 = math.sin(lat) ** 2
    g0 = GAMMA_E * (1.0 + _K_SOMIGLIANA * s2) / math.sqrt(1.0 - E2 * s2)
    return g0 * (-2.0 / A * (1.0 + F + _M - 2.0 * F * s2) + 6.0 * h / (A * A))


def earth_rate_ned(lat: float) -> np.ndarray:
    """Earth rotation rate resolved in NED, shape (3,) [rad/s]."""
    return np.array([OMEGA_E * math.cos(lat), 0.0, -OMEGA_E * math.sin(lat)])


def transport_rate_ned(lat: float, h: float, v_ned: np.ndarray) -> np.ndarray:
    """Transport rate (rotation of NED w.r.t. the earth) resolved in NED, shape (3,) [rad/s].

    Parameters
    ----------
    lat, h : float
        Geodetic latitude [rad] and height [m].
    v_ned : ndarray, shape (3,)
        Velocity over ground in NED [m/s].
    """
    rm, rn = radii(lat)
    return np.array(
        [v_ned[1] / (rn + h), -v_ned[0] / (rm + h), -v_ned[1] * math.tan(lat) / (rn + h)]
    )


def geodetic_rates(lat: float, h: float, v_ned: np.ndarray) -> tuple[float, float, float]:
    """Time derivatives of latitude, longitude [rad/s] and height [m/s] for a NED velocity."""
    rm, rn = radii(lat)
    return v_ned[0] / (rm + h), v_ned[1] / ((rn + h) * math.cos(lat)), -v_ned[2]


def ned_offset(lat: float, lon: float, h: float, lat0: float, lon0: float, h0: float) -> np.ndarray:
    """Small NED offset [m] of a point from a nearby reference, on the reference's curvature.

    First-order in the geodetic differences: accurate to ~1e-6 relative for offsets of a few
    kilometres. Use :func:`pymap3d.geodetic2ned` for large separations.
    """
    return np.array(ned_offset_scalars(lat, lon, h, lat0, lon0, h0))


def ned_offset_scalars(lat: float, lon: float, h: float, lat0: float, lon0: float,
                       h0: float) -> tuple[float, float, float]:
    """:func:`ned_offset` as three floats, for code that runs per message (no array)."""
    rm, rn = radii(lat0)
    return (lat - lat0) * (rm + h0), (lon - lon0) * (rn + h0) * math.cos(lat0), -(h - h0)


def offset_llh(llh: np.ndarray, d_ned: np.ndarray) -> np.ndarray:
    """The point ``d_ned`` [m] (NED, (3,)) away from ``llh`` (lat, lon [rad], h [m]): the inverse
    of :func:`ned_offset` to first order, for offsets of up to a few kilometres."""
    return np.array(offset_llh_scalars(float(llh[0]), float(llh[1]), float(llh[2]),
                                       float(d_ned[0]), float(d_ned[1]), float(d_ned[2])))


def offset_llh_scalars(lat: float, lon: float, h: float, dn: float, de: float,
                       dd: float) -> tuple[float, float, float]:
    """:func:`offset_llh` as three floats, for code that runs per message (no array)."""
    rm, rn = radii(lat)
    return lat + dn / (rm + h), lon + de / ((rn + h) * math.cos(lat)), h - dd


def ned_to_ecef_dcm(lat: float, lon: float) -> np.ndarray:
    """Rotation C_n^e from local NED at (lat, lon) [rad] to ECEF, shape (3, 3)."""
    sl, cl = math.sin(lat), math.cos(lat)
    so, co = math.sin(lon), math.cos(lon)
    return np.array(
        [[-sl * co, -so, -cl * co], [-sl * so, co, -cl * so], [cl, 0.0, -sl]]
    )
