"""15-state INS error model: continuous-time F, noise input G and Q, and discretisation.

State layout and sign conventions: :mod:`agent.nav.state`. The continuous model is
``dx/dt = F dx + G w`` with ``w = [gyro noise, accel noise, gyro-bias drive, accel-bias drive]``
(12 white-noise inputs with power spectral densities ``Qc``). Biases are first-order
Gauss-Markov processes (random walk when the correlation time is infinite).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slcp.geo import earth

from .state import ATT, BA, BG, N_STATES, VEL, NavState


@dataclass(frozen=True)
class ImuNoise:
    """IMU stochastic model in SI units (convert datasheet units at the config edge).

    Attributes
    ----------
    arw : float
        Angle random walk, gyro white-noise density [rad/s/sqrt(Hz)] = [rad/sqrt(s)].
    vrw : float
        Velocity random walk, accelerometer white-noise density [m/s^2/sqrt(Hz)].
    gyro_bias_sigma : float
        Steady-state standard deviation of the gyro bias process [rad/s].
    gyro_bias_tau : float
        Correlation time of the gyro bias [s]; ``inf`` for a random walk, in which case
        ``gyro_bias_sigma`` is read as the random-walk density [rad/s/sqrt(s)].
    accel_bias_sigma, accel_bias_tau : float
        Same for the accelerometer bias [m/s^2], [s].
    """

    arw: float
    vrw: float
    gyro_bias_sigma: float
    gyro_bias_tau: float
    accel_bias_sigma: float
    accel_bias_tau: float

    def psd(self) -> np.ndarray:
        """Diagonal of Qc, shape (12,): PSDs of the 12 white-noise inputs."""

        def drive(sigma: float, tau: float) -> float:
            return sigma**2 if math.isinf(tau) else 2.0 * sigma**2 / tau

        return np.repeat(
            [
                self.arw**2,
                self.vrw**2,
                drive(self.gyro_bias_sigma, self.gyro_bias_tau),
                drive(self.accel_bias_sigma, self.accel_bias_tau),
            ],
            3,
        )


def system_matrix(
    state: NavState, f_n: np.ndarray, noise: ImuNoise
) -> np.ndarray:
    """Continuous-time error-state matrix F, shape (15, 15).

    Parameters
    ----------
    state : NavState
        Nominal state the model is linearised about.
    f_n : ndarray, shape (3,)
        Specific force resolved in NED [m/s^2] (mean over the propagation interval).
    noise : ImuNoise
        Supplies the bias correlation times.
    """
    lat, h = float(state.lat), float(state.h)
    vn, ve, vd = state.v.tolist()
    rm, rn = earth.radii(lat)
    rmh, rnh = rm + h, rn + h
    w = earth.OMEGA_E
    sl, cl = math.sin(lat), math.cos(lat)
    tl = sl / cl
    c_bn = state.dcm
    dg_dh = earth.gravity_height_gradient(lat, h)
    fn, fe, fd = np.asarray(f_n, float).tolist()

    F = np.zeros((N_STATES, N_STATES))
    # attitude error (rows 0-2): position, velocity, attitude, gyro bias
    F[0, 6] = -w * sl / rmh
    F[0, 8] = ve / (rnh * rnh)
    F[1, 8] = -vn / (rmh * rmh)
    F[2, 6] = -w * cl / rmh - ve / (rmh * rnh * cl * cl)
    F[2, 8] = -ve * tl / (rnh * rnh)
    F[0, 4] = 1.0 / rnh
    F[1, 3] = -1.0 / rmh
    F[2, 4] = -tl / rnh
    win_n, win_e, win_d = w * cl + ve / rnh, -vn / rmh, -w * sl - ve * tl / rnh
    F[0, 1], F[0, 2] = win_d, -win_e
    F[1, 0], F[1, 2] = -win_d, win_n
    F[2, 0], F[2, 1] = win_e, -win_n
    F[ATT, BG] = c_bn
    # velocity error (rows 3-5)
    F[3, 6] = -2.0 * ve * w * cl / rmh - ve * ve / (rmh * rnh * cl * cl)
    F[3, 8] = vn * vd / (rmh * rmh) - ve * ve * tl / (rnh * rnh)
    F[4, 6] = 2.0 * w * (vn * cl - vd * sl) / rmh + vn * ve / (rmh * rnh * cl * cl)
    F[4, 8] = (ve * vd + vn * ve * tl) / (rnh * rnh)
    F[5, 6] = 2.0 * w * ve * sl / rmh
    F[5, 8] = -ve * ve / (rnh * rnh) - vn * vn / (rmh * rmh) - dg_dh
    F[3, 3] = vd / rmh
    F[3, 4] = -2.0 * (w * sl + ve * tl / rnh)
    F[3, 5] = vn / rmh
    F[4, 3] = 2.0 * w * sl + ve * tl / rnh
    F[4, 4] = (vd + vn * tl) / rnh
    F[4, 5] = 2.0 * w * cl + ve / rnh
    F[5, 3] = -2.0 * vn / rmh
    F[5, 4] = -2.0 * (w * cl + ve / rnh)
    F[3, 1], F[3, 2] = -fd, fe
    F[4, 0], F[4, 2] = fd, -fn
    F[5, 0], F[5, 1] = -fe, fn
    F[VEL, BA] = -c_bn
    # position error (rows 6-8)
    F[6, 6] = -vd / rmh
    F[6, 8] = vn / rmh
    F[7, 6] = ve * tl / rnh
    F[7, 7] = -(vd + vn * tl) / rnh
    F[7, 8] = ve / rnh
    F[6, 3] = F[7, 4] = F[8, 5] = 1.0
    # biases: first-order Gauss-Markov
    if not math.isinf(noise.gyro_bias_tau):
        F[9, 9] = F[10, 10] = F[11, 11] = -1.0 / noise.gyro_bias_tau
    if not math.isinf(noise.accel_bias_tau):
        F[12, 12] = F[13, 13] = F[14, 14] = -1.0 / noise.accel_bias_tau
    return F


def noise_input_matrix(state: NavState) -> np.ndarray:
    """Noise input matrix G, shape (15, 12), for ``w`` as in the module docstring."""
    c_bn = state.dcm
    G = _G_TEMPLATE.copy()
    G[ATT, 0:3] = -c_bn
    G[VEL, 3:6] = c_bn
    return G


_G_TEMPLATE = np.zeros((N_STATES, 12))
_G_TEMPLATE[BG, 6:9] = np.eye(3)
_G_TEMPLATE[BA, 9:12] = np.eye(3)


def process_noise_density(noise: ImuNoise) -> np.ndarray:
    """Diagonal of ``G Qc Gᵀ``, shape (15,): the density is constant and diagonal because the
    attitude and velocity blocks are ``C (σ² I) Cᵀ = σ² I`` for an orthonormal C and isotropic
    sensor noise."""
    return np.concatenate([np.full(3, noise.arw**2), np.full(3, noise.vrw**2),
                           np.zeros(3), noise.psd()[6:]])


def discretize_density(
    F: np.ndarray, gqg: np.ndarray, dt: float, method: str = "series"
) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`discretize` but with the noise density ``G Qc Gᵀ`` given directly: a full
    (n, n) matrix or, for a diagonal density, its diagonal of shape (n,)."""
    n = F.shape[0]
    q_diag = gqg if gqg.ndim == 1 else None
    if q_diag is not None:
        gqg = np.diag(q_diag)
    if method == "series":
        fdt = F * dt
        f2 = fdt @ fdt
        phi = fdt + 0.5 * f2 + (f2 @ fdt) * (1.0 / 6.0)
        phi.flat[:: n + 1] += 1.0
        # F Q with a diagonal Q is a column scaling
        fq = fdt * q_diag if q_diag is not None else fdt @ gqg
        a = fq + fdt @ fq * (1.0 / 3.0)
        qd = a + a.T
        qd *= 0.5
        qd += (fq @ fdt.T) * (1.0 / 3.0)
        qd += gqg
        qd *= dt
    elif method == "van_loan":
        from scipy.linalg import expm  # deferred: the series is the run-time method

        m = np.zeros((2 * n, 2 * n))
        m[:n, :n] = -F
        m[:n, n:] = gqg
        m[n:, n:] = F.T
        e = expm(m * dt)
        phi = e[n:, n:].T
        qd = phi @ e[:n, n:]
    else:
        raise ValueError(f"unknown discretisation method {method!r}; use 'series' or 'van_loan'")
    return phi, 0.5 * (qd + qd.T)


def discretize(
    F: np.ndarray, G: np.ndarray, qc: np.ndarray, dt: float, method: str = "series"
) -> tuple[np.ndarray, np.ndarray]:
    """Discrete transition Φ and process noise Qd over ``dt``.

    Parameters
    ----------
    F : ndarray, shape (n, n)
    G : ndarray, shape (n, m)
    qc : ndarray, shape (m,)
        Diagonal of the continuous noise PSD.
    dt : float
        Interval [s].
    method : {"series", "van_loan"}
        ``series``: Φ = I + FΔt + (FΔt)²/2 + (FΔt)³/6 and, with Q = G Qc Gᵀ,
        Qd = QΔt + (FQ + QFᵀ)Δt²/2 + (F²Q + 2FQFᵀ + QF²ᵀ)Δt³/6 (exact to third order, so the
        position variance from velocity noise is qΔt³/3); ``van_loan``: exact for constant F
        (matrix exponential, ~10x slower).

    Returns
    -------
    phi, qd : ndarray, shape (n, n)
    """
    return discretize_density(F, (G * qc) @ G.T, dt, method)


def unknown_heading_noise(f_n: np.ndarray, dt: float) -> np.ndarray:
    """The velocity noise [m²/s²] (3, 3) of a step of ``dt`` s with the heading unknown: the
    horizontal specific force ``f_n`` goes in an unknown direction, so the velocity error grows
    by up to twice its increment (180° off). As process noise, the velocity updates of a
    creeping start then correct the velocity, not the tilt."""
    q = np.zeros((3, 3))
    q[0, 0] = q[1, 1] = (2.0 * math.hypot(f_n[0], f_n[1]) * dt) ** 2
    return q


def gap_transition(n: int, gap: float, sigma_accel: tuple[float, float], sigma_rate: tuple[float, float],
                   gqg: np.ndarray, aug_tau: np.ndarray, aug_psd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Φ and Q_d (n, n) over ``gap`` s without IMU data: the position error grows by the
    velocity error; the vehicle may have had an unknown constant acceleration of σ
    ``sigma_accel`` (horizontal, vertical) [m/s²] and turn rate of σ ``sigma_rate`` (roll and
    pitch, yaw) [rad/s]; the biases (density ``gqg``) and the augmented Gauss-Markov states
    (``aug_tau``, ``aug_psd``) follow their processes exactly."""
    phi = np.eye(n)
    phi[6:9, 3:6] = np.eye(3) * gap  # dr' = dr + G dv
    qd = np.zeros((n, n))
    for k, sa in enumerate((sigma_accel[0], sigma_accel[0], sigma_accel[1])):
        a, b = 3 + k, 6 + k
        qd[a, a] = (sa * gap) ** 2
        qd[b, b] = (sa * gap * gap / 2.0) ** 2
        qd[a, b] = qd[b, a] = sa * sa * gap**3 / 2.0
    for k, sr in enumerate((sigma_rate[0], sigma_rate[0], sigma_rate[1])):
        qd[k, k] = (sr * gap) ** 2
    for k in range(9, 15):
        qd[k, k] = gqg[k] * gap
    if n > 15:
        decay = np.exp(-gap / aug_tau)
        idx = np.arange(15, n)
        phi[idx, idx] = decay
        with np.errstate(invalid="ignore"):
            qd[idx, idx] = np.where(np.isinf(aug_tau), aug_psd * gap, aug_psd * aug_tau / 2.0 * (1.0 - decay**2))
    return phi, qd


def level_from_accel(f_b_mean: np.ndarray) -> tuple[float, float]:
    """Coarse levelling: roll and pitch [rad] from the mean specific force at rest (FRD)."""
    fx, fy, fz = f_b_mean
    roll = math.atan2(-fy, -fz)
    pitch = math.atan2(fx, math.hypot(fy, fz))
    return roll, pitch
