"""Seeded Monte-Carlo consistency of the SP filter on a simulated drive.

GNSS errors are white plus a first-order Gauss-Markov part (multipath-like). The filter carries
the Gauss-Markov error as three extra states (the consistent treatment); a second test shows that
a filter which only inflates R by the Gauss-Markov variance is overconfident, because it averages
correlated fixes as if they were independent. Acceptance: horizontal RMS(error/σ) < 1.5 and the
GNSS NIS average inside its two-sided 95 % χ² band.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from slcp.agent.nav.error_model import ImuNoise
from slcp.agent.nav.ins_filter import InsFilter
from slcp.agent.nav.kalman import Measurement
from slcp.agent.nav.measurements.gnss import gnss_position, gnss_velocity
from slcp.agent.nav.rotation import euler_to_quat
from slcp.agent.nav.state import NavState, apply_error
from slcp.geo import earth
from slcp.hw_emulation.kinematics import SinusoidProfile, generate

NOISE = ImuNoise(arw=math.radians(0.2) / 60, vrw=0.1 / 60,
                 gyro_bias_sigma=math.radians(20) / 3600, gyro_bias_tau=3600.0,
                 accel_bias_sigma=0.01, accel_bias_tau=3600.0)
SIGMA_WHITE = np.array([0.6, 0.6, 1.0])
SIGMA_GM = np.array([0.5, 0.5, 0.8])
TAU_GM = 2.0
SIGMA_VEL = 0.1
GNSS_RATE = 5
N_RUNS = 12
DURATION = 90.0
SETTLE = 20.0


@pytest.fixture(scope="module")
def truth():
    prof = SinusoidProfile(speed0=9.0, speed_terms=((2.0, 0.1, 0.0),),
                           yaw_terms=((1.2, 0.06, 0.0),), pitch_terms=((0.01, 0.2, 0.0),))
    return generate(prof, DURATION)


def _one_run(truth, seed: int, model_gm: bool = True):
    rng = np.random.default_rng(seed)
    dt_imu = float(truth.t[1] - truth.t[0])
    bg = rng.normal(0, NOISE.gyro_bias_sigma, 3)
    ba = rng.normal(0, NOISE.accel_bias_sigma, 3)
    n = len(truth.t) - 1
    dth = truth.dtheta + bg * dt_imu + rng.normal(0, NOISE.arw * math.sqrt(dt_imu), (n, 3))
    dvl = truth.dvel + ba * dt_imu + rng.normal(0, NOISE.vrw * math.sqrt(dt_imu), (n, 3))

    true0 = NavState(*truth.llh[0], truth.v_ned[0].copy(), euler_to_quat(*truth.euler[0]), bg, ba)
    p0 = np.concatenate([np.radians([1.0, 1.0, 3.0]), [0.2] * 3, [2.0] * 3,
                         [NOISE.gyro_bias_sigma] * 3, [NOISE.accel_bias_sigma] * 3]) ** 2
    est0 = apply_error(true0, rng.normal(0, np.sqrt(p0)))  # initial error drawn from P0
    extra = tuple((0.0, float(s), 2 * float(s) ** 2 / TAU_GM, TAU_GM) for s in SIGMA_GM) if model_gm else ()
    flt = InsFilter(est0, np.diag(p0), NOISE, t=float(truth.t[0]), cov_interval=0.05, extra_states=extra)

    phi = math.exp(-1.0 / (GNSS_RATE * TAU_GM))
    gm = rng.normal(0, SIGMA_GM)
    r_pos = np.diag(SIGMA_WHITE**2 + (0.0 if model_gm else SIGMA_GM**2))
    step = int(round(1.0 / (GNSS_RATE * dt_imu)))
    z_norm, nis = [], []
    for k in range(n):
        flt.propagate(dth[k], dvl[k], dt_imu)
        if (k + 1) % step:
            continue
        i = k + 1
        gm = phi * gm + math.sqrt(1 - phi * phi) * rng.normal(0, SIGMA_GM)
        err_ned = gm + rng.normal(0, SIGMA_WHITE)
        lat, lon, h = truth.llh[i]
        rm, rn = earth.radii(lat)
        meas_llh = np.array([lat + err_ned[0] / (rm + h), lon + err_ned[1] / ((rn + h) * math.cos(lat)),
                             h - err_ned[2]])
        v_meas = truth.v_ned[i] + rng.normal(0, SIGMA_VEL, 3)
        if truth.t[i] - truth.t[0] >= SETTLE:
            e = earth.ned_offset(flt.state.lat, flt.state.lon, flt.state.h, lat, lon, h)
            sig = np.sqrt(np.diag(flt.position_cov))
            z_norm.append(e[:2] / sig[:2])
        m = gnss_position(flt.state, meas_llh, r_pos)
        if model_gm:  # predicted = p_est + gm_est, measured = p + gm + white
            m = Measurement(m.z + flt.extra, np.hstack([m.H, np.eye(3)]), m.R, m.name)
        res = flt.update(m)
        flt.update(gnss_velocity(flt.state, v_meas, np.eye(3) * SIGMA_VEL**2, np.zeros(3)))
        if truth.t[i] - truth.t[0] >= SETTLE:
            nis.append(res.nis)
    return np.array(z_norm), np.array(nis)


def _monte_carlo(truth, model_gm: bool):
    zs, nis = zip(*(_one_run(truth, 1000 + r, model_gm) for r in range(N_RUNS)))
    z = np.concatenate(zs)
    nis_all = np.concatenate(nis)
    return float(np.sqrt(np.mean(z**2))), float(nis_all.mean()), len(nis_all)


@pytest.mark.slow
def test_monte_carlo_error_over_sigma_and_nis(truth) -> None:
    rms_norm, mean_nis, n = _monte_carlo(truth, model_gm=True)
    # the innovations of a consistent filter are white: n independent 3-dof samples
    lo, hi = chi2.ppf([0.025, 0.975], 3 * n) / n
    print(f"RMS(error/sigma) horizontal = {rms_norm:.3f}; GNSS NIS mean = {mean_nis:.3f} "
          f"(3 dof, 95 % band {lo:.3f}-{hi:.3f}, {n} epochs)")
    assert rms_norm < 1.5
    assert lo <= mean_nis <= hi


@pytest.mark.slow
def test_treating_correlated_gnss_error_as_white_is_overconfident(truth) -> None:
    rms_norm, _, _ = _monte_carlo(truth, model_gm=False)
    print(f"R inflated only: RMS(error/sigma) horizontal = {rms_norm:.3f}")
    assert rms_norm > 1.5


def test_scale_factor_states_estimate_a_gyro_scale_error() -> None:
    """A 2 % gyro-z scale error on a winding drive: the scale-factor state converges to it."""
    prof = SinusoidProfile(speed0=8.0, yaw_terms=((2.0, 0.15, 0.0),))
    tr = generate(prof, 120.0)
    rng = np.random.default_rng(7)
    s_true = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.02])  # accel xyz, gyro xyz
    dt = float(tr.t[1] - tr.t[0])
    dth = tr.dtheta * (1 + s_true[3:]) + rng.normal(0, NOISE.arw * math.sqrt(dt), tr.dtheta.shape)
    dvl = tr.dvel * (1 + s_true[:3]) + rng.normal(0, NOISE.vrw * math.sqrt(dt), tr.dvel.shape)
    st = NavState(*tr.llh[0], tr.v_ned[0].copy(), euler_to_quat(*tr.euler[0]))
    p0 = np.concatenate([np.radians([0.5, 0.5, 1.0]), [0.1] * 3, [0.5] * 3,
                         [NOISE.gyro_bias_sigma] * 3, [NOISE.accel_bias_sigma] * 3]) ** 2
    flt = InsFilter(st, np.diag(p0), NOISE, t=0.0, cov_interval=0.05, scale_factors=(0.01, 0.03, 3600.0))
    for k in range(len(tr.t) - 1):
        flt.propagate(dth[k], dvl[k], dt)
        if (k + 1) % 20 == 0:
            i = k + 1
            llh = tr.llh[i].copy()
            flt.update(gnss_position(flt.state, llh, np.eye(3) * 0.05**2))
            flt.update(gnss_velocity(flt.state, tr.v_ned[i], np.eye(3) * 0.02**2, np.zeros(3)))
    sigma = math.sqrt(flt.P[20, 20])
    print(f"gyro-z scale estimate {flt.scale[5]:.4f} (truth 0.02, sigma {sigma:.4f})")
    assert abs(flt.scale[5] - 0.02) < max(3 * sigma, 1e-3)
    assert sigma < 0.005
