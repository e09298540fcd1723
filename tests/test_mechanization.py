"""Strapdown mechanisation with perfect increments stays on the truth (acceptance: 0.05 m over
10 minutes, stationary and turning), and splitting an IMU interval changes nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.agent.nav.mechanization import mechanize, split_increment
from slcp.agent.nav.rotation import euler_to_quat, quat_to_euler, wrap_angle
from slcp.agent.nav.state import NavState
from slcp.geo import earth
from slcp.hw_emulation.kinematics import SinusoidProfile, generate

from conftest import mechanization_drift


def test_stationary_ten_minutes() -> None:
    lat, h = math.radians(39.95), 50.0
    st = NavState(lat, math.radians(116.32), h, np.zeros(3), euler_to_quat(0.02, -0.01, 1.1))
    c = st.dcm
    dt = 0.01
    dth = c.T @ earth.earth_rate_ned(lat) * dt
    dv = c.T @ np.array([0.0, 0.0, -earth.gravity(lat, h)]) * dt
    s = st
    for _ in range(60000):
        s = mechanize(s, dth, dv, dt, dth, dv)
    assert np.linalg.norm(earth.ned_offset(s.lat, s.lon, s.h, st.lat, st.lon, st.h)) < 0.05
    assert np.linalg.norm(s.v) < 1e-3
    assert np.allclose(quat_to_euler(s.q), quat_to_euler(st.q), atol=1e-8)


@pytest.fixture(scope="module")
def turning_truth():
    prof = SinusoidProfile(
        speed0=10.0, speed_terms=((3.0, 0.05, 0.0),),
        roll_terms=((0.03, 0.2, 0.0),), pitch_terms=((0.02, 0.1, 0.5),),
        yaw_terms=((1.5, 0.04, 0.0), (0.2, 0.3, 0.0)),
    )
    return generate(prof, 600.0)


def test_turning_trajectory_ten_minutes(turning_truth) -> None:
    s, worst = mechanization_drift(turning_truth, every=1000)
    assert worst < 0.05, f"position drift {worst:.4f} m"
    assert np.linalg.norm(s.v - turning_truth.v_ned[-1]) < 1e-3
    att = quat_to_euler(s.q) - turning_truth.euler[-1]
    assert np.all(np.abs(wrap_angle(att)) < 1e-5)


def test_truth_generator_is_bit_identical() -> None:
    prof = SinusoidProfile(speed0=5.0, yaw_rate=0.1)
    a, b = generate(prof, 5.0), generate(prof, 5.0)
    assert np.array_equal(a.dtheta, b.dtheta) and np.array_equal(a.llh, b.llh)


def test_split_interval_matches_unsplit(turning_truth) -> None:
    """A GNSS epoch inside an IMU interval: propagating the two parts equals the whole."""
    tr = turning_truth
    s0 = NavState(*tr.llh[0], tr.v_ned[0].copy(), euler_to_quat(*tr.euler[0]))
    whole, parts = s0, s0
    for k in range(200):
        dt = tr.t[k + 1] - tr.t[k]
        whole = mechanize(whole, tr.dtheta[k], tr.dvel[k], dt)
        (a_th, a_dv, a_dt), (b_th, b_dv, b_dt) = split_increment(
            tr.dtheta[k], tr.dvel[k], tr.t[k], tr.t[k + 1], tr.t[k] + 0.37 * dt)
        parts = mechanize(parts, a_th, a_dv, a_dt)
        parts = mechanize(parts, b_th, b_dv, b_dt)
    e = earth.ned_offset(parts.lat, parts.lon, parts.h, whole.lat, whole.lon, whole.h)
    assert np.linalg.norm(e) < 1e-4
    assert np.linalg.norm(parts.v - whole.v) < 1e-5
    with pytest.raises(ValueError):
        split_increment(tr.dtheta[0], tr.dvel[0], 0.0, 0.01, 0.02)


def test_run_of_intervals_equals_one_by_one(turning_truth) -> None:
    """``mechanize_run`` over many intervals and ``InsFilter.propagate_run`` (with scale-factor
    states and covariance steps inside the run) give, bit for bit, what one call per interval
    gives: the same arithmetic in the same order (a run is an optimisation, not a model)."""
    from slcp.agent.nav.ins_filter import InsFilter
    from slcp.agent.nav.mechanization import mechanize_fast, mechanize_run

    from conftest import MEMS_NOISE

    tr = turning_truth
    n = 1000
    th, dv, dts = tr.dtheta[:n].tolist(), tr.dvel[:n].tolist(), np.diff(tr.t[: n + 1]).tolist()
    s0 = NavState(*tr.llh[0], tr.v_ned[0].copy(), euler_to_quat(*tr.euler[0]),
                  np.array([1e-4, -2e-4, 5e-5]), np.array([0.02, -0.01, 0.03]))
    one, pth, pdv = s0, None, None
    for k in range(n):
        one, pth, pdv = mechanize_fast(one, th[k], dv[k], dts[k], pth, pdv)
    vel: list = []
    run, rth, rdv, _, _ = mechanize_run(s0, th, dv, dts, None, None, velocities=vel)
    assert (run.lat, run.lon, run.h) == (one.lat, one.lon, one.h)
    assert run.v.tolist() == one.v.tolist() and run.q.tolist() == one.q.tolist()
    assert rth == pth and rdv == pdv
    assert len(vel) == n and vel[0] == tuple(s0.v) and vel[-1] != tuple(run.v)

    P0 = np.diag(np.r_[np.full(3, 1e-4), np.full(3, 0.01), np.full(3, 4.0), np.full(3, 1e-8), np.full(3, 1e-4)])

    def fresh() -> InsFilter:
        return InsFilter(s0.copy(), P0.copy(), MEMS_NOISE, t=float(tr.t[0]), cov_interval=0.1,
                         scale_factors=(1e-3, 1e-3, 100.0))

    a, b = fresh(), fresh()
    for k in range(n):
        a.propagate(th[k], dv[k], dts[k])
    for lo, hi in ((0, 7), (7, 333), (333, 334), (334, n)):  # runs across covariance steps
        b.propagate_run(th[lo:hi], dv[lo:hi], dts[lo:hi])
    assert b.t == a.t and b.stats.imu_samples == a.stats.imu_samples == n
    assert b.stats.cov_steps == a.stats.cov_steps
    assert np.array_equal(b.P, a.P) and np.array_equal(b.scale, a.scale)
    assert b.state.v.tolist() == a.state.v.tolist() and b.state.lat == a.state.lat
    with pytest.raises(ValueError):
        b.propagate_run([(0.0, 0.0, 0.0)], [(0.0, 0.0, 0.0)], [0.0])
