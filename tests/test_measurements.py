"""Every measurement Jacobian against numerical perturbation; stop-line geometry; range model;
stacked vs sequential updates."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import block_diag

from slcp.agent.nav.kalman import Measurement, kalman_update, stack
from slcp.agent.nav.measurements.common import point_llh, point_position_jacobian
from slcp.agent.nav.measurements.gnss import gnss_position, gnss_velocity
from slcp.agent.nav.measurements.lane_line import lane_line_measurement
from slcp.agent.nav.measurements.stop_line import (
    Line2D,
    StopGapModel,
    StopLineApproach,
    stop_line_fix,
    stop_line_measurement,
    stop_line_position,
)
from slcp.agent.nav.measurements.v2v_range import range_measurement, relative_position
from slcp.agent.nav.measurements.vehicle import non_holonomic, zero_angular_rate, zero_velocity
from slcp.agent.nav.state import N_STATES, apply_error
from slcp.geo import earth

from conftest import EPS, moving_state, numerical_jacobian

LEVER = np.array([0.4, -0.3, -1.2])


def _check_jacobian(model, truth=None, tol=1e-6) -> None:
    truth = truth or moving_state()
    H = model(truth).H
    H_num = numerical_jacobian(lambda dx: model(apply_error(truth, dx)).z, N_STATES, EPS)
    scale = np.maximum(1.0, np.abs(H))
    assert np.all(np.abs(H - H_num) <= tol * scale), np.abs(H - H_num).max()


def test_gnss_position_jacobian() -> None:
    meas = np.array([math.radians(39.95001), math.radians(116.32002), 57.0])
    # first-order geodetic-to-NED conversion: ~1e-6 relative model error
    _check_jacobian(lambda s: gnss_position(s, meas, np.eye(3), LEVER), tol=2e-5)


def test_gnss_velocity_jacobian() -> None:
    _check_jacobian(lambda s: gnss_velocity(s, np.array([8.1, -5.2, 0.2]), np.eye(3),
                                            np.array([0.05, -0.1, 0.4]), LEVER))


def test_each_update_is_counted_under_its_measurements_name() -> None:
    """The filters' counters (diagnostics) key each update by its model's name: one accepted
    GNSS velocity counts 1 under ``gnss_vel``, a rejected one 1 under the rejections."""
    from slcp.agent.nav.kalman import FilterStats, UpdateResult

    m = gnss_velocity(moving_state(), np.array([8.1, -5.2, 0.2]), np.eye(3), np.zeros(3), LEVER)
    assert m.name == "gnss_vel"
    stats = FilterStats()
    stats.count(UpdateResult(np.zeros(15), 1.0, 3, True, m.name))
    assert stats.updates == {"gnss_vel": 1} and stats.rejected == {}
    stats.count(UpdateResult(np.zeros(15), 99.0, 3, False, m.name))
    stats.count(UpdateResult(np.zeros(15), 1.0, 3, True, m.name))
    assert stats.updates == {"gnss_vel": 2} and stats.rejected == {"gnss_vel": 1}


def test_vehicle_constraint_jacobians() -> None:
    _check_jacobian(lambda s: zero_velocity(s, 0.01))
    _check_jacobian(lambda s: non_holonomic(s, 0.1, 0.1))
    # ZARU neglects the ~7e-5 attitude dependence of the earth-rate term
    _check_jacobian(lambda s: zero_angular_rate(s, np.array([1e-3, 2e-3, -1e-3]), 1e-3), tol=1e-4)


def test_range_jacobian_first_and_second_order() -> None:
    nb = np.array(point_llh(moving_state(), np.zeros(3))) + np.array([3e-5, -2e-5, 0.5])
    P = np.diag([0.5, 0.8, 1.0])
    _check_jacobian(lambda s: range_measurement(s, 4.0, 0.1, nb, P, LEVER, P, False), tol=3e-5)
    # the second-order bias term tr(MP)/2 varies with the geometry (~tr(P)/rho^2 = 1e-4 here);
    # H deliberately keeps the first-order direction
    _check_jacobian(lambda s: range_measurement(s, 4.0, 0.1, nb, P, LEVER, P, True), tol=1e-4)


@pytest.mark.parametrize("heading_deg", [0.0, 90.0, 37.0, 180.0, -123.0])
def test_stop_line_jacobian_for_every_heading(heading_deg: float) -> None:
    approach, origin = _approach(math.radians(heading_deg))
    gap = StopGapModel(2.0, 0.3, 1.75, 0.2, 3.5)
    _check_jacobian(lambda s: stop_line_measurement(s, approach, gap, origin, LEVER), tol=1e-4)


def _approach(heading: float, lane_width: float = 3.5):
    """Approach heading ``heading``: stop line through (40, 10), left lane line through the
    stop-line point shifted half a lane to the left."""
    u = np.array([math.cos(heading), math.sin(heading)])
    right = np.array([-u[1], u[0]])
    stop_pt = np.array([40.0, 10.0])
    left_pt = stop_pt - right * lane_width / 2
    approach = StopLineApproach(Line2D(tuple(stop_pt), tuple(right)), Line2D(tuple(left_pt), tuple(u)))
    origin = (math.radians(39.95), math.radians(116.32), 50.0)
    return approach, origin


@pytest.mark.parametrize("heading_deg", [0.0, 90.0, 37.0])
def test_stop_line_fix_is_behind_the_line_and_inside_the_lane(heading_deg: float) -> None:
    heading = math.radians(heading_deg)
    approach, _ = _approach(heading)
    u = np.array([math.cos(heading), math.sin(heading)])
    p, J = stop_line_fix(approach, d_e=5.0, d_l=1.2)
    # closed form: from the stop-line point go 5 m back and 1.75 - 1.2 = 0.55 m left
    right = np.array([-u[1], u[0]])
    expected = np.array([40.0, 10.0]) - 5.0 * u - 0.55 * right
    assert np.allclose(p, expected, atol=1e-9)
    # the same point satisfies the paper's distance equations with signs
    assert approach.left_lane_line.signed_distance(p) == pytest.approx(1.2)
    assert float(approach.stop_line_normal() @ (p - np.array([40.0, 10.0]))) == pytest.approx(-5.0)
    # covariance equals the paper's T Σ Tᵀ for a perpendicular stop line
    gap = StopGapModel(2.0, 0.3, 1.2, 0.2, 3.0)
    _, cov = stop_line_position(approach, gap)
    T = np.array([[math.cos(heading), -math.sin(heading)], [math.sin(heading), math.cos(heading)]])
    assert np.allclose(cov, T @ np.diag([0.3**2, 0.2**2]) @ T.T, atol=1e-12)


def test_due_north_stop_line_cannot_be_written_as_slope_intercept() -> None:
    # a stop line across a north-south road is x = const: y = kx + b has no such line,
    # but point + direction does and gives a regular fix
    approach, _ = _approach(0.0)
    assert abs(approach.stop_line.direction[0]) < 1e-12  # runs due east: x = 40 constant
    p, _ = stop_line_fix(approach, 4.0, 1.0)
    assert p[0] == pytest.approx(36.0)
    paper = Line2D.from_slope_intercept(0.5, 2.0)
    assert paper.signed_distance(np.array([0.0, 2.0])) == pytest.approx(0.0)


def test_oblique_stop_line_and_parallel_lines() -> None:
    u = (1.0, 0.0)
    oblique = StopLineApproach(Line2D((0.0, 0.0), (math.sin(0.3), math.cos(0.3))), Line2D((0.0, -2.0), u))
    p, _ = stop_line_fix(oblique, 3.0, 1.0)
    same = StopLineApproach(Line2D.from_points((0.0, 0.0), (math.sin(0.3), math.cos(0.3))),
                            Line2D.from_heading((0.0, -2.0), 0.0))
    assert np.allclose(stop_line_fix(same, 3.0, 1.0)[0], p)
    assert oblique.left_lane_line.signed_distance(p) == pytest.approx(1.0)
    assert float(oblique.stop_line_normal() @ p) == pytest.approx(-3.0)
    with pytest.raises(ValueError, match="parallel"):
        StopLineApproach(Line2D((0, 0), (1, 0.01)), Line2D((0, -2), u))
    with pytest.raises(ValueError, match="non-zero"):
        Line2D((0, 0), (0, 0))


@pytest.mark.parametrize("heading_deg", [0.0, 90.0, 37.0, 180.0, -123.0])
def test_lane_line_jacobian_for_every_heading(heading_deg: float) -> None:
    approach, origin = _approach(math.radians(heading_deg))
    _check_jacobian(lambda s: lane_line_measurement(s, approach.left_lane_line, 1.75, 0.03, origin, LEVER),
                    tol=1e-4)


@pytest.mark.parametrize("heading_deg", [0.0, 90.0, 37.0])
def test_lane_line_row_is_the_stop_line_fix_lateral_row(heading_deg: float) -> None:
    """The lane-keeping row is the stop-line fix's row across the lane: same innovation and
    Jacobian (projected on the lane's right normal), for a vehicle anywhere near the lane."""
    heading = math.radians(heading_deg)
    approach, origin = _approach(heading)
    gap = StopGapModel(2.0, 0.3, 1.2, 0.2, 3.0)
    s = moving_state(yaw=heading)
    import pymap3d
    s.lat, s.lon, s.h = pymap3d.ned2geodetic(31.0, 4.0, 0.0, *origin, deg=False)
    n_r = approach.left_lane_line.right_normal
    sl = stop_line_measurement(s, approach, gap, origin, LEVER)
    ll = lane_line_measurement(s, approach.left_lane_line, gap.m_yb, 0.03, origin, LEVER)
    assert ll.dim == 1 and ll.R[0, 0] == pytest.approx(0.03**2)
    assert ll.z[0] == pytest.approx(float(n_r @ sl.z), abs=1e-9)
    assert np.allclose(ll.H[0], n_r @ sl.H, atol=1e-12)


def test_stop_line_measurement_matches_truth_geometry() -> None:
    """A vehicle placed exactly at the fix gets a zero innovation (east scaling included)."""
    heading = math.radians(37.0)
    approach, origin = _approach(heading)
    gap = StopGapModel(2.0, 0.3, 1.2, 0.2, 3.0)
    p, _ = stop_line_position(approach, gap)
    import pymap3d
    lat, lon, h = pymap3d.ned2geodetic(p[0], p[1], 0.0, *origin, deg=False)
    s = moving_state(yaw=heading)
    s.lat, s.lon, s.h = lat, lon, h
    m = stop_line_measurement(s, approach, gap, origin)
    assert np.allclose(m.z, 0.0, atol=1e-6)


def test_range_with_road_height_offset_ignores_the_estimated_heights() -> None:
    """With the antennas' height difference from the road, the estimated heights (however
    wrong, however uncertain) change neither the prediction nor R; H has no vertical column and
    still matches numerical perturbation."""
    s = moving_state()
    nb = np.array(point_llh(s, np.zeros(3)))
    rm, rn = earth.radii(nb[0])
    nb[0] += 30.0 / (rm + nb[2])
    nb[1] += 40.0 / ((rn + nb[2]) * np.cos(nb[0]))
    nb[2] += 9.0  # the neighbour's estimated height is 9 m above ours
    Pj = np.array([[0.5, 0.1, 0.3], [0.1, 0.8, -0.2], [0.3, -0.2, 100.0]])
    Pi = np.diag([1.0, 2.0, 150.0])
    m3d = range_measurement(s, 50.0, 0.1, nb, Pj)
    m = range_measurement(s, 50.0, 0.1, nb, Pj, height_offset=(0.0, 0.3))
    assert m3d.z[0] == pytest.approx(math.sqrt(50.0**2 + 81.0) - 50.0, rel=1e-3)  # 0.80 m
    assert m.z[0] == pytest.approx(0.0, abs=2e-3)
    u = np.array([-0.6, -0.8, 0.0])  # from the neighbour to us, horizontal
    assert m.R[0, 0] == pytest.approx(0.01 + u @ Pj @ u, rel=1e-3)
    assert m.H[0, 8] == 0.0
    m2 = range_measurement(s, 50.0, 0.1, nb, Pj, own_cov_ned=Pi, second_order=True, height_offset=(0.0, 0.3))
    # only the horizontal cross-range variance (and the offset's) curves the range:
    # (0.5 + 1.0)·0.64 + (0.8 + 2.0)·0.36 − 2·0.1·0.48 = 1.872 m² across, 0.09 m² vertical
    assert m2.z[0] == pytest.approx((1.872 + 0.09) / (2 * 50.0), rel=2e-2)
    # a known offset of the antennas (this one 0.8 m higher) enters as the vertical leg
    m4 = range_measurement(s, 50.0, 0.1, nb, Pj, height_offset=(0.8, 0.3))
    assert m4.z[0] == pytest.approx(math.hypot(50.0, 0.8) - 50.0, abs=2e-3)
    assert m4.R[0, 0] == pytest.approx(m.R[0, 0] + (0.8 / 50.0 * 0.3) ** 2, rel=1e-3)
    for offset in ((0.0, 0.3), (0.8, 0.3)):
        _check_jacobian(lambda st, o=offset: range_measurement(st, 50.0, 0.1, nb, Pj, LEVER, height_offset=o), tol=3e-5)
    # a large, uncertain offset: R = σ² + (u_v σ_dh)² + u_hᵀ P_h u_h along the slanted line
    m8 = range_measurement(s, 50.0, 0.1, nb, Pj, height_offset=(8.0, 2.0))
    rho = math.hypot(50.0, 8.0)
    u_h = np.array([-0.6, -0.8]) * 50.0 / rho
    assert m8.R[0, 0] == pytest.approx(0.01 + (8.0 / rho * 2.0) ** 2 + u_h @ Pj[:2, :2] @ u_h, rel=2e-3)


def test_range_r_includes_neighbour_covariance_and_second_order_terms() -> None:
    s = moving_state()
    nb = np.array(point_llh(s, np.zeros(3)))
    nb[0] += 7.0 / (earth.radii(nb[0])[0] + nb[2])  # neighbour 7 m north
    P = np.diag([4.0, 9.0, 1.0])
    m1 = range_measurement(s, 7.0, 0.1, nb, P)
    # u points from j to i: south; u^T P u = P_NN
    assert m1.R[0, 0] == pytest.approx(0.01 + 4.0, rel=1e-6)
    assert m1.z[0] == pytest.approx(0.0, abs=1e-6)
    m2 = range_measurement(s, 7.0, 0.1, nb, P, own_cov_ned=P, second_order=True)
    # cross-range variance 2*(9+9)=18 and 2*(1+1)=2 m² curve the range: bias (18+2)/(2*7)
    assert m2.z[0] == pytest.approx((18.0 + 2.0) / 14.0, rel=1e-4)
    assert m2.R[0, 0] == pytest.approx(m1.R[0, 0] + 0.5 * (18.0**2 + 2.0**2) / 49.0, rel=1e-4)


def test_stacked_and_sequential_updates_agree(rng: np.random.Generator) -> None:
    """Paper's cases 1-3: stacking independent rows equals applying them one after another."""
    A = rng.normal(size=(N_STATES, N_STATES))
    P0 = A @ A.T / N_STATES + np.eye(N_STATES) * 0.1
    gnss = Measurement(rng.normal(size=3), rng.normal(size=(3, N_STATES)), np.diag([1.0, 2.0, 3.0]), "gnss")
    rng_rows = [Measurement(rng.normal(size=1), rng.normal(size=(1, N_STATES)), np.array([[0.3]]), "r")
                for _ in range(3)]
    beacons = stack(rng_rows, "ranges")
    for case in ([gnss], rng_rows, [gnss] + rng_rows):
        dx_s, P_s, _ = kalman_update(P0, stack(case))
        P, dx = P0.copy(), np.zeros(N_STATES)
        for m in case:
            # sequential: later rows see the earlier correction in their innovation
            shifted = Measurement(m.z - m.H @ dx, m.H, m.R, m.name)
            d, P, _ = kalman_update(P, shifted)
            dx = dx + d
        assert np.allclose(P, P_s, atol=1e-10)
        assert np.allclose(dx, dx_s, atol=1e-10)
    assert beacons.R.shape == (3, 3) and np.allclose(beacons.R, block_diag(*[r.R for r in rng_rows]))


def test_nis_and_gating(rng: np.random.Generator) -> None:
    P = np.eye(N_STATES)
    H = np.zeros((2, N_STATES))
    H[0, 6] = H[1, 7] = 1.0
    m = Measurement(np.array([3.0, 4.0]), H, np.eye(2), "x")
    _, _, res = kalman_update(P, m)
    assert res.nis == pytest.approx(25.0 / 2.0)
    dx, P2, res = kalman_update(P, m, gate_probability=0.99)
    assert not res.accepted and np.all(dx == 0) and P2 is P
    bad = Measurement(np.array([1.0, 1.0]), H, np.full((2, 2), np.nan), "nan")
    _, _, res = kalman_update(P, bad)
    assert not res.accepted


def test_range_closed_forms_equal_the_matrix_forms(rng: np.random.Generator) -> None:
    """The second-order terms in closed form equal ½tr(MQ) and ½tr((MQ)²) with the Hessian
    M = (I - uuᵀ)/ρ, for a full covariance; the zero-lever Jacobian equals uᵀ∂p/∂x."""
    s = moving_state()
    nb = np.array(point_llh(s, np.zeros(3)))
    nb[0] += 5.0 / (earth.radii(nb[0])[0] + nb[2])
    nb[1] -= 3.0 / (earth.radii(nb[0])[1] * np.cos(nb[0]))
    A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
    Pj, Pi = A @ A.T + np.eye(3), B @ B.T + 0.5 * np.eye(3)
    m1 = range_measurement(s, 6.0, 0.1, nb, Pj)
    m2 = range_measurement(s, 6.0, 0.1, nb, Pj, own_cov_ned=Pi, second_order=True)
    d = relative_position(s, np.zeros(3), nb)
    rho = np.linalg.norm(d)
    u = d / rho
    MQ = (np.eye(3) - np.outer(u, u)) / rho @ (Pi + Pj)
    assert m2.z[0] - m1.z[0] == pytest.approx(0.5 * np.trace(MQ), rel=1e-12)
    assert m2.R[0, 0] - m1.R[0, 0] == pytest.approx(0.5 * np.trace(MQ @ MQ), rel=1e-12)
    assert np.allclose(m1.H[0], u @ point_position_jacobian(s, np.zeros(3)), atol=0)
    m3 = range_measurement(s, 6.0, 0.1, nb, Pj, relative=d)
    assert np.array_equal(m3.z, m1.z) and np.array_equal(m3.R, m1.R)


@pytest.mark.parametrize("heading_deg", [0.0, 90.0, 37.0, -128.0])
def test_the_along_only_stop_line_row_is_the_full_fix_along_the_normal(heading_deg: float) -> None:
    """A first stopped vehicle whose lane is ambiguous among lanes sharing the stop line uses
    only the distance behind the line: the full fix's innovation and Jacobian projected on the
    stop line's normal, with the variance of d_s alone (``nᵀ J Σ Jᵀ n = σ_xb²``, since the
    normal component of the fix does not depend on d_l), computed both ways."""
    heading = math.radians(heading_deg)
    approach, origin = _approach(heading)
    gap = StopGapModel(m_xb=2.0, sigma_xb=0.3, m_yb=1.2, sigma_yb=0.7, l0=3.0)
    s = moving_state(yaw=heading)
    full = stop_line_measurement(s, approach, gap, origin, LEVER)
    along = stop_line_measurement(s, approach, gap, origin, LEVER, along_only=True)
    n = approach.stop_line_normal()
    assert along.dim == 1 and along.name == "stop_line_along"
    assert along.z[0] == pytest.approx(float(n @ full.z), abs=1e-9)
    assert np.allclose(along.H[0], n @ full.H, atol=1e-12)
    assert along.R[0, 0] == pytest.approx(float(n @ full.R @ n), rel=1e-9)
    assert along.R[0, 0] == pytest.approx(gap.sigma_xb**2, rel=1e-12)
    _check_jacobian(lambda st: stop_line_measurement(st, approach, gap, origin, LEVER, along_only=True), s, tol=2e-5)


def test_the_joseph_form_holds_for_any_gain(rng: np.random.Generator) -> None:
    """``joseph`` is ``(I - K H) P (I - K H)ᵀ + K R Kᵀ`` for any gain, computed both ways: the
    explicit product, and the covariance of ``(I - KH) e - K v`` over samples; with the optimal
    gain it equals ``P - K S Kᵀ``; with consider states (rows of K zeroed) their block is kept."""
    from slcp.agent.nav.kalman import joseph

    n, m = 6, 2
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    H = rng.normal(size=(m, n))
    R = np.diag([0.3, 0.7])
    K = rng.normal(size=(n, m))  # not the optimal gain
    I_KH = np.eye(n) - K @ H
    want = I_KH @ P @ I_KH.T + K @ R @ K.T
    assert np.allclose(joseph(P, K, H, R), want, rtol=1e-12, atol=1e-12)
    e = rng.multivariate_normal(np.zeros(n), P, 200_000)
    v = rng.multivariate_normal(np.zeros(m), R, 200_000)
    post = e @ I_KH.T - v @ K.T
    assert np.allclose(np.cov(post.T), want, rtol=0.03, atol=0.03 * np.abs(want).max())
    meas = Measurement(rng.normal(size=m), H, R, "x")
    S = H @ P @ H.T + R
    Kopt = P @ H.T @ np.linalg.inv(S)
    dx, Ppost, res = kalman_update(P, meas)
    assert np.allclose(Ppost, P - Kopt @ S @ Kopt.T, rtol=1e-10, atol=1e-10)
    assert np.allclose(dx, Kopt @ meas.z) and np.array_equal(res.dx, dx) and res.accepted and res.dof == m
    assert np.allclose(res.gain, Kopt, rtol=1e-10, atol=1e-12)
    consider = np.array([4, 5])
    dx, Pc, res = kalman_update(P, meas, consider=consider)
    Kc = Kopt.copy()
    Kc[consider] = 0.0
    assert np.allclose(dx[consider], 0.0) and np.allclose(Pc[4:, 4:], P[4:, 4:], rtol=1e-12)
    assert np.allclose(Pc, (np.eye(n) - Kc @ H) @ P @ (np.eye(n) - Kc @ H).T + Kc @ R @ Kc.T, rtol=1e-10)


def test_vehicle_pseudo_measurements_in_closed_form() -> None:
    """ZUPT, ZARU and NHC: their innovations where the constraint holds exactly (zero), their
    noise matrices, dimensions and names. A body at rest reads the earth's rotation in its
    gyros: ZARU removes it (and the estimated bias) from the mean rate."""
    s = moving_state(yaw=0.7)
    z = zero_velocity(s, 0.02)
    assert z.name == "zupt" and np.array_equal(z.z, s.v) and np.allclose(z.R, np.eye(3) * 4e-4)
    s.bg = np.array([1e-4, -2e-4, 3e-4])
    w_ie_b = s.dcm.T @ earth.earth_rate_ned(s.lat)
    zr = zero_angular_rate(s, w_ie_b + s.bg, 1e-3)
    assert zr.name == "zaru" and np.allclose(zr.z, 0.0, atol=1e-15) and np.allclose(zr.R, np.eye(3) * 1e-6)
    assert np.allclose(zero_angular_rate(s, w_ie_b + s.bg + [1e-5, 0, 0], 1e-3).z, [1e-5, 0, 0], atol=1e-15)
    # NHC: a velocity along the body's forward axis has no lateral or vertical component
    s.v = s.dcm @ np.array([12.0, 0.0, 0.0])
    nh = non_holonomic(s, 0.1, 0.3)
    assert nh.name == "nhc" and nh.dim == 2 and np.allclose(nh.z, 0.0, atol=1e-12)
    assert np.allclose(nh.R, np.diag([0.01, 0.09]))
    assert np.allclose(non_holonomic(s, 0.1).R, np.diag([0.01, 0.01]))
    s.v = s.dcm @ np.array([12.0, 0.5, -0.2])
    assert np.allclose(non_holonomic(s, 0.1).z, [0.5, -0.2])


def test_the_nhc_widens_its_rows_by_the_rotation_at_the_unknown_lever() -> None:
    """The IMU sits an unknown distance l from the rear axle, whose velocity the constraint
    knows: the body's rotation adds ω × (l, 0, 0) = (0, ω_z l, −ω_y l), so the lateral σ grows
    with the yaw rate and the vertical σ with the pitch rate (the roll rate adds nothing)."""
    from slcp.agent.nav.ins_filter import InsFilter
    from slcp.agent.own_sensors import OwnSensors
    from slcp.agent.settings import FilterSettings

    from conftest import MEMS_NOISE

    lever, w = 2.0, np.array([0.3, 0.04, -0.03])  # [m], roll, pitch, yaw rates [rad/s]
    s = moving_state()
    s.v = s.dcm @ np.array([10.0, 0.0, 0.0])  # the rear axle's velocity, forward only
    settings = FilterSettings(MEMS_NOISE, nhc_sigma=0.1, nhc_vertical_sigma=0.05, nhc_lever_uncertainty=lever)
    own = OwnSensors(InsFilter(s, np.eye(N_STATES), MEMS_NOISE), settings, slice(0, 0), None, {})
    dt = 0.01
    own.imu(w * dt, np.zeros(3), dt)
    m = own.nhc()
    added = np.cross(w, [lever, 0.0, 0.0])  # what the rotation adds at the IMU
    assert np.allclose(added, [0.0, w[2] * lever, -w[1] * lever])
    assert np.allclose(m.R, np.diag([0.1**2 + added[1] ** 2, 0.05**2 + added[2] ** 2]), rtol=1e-12)
    # without rotation, the plain σ
    own.imu(np.zeros(3), np.zeros(3), dt)
    assert np.allclose(own.nhc().R, np.diag([0.1**2, 0.05**2]), rtol=1e-12)


def test_stacking_keeps_each_block_and_the_name() -> None:
    a = Measurement(np.array([1.0]), np.ones((1, 4)), np.array([[2.0]]), "a")
    b = Measurement(np.array([3.0, 4.0]), np.arange(8.0).reshape(2, 4), np.array([[5.0, 0.5], [0.5, 6.0]]), "b")
    s = stack([a, b])
    assert s.name == "stacked" and stack([a, b], "gnss").name == "gnss"
    assert np.array_equal(s.z, [1.0, 3.0, 4.0]) and np.array_equal(s.H, np.vstack([a.H, b.H]))
    assert np.array_equal(s.R, block_diag(a.R, b.R))


def test_chi2_survival_at_and_below_zero_is_one() -> None:
    from slcp.agent.nav.kalman import chi2_survival

    for dof in (1, 2, 3, 4):
        assert chi2_survival(0.0, dof) == 1.0 and chi2_survival(-1.0, dof) == 1.0
    assert chi2_survival(2.0, 2) == pytest.approx(math.exp(-1.0), rel=1e-14)


def test_lines_from_points_and_slope_intercept() -> None:
    """Both constructors give a unit direction and a point on the line, away from the origin."""
    ln = Line2D.from_points((3.0, -2.0), (7.0, 1.0))
    assert np.allclose(ln.direction, [0.8, 0.6]) and ln.point == (3.0, -2.0)
    assert ln.signed_distance(np.array([7.0, 1.0])) == pytest.approx(0.0, abs=1e-12)
    sl = Line2D.from_slope_intercept(2.0, 5.0)
    assert np.allclose(sl.direction, np.array([1.0, 2.0]) / math.sqrt(5.0)) and sl.point == (0.0, 5.0)
    assert sl.signed_distance(np.array([1.0, 7.0])) == pytest.approx(0.0, abs=1e-12)  # y = 2x + 5 at x = 1
