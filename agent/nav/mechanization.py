"""Strapdown INS mechanisation on the WGS-84 ellipsoid in the local NED frame.

One step integrates one IMU interval given as *increments* (angle Δθ [rad] and velocity Δv
[m/s] over the interval, body FRD) with that interval's own Δt, so jittery sample times are
handled exactly. Two-sample coning and sculling corrections use the previous interval's
increments; earth rate, transport rate and normal gravity are included (Groves 2013, §5.4-5.5;
Shin 2005).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from slcp.geo import earth

from .rotation import skew
from .state import NavState


def mechanize(
    state: NavState,
    dtheta: np.ndarray,
    dvel: np.ndarray,
    dt: float,
    dtheta_prev: np.ndarray | None = None,
    dvel_prev: np.ndarray | None = None,
) -> NavState:
    """Propagate the nominal state over one IMU interval.

    Parameters
    ----------
    state : NavState
        State at the start of the interval (its biases are subtracted from the increments).
    dtheta, dvel : ndarray, shape (3,)
        Raw angle [rad] and velocity [m/s] increments over the interval, body frame.
    dt : float
        Interval length [s] (> 0).
    dtheta_prev, dvel_prev : ndarray, shape (3,), optional
        Bias-corrected increments of the previous interval, for coning/sculling. ``None``
        (first sample, or after a data gap) disables the two-sample terms.

    Returns
    -------
    NavState
        State at the end of the interval; biases are carried over unchanged.

    Notes
    -----
    Written with scalar arithmetic: on 3-vectors this is ~5x faster than numpy.
    """
    prev_th = None if dtheta_prev is None else tuple(np.asarray(dtheta_prev, float).tolist())
    prev_dv = None if dvel_prev is None else tuple(np.asarray(dvel_prev, float).tolist())
    return mechanize_fast(state, np.asarray(dtheta, float).tolist(), np.asarray(dvel, float).tolist(),
                          float(dt), prev_th, prev_dv)[0]


def mechanize_fast(
    state: NavState,
    dtheta: list[float] | tuple[float, float, float],
    dvel: list[float] | tuple[float, float, float],
    dt: float,
    prev_th: tuple[float, float, float] | None,
    prev_dv: tuple[float, float, float] | None,
) -> tuple[NavState, tuple[float, float, float], tuple[float, float, float]]:
    """:func:`mechanize` on plain float sequences, for hot loops.

    Returns the new state and this interval's bias-corrected angle and velocity increments
    (to pass as ``prev_th``/``prev_dv`` to the next call).
    """
    new, th, dv, _, _ = mechanize_run(state, (dtheta,), (dvel,), (dt,), prev_th, prev_dv)
    return new, th, dv


def mechanize_run(
    state: NavState,
    dtheta: Sequence[Sequence[float]],
    dvel: Sequence[Sequence[float]],
    dt: Sequence[float],
    prev_th: tuple[float, float, float] | None,
    prev_dv: tuple[float, float, float] | None,
    sums: tuple[Sequence[float], Sequence[float]] | None = None,
    velocities: list[tuple[float, float, float]] | None = None,
) -> tuple[NavState, tuple[float, float, float], tuple[float, float, float],
           tuple[float, float, float], tuple[float, float, float]]:
    """:func:`mechanize` over ``n`` consecutive IMU intervals, sample by sample.

    Long: the strapdown step unrolled in scalar float arithmetic, one loop and no calls, the
    hot path of every filter (a call per term costs more than the term).

    The same algorithm and arithmetic as ``n`` calls of :func:`mechanize_fast` (results agree
    to rounding), with the state held in local floats between samples: no per-sample state
    objects, which is most of the cost in Python.

    Parameters
    ----------
    state : NavState
        State at the start of the first interval (its biases are subtracted).
    dtheta, dvel : sequence of n 3-sequences of float
        Raw angle [rad] and velocity [m/s] increments of each interval, body FRD (lists of
        lists or tuples; not numpy rows, whose scalars are slow).
    dt : sequence of n float
        Interval lengths [s].
    prev_th, prev_dv : tuple of 3 float, optional
        Bias-corrected increments of the interval before the first (two-sample coning and
        sculling); None disables those terms for the first interval.
    sums : pair of 3-sequences of float, optional
        Running sums to add this run's bias-corrected increments to, sample by sample (the
        same rounding as one call per sample); default zeros.
    velocities : list, optional
        Gets each interval's NED velocity [m/s] at its *start* appended, as a tuple.

    Returns
    -------
    state : NavState
        State at the end of the last interval.
    last_th, last_dv : tuple of 3 float
        The last interval's bias-corrected increments (``prev_th``/``prev_dv`` of the next call).
    sum_th, sum_dv : tuple of 3 float
        Sums of the bias-corrected angle [rad] and velocity [m/s] increments (body frame),
        added to ``sums`` when given.
    """
    if not len(dt):
        raise ValueError("mechanize_run needs at least one interval")
    # python floats: numpy scalars are ~3x slower in scalar arithmetic
    gx, gy, gz = state.bg.tolist()
    fx, fy, fz = state.ba.tolist()
    lat, lon, h = float(state.lat), float(state.lon), float(state.h)
    vn, ve, vd = state.v.tolist()
    qw, qx_, qy_, qz_ = state.q.tolist()
    sin, cos, sqrt = math.sin, math.cos, math.sqrt
    A, E2, OMEGA_E = earth.A, earth.E2, earth.OMEGA_E
    GAMMA_E, K_SOM, F_, M_ = earth.GAMMA_E, earth._K_SOMIGLIANA, earth.F, earth._M
    sth = [0.0, 0.0, 0.0] if sums is None else [float(x) for x in sums[0]]
    sdv = [0.0, 0.0, 0.0] if sums is None else [float(x) for x in sums[1]]
    ax = ay = az = ux = uy = uz = 0.0
    for k in range(len(dt)):
        dt_k = dt[k]
        if velocities is not None:
            velocities.append((vn, ve, vd))
        ax, ay, az = dtheta[k]
        ux, uy, uz = dvel[k]
        ax, ay, az = ax - gx * dt_k, ay - gy * dt_k, az - gz * dt_k
        ux, uy, uz = ux - fx * dt_k, uy - fy * dt_k, uz - fz * dt_k
        sth[0] += ax
        sth[1] += ay
        sth[2] += az
        sdv[0] += ux
        sdv[1] += uy
        sdv[2] += uz
        slat, clat = sin(lat), cos(lat)
        w = 1.0 - E2 * slat * slat
        rn = A / sqrt(w)
        rm = rn * (1.0 - E2) / w
        wie_n, wie_d = OMEGA_E * clat, -OMEGA_E * slat
        wen_n, wen_e, wen_d = ve / (rn + h), -vn / (rm + h), -ve * slat / clat / (rn + h)
        win_n, win_e, win_d = wie_n + wen_n, wen_e, wie_d + wen_d

        # velocity: rotation + sculling compensated specific-force increment (body)
        bx = ux + 0.5 * (ay * uz - az * uy)
        by = uy + 0.5 * (az * ux - ax * uz)
        bz = uz + 0.5 * (ax * uy - ay * ux)
        if prev_th is not None and prev_dv is not None:
            px, py, pz = prev_th
            qx, qy, qz = prev_dv
            bx += ((py * uz - pz * uy) + (qy * az - qz * ay)) / 12.0
            by += ((pz * ux - px * uz) + (qz * ax - qx * az)) / 12.0
            bz += ((px * uy - py * ux) + (qx * ay - qy * ax)) / 12.0
        c00 = 1 - 2 * (qy_ * qy_ + qz_ * qz_)
        c01 = 2 * (qx_ * qy_ - qw * qz_)
        c02 = 2 * (qx_ * qz_ + qw * qy_)
        c10 = 2 * (qx_ * qy_ + qw * qz_)
        c11 = 1 - 2 * (qx_ * qx_ + qz_ * qz_)
        c12 = 2 * (qy_ * qz_ - qw * qx_)
        c20 = 2 * (qx_ * qz_ - qw * qy_)
        c21 = 2 * (qy_ * qz_ + qw * qx_)
        c22 = 1 - 2 * (qx_ * qx_ + qy_ * qy_)
        nx = c00 * bx + c01 * by + c02 * bz
        ny = c10 * bx + c11 * by + c12 * bz
        nz = c20 * bx + c21 * by + c22 * bz
        # (I - [0.5 w_in dt ×]) rotation of the navigation frame over the interval
        hx, hy, hz = 0.5 * dt_k * win_n, 0.5 * dt_k * win_e, 0.5 * dt_k * win_d
        dvn = nx - (hy * nz - hz * ny)
        dve = ny - (hz * nx - hx * nz)
        dvd = nz - (hx * ny - hy * nx)
        # normal gravity (earth.gravity written out with this sample's sin²(lat))
        s2 = slat * slat
        g = (GAMMA_E * (1.0 + K_SOM * s2) / sqrt(w)
             * (1.0 - 2.0 / A * (1.0 + F_ + M_ - 2.0 * F_ * s2) * h + 3.0 * h * h / (A * A)))
        kx, ky, kz = 2.0 * wie_n + wen_n, wen_e, 2.0 * wie_d + wen_d
        vn1 = vn + dvn - dt_k * (ky * vd - kz * ve)
        ve1 = ve + dve - dt_k * (kz * vn - kx * vd)
        vd1 = vd + dvd + dt_k * (g - (kx * ve - ky * vn))

        # position: trapezoidal velocity, curvature at the mid-point (Groves eq. 5.56)
        h1 = h - 0.5 * (vd + vd1) * dt_k
        hm = 0.5 * (h + h1)
        lat1 = lat + 0.5 * (vn + vn1) * dt_k / (rm + hm)
        latm = 0.5 * (lat + lat1)
        rnm = A / sqrt(1.0 - E2 * sin(latm) ** 2)
        lon = lon + 0.5 * (ve + ve1) * dt_k / ((rnm + hm) * cos(latm))
        lat, h, vn, ve, vd = lat1, h1, vn1, ve1, vd1

        # attitude: q_new = q(-w_in dt) ⊗ q ⊗ q(phi_b), phi_b with two-sample coning
        cx, cy, cz = ax, ay, az
        if prev_th is not None:
            px, py, pz = prev_th
            cx, cy, cz = (
                ax + (py * az - pz * ay) / 12.0,
                ay + (pz * ax - px * az) / 12.0,
                az + (px * ay - py * ax) / 12.0,
            )
        # rotation vectors to quaternions (series below 1e-8 rad) and the two quaternion
        # products, written out: function calls were a third of the loop's cost
        a2 = cx * cx + cy * cy + cz * cz
        if a2 < 1e-16:
            s_, bw = 0.5 - a2 / 48.0, 1.0 - a2 / 8.0
        else:
            an = sqrt(a2)
            s_, bw = sin(0.5 * an) / an, cos(0.5 * an)
        bi, bj, bk = s_ * cx, s_ * cy, s_ * cz
        ni, nj, nk = -win_n * dt_k, -win_e * dt_k, -win_d * dt_k
        a2 = ni * ni + nj * nj + nk * nk
        if a2 < 1e-16:
            s_, nw = 0.5 - a2 / 48.0, 1.0 - a2 / 8.0
        else:
            an = sqrt(a2)
            s_, nw = sin(0.5 * an) / an, cos(0.5 * an)
        ni, nj, nk = s_ * ni, s_ * nj, s_ * nk
        tw = nw * qw - ni * qx_ - nj * qy_ - nk * qz_
        ti = nw * qx_ + ni * qw + nj * qz_ - nk * qy_
        tj = nw * qy_ - ni * qz_ + nj * qw + nk * qx_
        tk = nw * qz_ + ni * qy_ - nj * qx_ + nk * qw
        qw = tw * bw - ti * bi - tj * bj - tk * bk
        qx_ = tw * bi + ti * bw + tj * bk - tk * bj
        qy_ = tw * bj - ti * bk + tj * bw + tk * bi
        qz_ = tw * bk + ti * bj - tj * bi + tk * bw
        inv = 1.0 / sqrt(qw * qw + qx_ * qx_ + qy_ * qy_ + qz_ * qz_)
        if qw < 0:
            inv = -inv
        qw, qx_, qy_, qz_ = qw * inv, qx_ * inv, qy_ * inv, qz_ * inv
        prev_th, prev_dv = (ax, ay, az), (ux, uy, uz)
    new = NavState(lat, lon, h, np.array([vn, ve, vd]), np.array([qw, qx_, qy_, qz_]), state.bg, state.ba)
    return new, (ax, ay, az), (ux, uy, uz), (sth[0], sth[1], sth[2]), (sdv[0], sdv[1], sdv[2])


def continuous_dynamics(
    state: NavState, omega_ib_b: np.ndarray, f_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Continuous-time navigation equations (used by truth generators and Jacobian tests).

    Parameters
    ----------
    state : NavState
        Current state (biases ignored: the inputs are true rates).
    omega_ib_b : ndarray, shape (3,)
        Angular rate of body w.r.t. inertial space, body frame [rad/s].
    f_b : ndarray, shape (3,)
        Specific force, body frame [m/s^2].

    Returns
    -------
    llh_dot : ndarray, shape (3,)
        ``[dLat/dt rad/s, dLon/dt rad/s, dh/dt m/s]``.
    v_dot : ndarray, shape (3,)
        NED acceleration [m/s^2].
    c_dot : ndarray, shape (3, 3)
        Derivative of the body-to-NED DCM.
    """
    w_ie = earth.earth_rate_ned(state.lat)
    w_en = earth.transport_rate_ned(state.lat, state.h, state.v)
    c = state.dcm
    g = np.array([0.0, 0.0, earth.gravity(state.lat, state.h)])
    v_dot = c @ f_b - np.cross(2.0 * w_ie + w_en, state.v) + g
    c_dot = c @ skew(omega_ib_b) - skew(w_ie + w_en) @ c
    return np.array(earth.geodetic_rates(state.lat, state.h, state.v)), v_dot, c_dot


def split_increment(
    dtheta: np.ndarray, dvel: np.ndarray, t0: float, t1: float, t_split: float
) -> tuple[tuple[np.ndarray, np.ndarray, float], tuple[np.ndarray, np.ndarray, float]]:
    """Split an IMU interval [t0, t1] at ``t_split`` (e.g. a GNSS epoch) by linear interpolation.

    Returns two ``(dtheta, dvel, dt)`` parts; increments are shared in proportion to time.
    """
    if not t0 < t_split < t1:
        raise ValueError(f"split time {t_split} outside ({t0}, {t1})")
    a = (t_split - t0) / (t1 - t0)
    return (a * dtheta, a * dvel, t_split - t0), ((1 - a) * dtheta, (1 - a) * dvel, t1 - t_split)
