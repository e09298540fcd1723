"""The 15-state error model against numerical perturbation of the full nonlinear dynamics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.agent.nav.error_model import ImuNoise, discretize, noise_input_matrix, system_matrix
from slcp.agent.nav.mechanization import continuous_dynamics
from slcp.agent.nav.rotation import dcm_to_quat
from slcp.agent.nav.state import N_STATES, NavState, apply_error, state_error
from slcp.geo import earth

from conftest import EPS, MEMS_NOISE, moving_state, numerical_jacobian


class _Offset:
    """Nav state with latitude/longitude held as offsets from the start point, so that the
    finite differences below keep full precision (absolute latitude has a 0.6 nm ulp)."""

    def __init__(self, base: NavState, dlat: float, dlon: float, s: NavState) -> None:
        self.base, self.dlat, self.dlon, self.s = base, dlat, dlon, s

    def nav(self) -> NavState:
        out = self.s.copy()
        out.lat, out.lon = self.base.lat + self.dlat, self.base.lon + self.dlon
        return out


def _rk4(x: _Offset, w_ib: np.ndarray, f_b: np.ndarray, h: float, tau: float) -> _Offset:
    """RK4 step of the continuous navigation equations with constant body inputs; the biases
    are subtracted from the inputs and decay as Gauss-Markov processes."""

    def deriv(y: _Offset):
        s = y.nav()
        return continuous_dynamics(s, w_ib - s.bg, f_b - s.ba)

    def add(y: _Offset, k, a: float) -> _Offset:
        llh_d, v_d, c_d = k
        s = y.s
        u, _, vt = np.linalg.svd(s.dcm + a * c_d)
        new = NavState(s.lat, s.lon, s.h + a * llh_d[2], s.v + a * v_d, dcm_to_quat(u @ vt),
                       s.bg * (1 - a / tau), s.ba * (1 - a / tau))
        return _Offset(y.base, y.dlat + a * llh_d[0], y.dlon + a * llh_d[1], new)

    k1 = deriv(x)
    k2 = deriv(add(x, k1, h / 2))
    k3 = deriv(add(x, k2, h / 2))
    k4 = deriv(add(x, k3, h))
    k = tuple((a + 2 * b + 2 * c + d) / 6 for a, b, c, d in zip(k1, k2, k3, k4))
    return add(x, k, h)


def _error(est: _Offset, truth: _Offset) -> np.ndarray:
    dx = state_error(est.nav(), truth.nav())
    t = truth.nav()
    rm, rn = earth.radii(t.lat)
    dx[6] = (est.dlat - truth.dlat) * (rm + t.h)
    dx[7] = (est.dlon - truth.dlon) * (rn + t.h) * math.cos(t.lat)
    return dx


def _turning(yaw: float) -> tuple[NavState, _Offset, np.ndarray, np.ndarray]:
    """A moving state without biases, as truth, and constant body rate and specific force."""
    base = moving_state(yaw)
    base.bg = np.zeros(3)
    base.ba = np.zeros(3)
    return base, _Offset(base, 0.0, 0.0, base), np.array([0.01, -0.02, 0.15]), np.array([0.8, -1.5, -9.6])


@pytest.mark.parametrize("yaw, climb", [(0.0, 0.0), (0.6, 0.0), (-2.4, 0.0), (0.6, 4.0)])
def test_F_matches_numerical_error_dynamics(yaw: float, climb: float) -> None:
    """``climb`` [m/s] up: the terms in the vertical velocity (a few 1e-7 at 4 m/s) stand above
    the comparison's resolution."""
    base, truth, w_ib, f_b = _turning(yaw)
    base.v[2] -= climb
    tau = MEMS_NOISE.gyro_bias_tau
    noise = ImuNoise(MEMS_NOISE.arw, MEMS_NOISE.vrw, MEMS_NOISE.gyro_bias_sigma, tau,
                     MEMS_NOISE.accel_bias_sigma, tau)

    def central(est: _Offset, h: float) -> np.ndarray:
        ep = _error(_rk4(est, w_ib, f_b, h, tau), _rk4(truth, w_ib, f_b, h, tau))
        em = _error(_rk4(est, w_ib, f_b, -h, tau), _rk4(truth, w_ib, f_b, -h, tau))
        return (ep - em) / (2 * h)

    def error_rate(dx: np.ndarray) -> np.ndarray:
        # Richardson extrapolation of the central time difference removes the O(h²) term
        e = apply_error(base, dx)
        est = _Offset(base, e.lat - base.lat, e.lon - base.lon, e)
        h = 0.02
        return (4.0 * central(est, h / 2) - central(est, h)) / 3.0

    F_num = numerical_jacobian(error_rate, N_STATES, EPS * 10)
    f_n = base.dcm @ f_b
    F = system_matrix(base, f_n, noise)
    # every entry within 5e-8 absolute (the smallest F terms, ~1e-12, are below the
    # resolution of height in double precision)
    # or 1e-4 relative
    err = np.abs(F - F_num)
    tol = 5e-8 + 1e-4 * np.abs(F)
    bad = np.argwhere(err > tol)
    assert bad.size == 0, f"F mismatch at {bad.tolist()}: {F[tuple(bad.T)]} vs {F_num[tuple(bad.T)]}"


def test_series_and_van_loan_discretisations_agree() -> None:
    st = moving_state()
    F = system_matrix(st, st.dcm @ np.array([0.5, 0.2, -9.8]), MEMS_NOISE)
    G = noise_input_matrix(st)
    qc = MEMS_NOISE.psd()
    for dt in (0.01, 0.05, 0.1):
        phi_s, q_s = discretize(F, G, qc, dt, "series")
        phi_v, q_v = discretize(F, G, qc, dt, "van_loan")
        # third-order series: the first neglected term is (FΔt)^4/24
        assert np.abs(phi_s - phi_v).max() < 1e-3 * dt
        scale = np.sqrt(np.outer(np.diag(q_v), np.diag(q_v)))
        assert np.all(np.abs(q_s - q_v) <= 0.02 * scale + 1e-30)


def test_bad_discretisation_method_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="van_loan"):
        discretize(np.eye(2), np.eye(2), np.ones(2), 0.1, "euler")


def test_apply_and_remove_error_round_trip(rng: np.random.Generator) -> None:
    truth = moving_state()
    for _ in range(20):
        dx = rng.normal(size=N_STATES) * EPS * 100
        est = apply_error(truth, dx)
        assert np.allclose(state_error(est, truth), dx, rtol=1e-4, atol=1e-9)


def test_gravity_and_radii_closed_form() -> None:
    # Somigliana at the equator and the pole; radii at the equator
    assert math.isclose(earth.gravity(0.0, 0.0), earth.GAMMA_E, rel_tol=1e-12)
    assert math.isclose(earth.gravity(math.pi / 2, 0.0), earth.GAMMA_P, rel_tol=1e-9)
    rm, rn = earth.radii(0.0)
    assert math.isclose(rn, earth.A) and math.isclose(rm, earth.A * (1 - earth.E2))
    # free-air gradient ~ -3.086e-6 /s^2 and matches a finite difference
    g1, g2 = earth.gravity(0.7, 100.0), earth.gravity(0.7, 101.0)
    assert math.isclose(g2 - g1, earth.gravity_height_gradient(0.7, 100.5), rel_tol=1e-6)
    assert -3.1e-6 < earth.gravity_height_gradient(0.7, 0.0) < -3.07e-6


def test_constant_noise_density_equals_G_Qc_Gt() -> None:
    from slcp.agent.nav.error_model import process_noise_density

    for yaw in (0.0, 1.0, -2.0):
        st = moving_state(yaw)
        G = noise_input_matrix(st)
        assert np.allclose((G * MEMS_NOISE.psd()) @ G.T, np.diag(process_noise_density(MEMS_NOISE)), atol=1e-20)


@pytest.mark.parametrize("method", ["van_loan", "series"])
def test_a_gauss_markov_bias_keeps_its_steady_state_sigma(method: str) -> None:
    """First-order Gauss-Markov ``ḃ = -b/τ + w``: the drive's PSD 2σ²/τ is what keeps the
    variance at σ². Over dt the exact discrete variance is ``σ² (1 - e^(-2 dt/τ))`` and the
    transition ``e^(-dt/τ)`` (the series is third order in dt/τ); propagated long, a bias that
    starts known settles at σ², and one that starts at σ² stays there."""
    noise = ImuNoise(arw=1e-3, vrw=1e-2, gyro_bias_sigma=2e-4, gyro_bias_tau=20.0,
                     accel_bias_sigma=3e-3, accel_bias_tau=50.0)
    F = system_matrix(moving_state(), np.array([0.0, 0.0, -9.8]), noise)
    G = noise_input_matrix(moving_state())
    dt = 0.1
    phi, qd = discretize(F, G, noise.psd(), dt, method)
    tol = 1e-9 if method == "van_loan" else 1e-6
    for idx, sigma, tau in ((9, 2e-4, 20.0), (12, 3e-3, 50.0)):
        assert phi[idx, idx] == pytest.approx(math.exp(-dt / tau), rel=tol)
        assert qd[idx, idx] == pytest.approx(sigma**2 * (1 - math.exp(-2 * dt / tau)), rel=tol)
        p = 0.0
        for _ in range(3000):  # 300 s = 6-15 τ
            p = phi[idx, idx] ** 2 * p + qd[idx, idx]
        assert p == pytest.approx(sigma**2, rel=2e-3)
        assert phi[idx, idx] ** 2 * sigma**2 + qd[idx, idx] == pytest.approx(sigma**2, rel=1e-6)


def test_a_random_walk_bias_reads_sigma_as_its_density() -> None:
    """τ = ∞: no decay, and σ is the random walk's density, so the variance grows as σ² dt."""
    noise = ImuNoise(arw=1e-3, vrw=1e-2, gyro_bias_sigma=2e-5, gyro_bias_tau=math.inf,
                     accel_bias_sigma=3e-4, accel_bias_tau=math.inf)
    assert np.allclose(noise.psd()[6:], np.repeat([4e-10, 9e-8], 3), rtol=1e-12)
    F = system_matrix(moving_state(), np.array([0.0, 0.0, -9.8]), noise)
    phi, qd = discretize(F, noise_input_matrix(moving_state()), noise.psd(), 2.0, "van_loan")
    assert phi[9, 9] == 1.0 and phi[12, 12] == 1.0
    assert qd[9, 9] == pytest.approx(4e-10 * 2.0, rel=1e-9)
    assert qd[12, 12] == pytest.approx(9e-8 * 2.0, rel=1e-9)


@pytest.mark.parametrize("h0", [0.0, 3000.0, -400.0])
def test_ned_offset_uses_the_radii_at_the_reference_height(h0: float) -> None:
    """``ned_offset`` against pymap3d's exact conversion for offsets of ±20 m: the arcs are on
    radii R_M + h0 and (R_N + h0) cos L0 (at 3 km, leaving out h0 would be 9 mm in 20 m, where
    the first-order conversion is good to 0.1 mm); ``offset_llh`` is its inverse."""
    import pymap3d

    lat0, lon0 = math.radians(39.9), math.radians(116.3)
    for dn, de, dd in ((20.0, 0.0, 0.0), (0.0, 20.0, 0.0), (-15.0, 13.0, 1.5), (7.0, -20.0, -3.0)):
        lat, lon, h = pymap3d.ned2geodetic(dn, de, dd, lat0, lon0, h0, deg=False)
        got = earth.ned_offset(lat, lon, h, lat0, lon0, h0)
        assert np.allclose(got, [dn, de, dd], atol=1e-4), got - [dn, de, dd]
        back = earth.offset_llh(np.array([lat0, lon0, h0]), np.array([dn, de, dd]))
        assert np.allclose(earth.ned_offset(*back, lat0, lon0, h0), [dn, de, dd], atol=1e-9)


@pytest.mark.parametrize("yaw", [0.0, 0.6, -2.4])
def test_G_matches_numerical_error_dynamics_of_sensor_noise(yaw: float) -> None:
    """The noise input matrix against the navigation equations: the estimate integrates the
    measured rate and specific force (true + noise), the truth the true ones, and the error's
    rate per unit of noise is G's gyro and accelerometer columns (the sign included: a rate
    measured too large turns the estimate the other way from a bias estimated too large)."""
    base, truth, w_ib, f_b = _turning(yaw)
    tau = MEMS_NOISE.gyro_bias_tau

    def central(noise: np.ndarray, h: float) -> np.ndarray:
        w, f = w_ib + noise[:3], f_b + noise[3:]
        ep = _error(_rk4(truth, w, f, h, tau), _rk4(truth, w_ib, f_b, h, tau))
        em = _error(_rk4(truth, w, f, -h, tau), _rk4(truth, w_ib, f_b, -h, tau))
        return (ep - em) / (2 * h)

    def error_rate(noise: np.ndarray) -> np.ndarray:
        return (4.0 * central(noise, 0.01) - central(noise, 0.02)) / 3.0

    G_num = numerical_jacobian(error_rate, 6, 1e-4)
    G = noise_input_matrix(base)
    assert np.allclose(G[:, :6], G_num, atol=1e-6), np.abs(G[:, :6] - G_num).max()
    # the bias drives enter their own states only
    assert np.array_equal(G[9:, 6:], np.eye(6)) and not G[:9, 6:].any() and not G[9:, :6].any()


def test_transport_rate_and_geodetic_rates_at_altitude() -> None:
    """At 8 km (where R + h and R differ by 0.13 %): the geodetic rates against pymap3d moving a
    point along its NED velocity, and the transport rate ω_en = (λ̇ cos L, -L̇, -λ̇ sin L) built
    from them."""
    import pymap3d

    lat, lon, h = math.radians(52.0), math.radians(13.0), 8000.0
    v = np.array([40.0, -70.0, 3.0])
    dt = 1e-3
    lat2, lon2, h2 = pymap3d.ned2geodetic(*(v * dt), lat, lon, h, deg=False)
    lat1, lon1, h1 = pymap3d.ned2geodetic(*(-v * dt), lat, lon, h, deg=False)
    rates = np.array(earth.geodetic_rates(lat, h, v))
    assert np.allclose(rates, [(lat2 - lat1) / (2 * dt), (lon2 - lon1) / (2 * dt), (h2 - h1) / (2 * dt)], rtol=1e-6)
    ldot, odot = rates[0], rates[1]
    w_en = earth.transport_rate_ned(lat, h, v)
    assert np.allclose(w_en, [odot * math.cos(lat), -ldot, -odot * math.sin(lat)], rtol=1e-12)


def test_a_gap_without_imu_data_in_closed_form() -> None:
    """Φ and Q_d over a gap: an unknown constant acceleration a ~ N(0, σ²) per axis moves the
    velocity error by a·G and the position error by a·G²/2 (so their covariance is
    σ² [G, G²/2]ᵀ[G, G²/2]); a constant turn rate the attitude by ω·G; the biases walk with their
    density; the augmented Gauss-Markov states decay exactly, their added variance the integral
    ∫₀ᴳ q e^(−2s/τ) ds computed here by quadrature, and a random walk (τ = ∞) gains q·G."""
    from scipy.integrate import quad

    from slcp.agent.nav.error_model import gap_transition

    gap, sa, sr = 1.7, (0.8, 0.3), (0.02, 0.05)
    gqg = np.arange(1.0, 16.0) * 1e-6
    tau, psd = np.array([30.0, np.inf, 4.0]), np.array([0.5, 0.01, 2.0])
    phi, qd = gap_transition(18, gap, sa, sr, gqg, tau, psd)
    want_phi = np.eye(18)
    want_phi[6:9, 3:6] = gap * np.eye(3)
    want_phi[15, 15], want_phi[17, 17] = math.exp(-gap / 30.0), math.exp(-gap / 4.0)
    np.testing.assert_allclose(phi, want_phi, rtol=1e-14, atol=0)
    want = np.zeros((18, 18))
    for k, s in enumerate((sa[0], sa[0], sa[1])):
        j = np.zeros(18)
        j[3 + k], j[6 + k] = gap, gap**2 / 2.0
        want += s**2 * np.outer(j, j)
    for k, s in enumerate((sr[0], sr[0], sr[1])):
        want[k, k] = (s * gap) ** 2
    want[range(9, 15), range(9, 15)] = gqg[9:15] * gap
    for i, (t_, q) in enumerate(zip(tau, psd)):
        want[15 + i, 15 + i] = quad(lambda s, t_=t_, q=q: q * math.exp(-2.0 * s / t_), 0.0, gap)[0]
    np.testing.assert_allclose(qd, want, rtol=1e-12, atol=1e-18)
    phi15, qd15 = gap_transition(15, gap, sa, sr, gqg, np.array([]), np.array([]))
    np.testing.assert_array_equal(phi15, want_phi[:15, :15])
    np.testing.assert_allclose(qd15, want[:15, :15], rtol=1e-12, atol=1e-18)


def test_F_position_columns_are_the_velocity_equations_derivative() -> None:
    """The velocity rows' position columns (Coriolis and transport rate: 1e-12 to 1e-9 /s², under
    the resolution of the whole-state test above) against central differences of the velocity
    equation itself over ±10 m of north, east and down, at 20 m/s with a climb. F leaves out the
    change of gravity with latitude (about 8e-9 /s² per metre north, a modelling choice of the
    error model), so it is added back to that one entry before the comparison."""
    st = moving_state(0.6)
    st.v = np.array([20.0, -15.0, 3.0])
    w_ib, f_b = np.array([0.01, -0.02, 0.15]), np.array([0.8, -1.5, -9.6])
    F = system_matrix(st, st.dcm @ f_b, MEMS_NOISE)
    rm, rn = earth.radii(st.lat)

    def v_dot(ned: np.ndarray) -> np.ndarray:
        s = st.copy()
        s.lat = st.lat + ned[0] / (rm + st.h)
        s.lon = st.lon + ned[1] / ((rn + st.h) * math.cos(st.lat))
        s.h = st.h - ned[2]
        return continuous_dynamics(s, w_ib, f_b)[1]

    J = numerical_jacobian(v_dot, 3, 10.0)
    dg_north = (earth.gravity(st.lat + 1e-6, st.h) - earth.gravity(st.lat - 1e-6, st.h)) / (2e-6 * (rm + st.h))
    want = J.copy()
    want[2, 0] -= dg_north
    np.testing.assert_allclose(F[3:6, 6:9], want, rtol=1e-3, atol=1e-17)
    assert np.abs(F[3:6, 6:9]).max() < 1e-5 and np.count_nonzero(F[3:6, 6:9]) == 6  # east: no effect
