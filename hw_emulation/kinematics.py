"""Truth trajectories with exactly consistent IMU increments.

A trajectory is given by smooth functions of time: speed along the body x axis ``s(t)`` and
Euler angles roll, pitch, yaw with their rates. Velocity is ``v_n = s * C_bn[:, 0]`` (no side
slip). Position follows by integrating the geodetic rates; the IMU
increments are the time integrals of the true body angular rate ``ω_ib^b`` and specific force
``f^b`` over each sample interval, and position the integral of the geodetic rates, all by
Gauss-Legendre quadrature. Everything is vectorised and
pure: the same inputs give bit-identical outputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy.interpolate import CubicHermiteSpline

from slcp.geo import earth


class KinematicProfile(Protocol):
    """Smooth motion description; all methods are vectorised over ``t`` (shape (n,))."""

    def speed(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Speed along body x [m/s] and its time derivative [m/s²], each shape (n,)."""

    def euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Roll, pitch, yaw [rad] and their rates [rad/s], each shape (n, 3)."""


@dataclass(frozen=True)
class SinusoidProfile:
    """Speed and Euler angles as a constant plus sinusoids: ``c + Σ a sin(ω t + φ)``.

    Each of ``speed_terms`` and ``roll/pitch/yaw_terms`` is a tuple of ``(amplitude, angular
    frequency rad/s, phase rad)``; ``yaw_rate`` adds a constant turn rate [rad/s].
    """

    speed0: float = 0.0
    speed_terms: tuple[tuple[float, float, float], ...] = ()
    roll_terms: tuple[tuple[float, float, float], ...] = ()
    pitch_terms: tuple[tuple[float, float, float], ...] = ()
    yaw0: float = 0.0
    yaw_rate: float = 0.0
    yaw_terms: tuple[tuple[float, float, float], ...] = ()

    @staticmethod
    def _series(t: np.ndarray, c: float, terms) -> tuple[np.ndarray, np.ndarray]:
        v = np.full_like(t, c, dtype=float)
        d = np.zeros_like(t, dtype=float)
        for a, w, p in terms:
            v = v + a * np.sin(w * t + p)
            d = d + a * w * np.cos(w * t + p)
        return v, d

    def speed(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self._series(t, self.speed0, self.speed_terms)

    def euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, rd = self._series(t, 0.0, self.roll_terms)
        p, pd = self._series(t, 0.0, self.pitch_terms)
        y, yd = self._series(t, self.yaw0, self.yaw_terms)
        y = y + self.yaw_rate * t
        yd = yd + self.yaw_rate
        return np.stack([r, p, y], axis=1), np.stack([rd, pd, yd], axis=1)


@dataclass(frozen=True)
class Truth:
    """Truth samples at the IMU times and the IMU increments between them.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Sample times [s].
    llh : ndarray, shape (n, 3)
        Latitude, longitude [rad], ellipsoidal height [m].
    v_ned : ndarray, shape (n, 3)
        Velocity [m/s].
    euler : ndarray, shape (n, 3)
        Roll, pitch, yaw [rad].
    dtheta, dvel : ndarray, shape (n-1, 3)
        True angle [rad] and velocity [m/s] increments over ``[t[k], t[k+1]]`` (body FRD).
    """

    t: np.ndarray
    llh: np.ndarray
    v_ned: np.ndarray
    euler: np.ndarray
    dtheta: np.ndarray
    dvel: np.ndarray


def _dcm_bn(euler: np.ndarray) -> np.ndarray:
    """Body-to-NED DCMs, shape (n, 3, 3), of roll, pitch, yaw rows [rad] (z-y-x), the closed form
    of :func:`agent.nav.rotation.euler_to_dcm` on arrays (scipy's ``Rotation.from_euler`` takes
    about 16 µs a row, and a route has one row per IMU sample)."""
    sr, cr = np.sin(euler[:, 0]), np.cos(euler[:, 0])
    sp, cp = np.sin(euler[:, 1]), np.cos(euler[:, 1])
    sy, cy = np.sin(euler[:, 2]), np.cos(euler[:, 2])
    c = np.empty((len(euler), 3, 3))
    c[:, 0, 0], c[:, 0, 1], c[:, 0, 2] = cp * cy, -cr * sy + sr * sp * cy, sr * sy + cr * sp * cy
    c[:, 1, 0], c[:, 1, 1], c[:, 1, 2] = cp * sy, cr * cy + sr * sp * sy, -sr * cy + cr * sp * sy
    c[:, 2, 0], c[:, 2, 1], c[:, 2, 2] = -sp, sr * cp, cr * cp
    return c


def _velocity(profile: KinematicProfile, t: np.ndarray) -> tuple[np.ndarray, ...]:
    """NED velocity, acceleration, DCM, Euler angles and body rate w.r.t. NED at ``t``.

    Independent of position: velocity is speed along the body x axis."""
    s, sd = profile.speed(t)
    ang, rates = profile.euler(t)
    c = _dcm_bn(ang)
    x_axis = c[:, :, 0]
    v = s[:, None] * x_axis
    r, p = ang[:, 0], ang[:, 1]
    rd, pd, yd = rates[:, 0], rates[:, 1], rates[:, 2]
    w_nb = np.stack(
        [
            rd - yd * np.sin(p),
            pd * np.cos(r) + yd * np.sin(r) * np.cos(p),
            -pd * np.sin(r) + yd * np.cos(r) * np.cos(p),
        ],
        axis=1,
    )
    # d/dt of the body x axis in NED: C [ω_nb^b ×] e_x
    dx_axis = np.einsum("nij,nj->ni", c, np.cross(w_nb, np.array([1.0, 0.0, 0.0])))
    a = sd[:, None] * x_axis + s[:, None] * dx_axis
    return v, a, c, ang, w_nb


def _radii_vec(lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sl2 = np.sin(lat) ** 2
    rn = earth.A / np.sqrt(1 - earth.E2 * sl2)
    return rn * (1 - earth.E2) / (1 - earth.E2 * sl2), rn


def _geodetic_rates_vec(llh: np.ndarray, v: np.ndarray) -> np.ndarray:
    rm, rn = _radii_vec(llh[:, 0])
    h = llh[:, 2]
    return np.column_stack([v[:, 0] / (rm + h), v[:, 1] / ((rn + h) * np.cos(llh[:, 0])), -v[:, 2]])


def _imu_at(llh: np.ndarray, v: np.ndarray, a: np.ndarray, c: np.ndarray, w_nb: np.ndarray):
    """True body angular rate and specific force at given positions and motion."""
    lat, h = llh[:, 0], llh[:, 2]
    rm, rn = _radii_vec(lat)
    w_ie = np.stack([earth.OMEGA_E * np.cos(lat), np.zeros_like(lat), -earth.OMEGA_E * np.sin(lat)], 1)
    w_en = np.stack([v[:, 1] / (rn + h), -v[:, 0] / (rm + h), -v[:, 1] * np.tan(lat) / (rn + h)], 1)
    g = _gravity_vec(lat, h)
    g_n = np.stack([np.zeros_like(g), np.zeros_like(g), g], 1)
    f_n = a + np.cross(2 * w_ie + w_en, v) - g_n
    ct = np.transpose(c, (0, 2, 1))
    f_b = np.einsum("nij,nj->ni", ct, f_n)
    w_ib = np.einsum("nij,nj->ni", ct, w_ie + w_en) + w_nb
    return w_ib, f_b


def _gravity_vec(lat: np.ndarray, h: np.ndarray) -> np.ndarray:
    s2 = np.sin(lat) ** 2
    g0 = earth.GAMMA_E * (1.0 + earth._K_SOMIGLIANA * s2) / np.sqrt(1.0 - earth.E2 * s2)
    return g0 * (1.0 - 2.0 / earth.A * (1.0 + earth.F + earth._M - 2.0 * earth.F * s2) * h
                 + 3.0 * h * h / (earth.A * earth.A))


def generate(
    profile: KinematicProfile,
    duration: float,
    rate: float = 100.0,
    origin_llh: tuple[float, float, float] = (np.radians(39.95), np.radians(116.32), 50.0),
    t0: float = 0.0,
    quad_nodes: int = 6,
) -> Truth:
    """Generate a truth trajectory and its exact IMU increments.

    Parameters
    ----------
    profile : KinematicProfile
    duration : float
        Length [s].
    rate : float
        IMU rate [Hz].
    origin_llh : tuple of float
        Start latitude, longitude [rad], height [m].
    t0 : float
        Start time [s].
    quad_nodes : int
        Gauss-Legendre nodes per IMU interval.
    """
    n = int(round(duration * rate)) + 1
    t = t0 + np.arange(n) / rate
    x, wq = np.polynomial.legendre.leggauss(quad_nodes)
    dt = np.diff(t)
    tq = (t[:-1, None] + 0.5 * dt[:, None] * (x[None, :] + 1.0)).ravel()
    wts = (0.5 * dt[:, None] * wq[None, :])[..., None]
    vq, aq, cq, _, wnbq = _velocity(profile, tq)
    v, _, _, ang, _ = _velocity(profile, t)

    # position: Gauss-Legendre quadrature of the geodetic rates over each interval; the radii
    # depend on the (slowly varying) position, so two passes converge to double precision
    llh = np.tile(np.asarray(origin_llh, float), (n, 1))
    for _ in range(2):
        llh_q = np.repeat(llh[:-1], quad_nodes, axis=0)
        inc = (_geodetic_rates_vec(llh_q, vq).reshape(n - 1, quad_nodes, 3) * wts).sum(axis=1)
        llh = np.vstack([np.asarray(origin_llh, float), np.asarray(origin_llh, float) + np.cumsum(inc, axis=0)])
    # positions at the quadrature nodes (they only enter gravity and the transport rate)
    llh_q = CubicHermiteSpline(t, llh, _geodetic_rates_vec(llh, v), axis=0)(tq)

    w_ib, f_b = _imu_at(llh_q, vq, aq, cq, wnbq)
    dtheta = (w_ib.reshape(n - 1, quad_nodes, 3) * wts).sum(axis=1)
    dvel = (f_b.reshape(n - 1, quad_nodes, 3) * wts).sum(axis=1)
    return Truth(t, llh, v, ang, dtheta, dvel)
