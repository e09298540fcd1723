"""IMU error model: increments with turn-on bias, in-run bias, white noise, scale factor and
misalignment.

Defaults approximate an Xsens MTi-630 (industrial MEMS): gyro in-run bias stability 8 °/h,
angle random walk 0.007 °/s/√Hz, accelerometer noise 60 µg/√Hz, accelerometer bias stability
15 µg; turn-on biases, scale factors and misalignments are typical of the class.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slcp.vehicles.profile import ImuSpec

from . import params
from .processes import gauss_markov

G0 = 9.80665
DEG = math.pi / 180.0


@dataclass(frozen=True)
class ImuModel:
    """IMU stochastic and deterministic errors (SI units).

    Attributes
    ----------
    arw : float
        Gyro white noise density [rad/s/√Hz].
    vrw : float
        Accelerometer white noise density [m/s²/√Hz].
    gyro_turn_on, accel_turn_on : float
        Standard deviation of the constant turn-on bias [rad/s], [m/s²].
    gyro_in_run, accel_in_run : float
        Standard deviation of the in-run (Gauss-Markov) bias [rad/s], [m/s²].
    bias_tau : float
        Correlation time of the in-run biases [s].
    gyro_scale, accel_scale : float
        Standard deviation of the per-axis scale-factor error [-].
    misalignment : float
        Standard deviation of the per-axis small-angle misalignment [rad].
    """

    arw: float = 0.007 * DEG
    vrw: float = 60e-6 * G0
    gyro_turn_on: float = 0.05 * DEG
    accel_turn_on: float = 2e-3 * G0
    gyro_in_run: float = 8.0 * DEG / 3600.0
    accel_in_run: float = 15e-6 * G0
    bias_tau: float = 600.0
    gyro_scale: float = 1e-3
    accel_scale: float = 1e-3
    misalignment: float = 0.05 * DEG

    def __post_init__(self) -> None:
        params.non_negative(self, "arw", "vrw", "gyro_turn_on", "accel_turn_on", "gyro_in_run",
                            "accel_in_run", "gyro_scale", "accel_scale", "misalignment")
        params.positive(self, "bias_tau")


def imu_model_of(spec: ImuSpec) -> ImuModel:
    """The emulated IMU of a vehicle profile's ``[imu]``: its datasheet noise (without the
    profile's inflation for the vehicle, which is the filter's), biases and scale factors."""
    return ImuModel(arw=math.radians(spec.gyro_noise_dps_rthz), vrw=spec.accel_noise_ug_rthz * 1e-6 * G0,
                    gyro_turn_on=spec.gyro_turn_on, accel_turn_on=spec.accel_turn_on,
                    gyro_in_run=spec.gyro_bias, accel_in_run=spec.accel_bias, bias_tau=spec.bias_correlation_s,
                    gyro_scale=spec.scale_factor_ppm * 1e-6, accel_scale=spec.scale_factor_ppm * 1e-6)


@dataclass(frozen=True)
class ImuErrors:
    """Measured increments and the error terms that produced them.

    Attributes
    ----------
    dtheta, dvel : ndarray, shape (n, 3)
        Measured angle [rad] and velocity [m/s] increments.
    gyro_bias, accel_bias : ndarray, shape (n, 3)
        True total biases per interval [rad/s], [m/s²].
    gyro_matrix, accel_matrix : ndarray, shape (3, 3)
        ``I + scale + misalignment`` applied to the true increments.
    """

    dtheta: np.ndarray
    dvel: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    gyro_matrix: np.ndarray
    accel_matrix: np.ndarray


def _error_matrix(scale_sigma: float, mis_sigma: float, rng: np.random.Generator) -> np.ndarray:
    s = rng.normal(0.0, scale_sigma, 3)
    m = rng.normal(0.0, mis_sigma, 3)
    return np.eye(3) + np.diag(s) + np.array([[0.0, -m[2], m[1]], [m[2], 0.0, -m[0]], [-m[1], m[0], 0.0]])


def corrupt_increments(model: ImuModel, dtheta: np.ndarray, dvel: np.ndarray, dt: np.ndarray,
                       rng: np.random.Generator) -> ImuErrors:
    """Apply the IMU errors to true increments of shape (n, 3) over intervals ``dt`` (n,) [s]."""
    dtheta = np.asarray(dtheta, float)
    dvel = np.asarray(dvel, float)
    dt = np.asarray(dt, float)
    n = len(dt)
    if dtheta.shape != (n, 3) or dvel.shape != (n, 3):
        raise ValueError(f"increments must have shape ({n}, 3)")
    mg = _error_matrix(model.gyro_scale, model.misalignment, rng)
    ma = _error_matrix(model.accel_scale, model.misalignment, rng)
    step = float(np.median(dt)) if n else 0.01
    bg = rng.normal(0.0, model.gyro_turn_on, 3) + gauss_markov(n, step, model.gyro_in_run, model.bias_tau, rng, 3)
    ba = rng.normal(0.0, model.accel_turn_on, 3) + gauss_markov(n, step, model.accel_in_run, model.bias_tau, rng, 3)
    sq = np.sqrt(dt)[:, None]
    meas_th = dtheta @ mg.T + bg * dt[:, None] + rng.normal(0.0, model.arw, (n, 3)) * sq
    meas_dv = dvel @ ma.T + ba * dt[:, None] + rng.normal(0.0, model.vrw, (n, 3)) * sq
    return ImuErrors(meas_th, meas_dv, bg, ba, mg, ma)
