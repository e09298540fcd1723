"""Sensor and link models: emitted statistics against the configured parameters (stated
tolerances), bit-identical seeded output, and clear parameter errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.geo.lane_markings import BOUNDARY, DIVIDER, UNSEEN
from slcp.hw_emulation.sensors.camera import LaneCameraModel, simulate_markings
from slcp.hw_emulation.sensors.gnss import GnssModel, common_mode_error, simulate_gnss
from slcp.hw_emulation.sensors.imu import ImuModel, corrupt_increments
from slcp.hw_emulation.sensors.processes import ar1_filter, gauss_markov, gauss_markov_varying, two_state_markov
from slcp.hw_emulation.sensors.radio import RadioModel, simulate_link
from slcp.hw_emulation.sensors.uwb import UwbModel, simulate_pair


def _tau_from_lag1(x: np.ndarray, dt: float) -> float:
    r = np.corrcoef(x[:-1], x[1:])[0, 1]
    return -dt / math.log(r)


def test_gauss_markov_sigma_and_correlation_time(rng) -> None:
    x = gauss_markov(200_000, 0.1, 2.0, 5.0, rng)[:, 0]
    assert x.std() == pytest.approx(2.0, rel=0.05)          # ±5 %
    assert _tau_from_lag1(x, 0.1) == pytest.approx(5.0, rel=0.10)  # ±10 %
    y = gauss_markov_varying(np.full(200_000, 0.1), 1.5, np.full(200_000, 5.0), rng)[:, 0]
    assert y.std() == pytest.approx(1.5, rel=0.05)
    assert _tau_from_lag1(y, 0.1) == pytest.approx(5.0, rel=0.10)



def test_a_varying_gauss_markov_process_starts_and_stays_stationary(rng) -> None:
    """Many short runs: the first sample is already the stationary N(0, σ²) (no warm-up), and
    so is every later one whatever τ does between them."""
    dt = np.full(6, 0.5)
    tau = np.array([1.0, 1.0, 100.0, 0.2, 5.0, 1.0])
    x = np.stack([gauss_markov_varying(dt, 2.0, tau, rng)[:, 0] for _ in range(20_000)])
    assert np.allclose(x.mean(0), 0.0, atol=0.06) and np.allclose(x.std(0), 2.0, rtol=0.03)
    lag = np.mean(x[:, 1] * x[:, 0]) / 4.0
    assert lag == pytest.approx(math.exp(-0.5 / 1.0), abs=0.03)


def test_each_uwb_nlos_episode_draws_its_own_bias(rng) -> None:
    model = UwbModel(nlos_enter=0.5, nlos_exit=0.5, outlier_prob=0.0, sigma_los=1e-6)
    n = 5000
    r = simulate_pair(model, np.arange(n) / model.rate, np.full(n, 20.0), rng)
    bias = np.round(r.range[r.nlos] - 20.0, 4)
    assert len(np.unique(bias)) > 100  # one per episode, not one for all
    assert bias.min() >= model.nlos_bias_min - 1e-3 and bias.max() <= model.nlos_bias_max + 1e-3

def test_two_state_markov_occupancy_and_dwell(rng) -> None:
    assert two_state_markov(0, 0.1, 0.1, rng).shape == (0,)
    s = two_state_markov(500_000, 0.01, 0.09, rng)
    assert s.mean() == pytest.approx(0.1, abs=0.01)
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], s.astype(int), [0]]))))[::2]
    assert runs.mean() == pytest.approx(1 / 0.09, rel=0.1)


def test_imu_noise_and_bias_statistics(rng) -> None:
    model = ImuModel()
    n, dt = 100_000, 0.01
    zero = np.zeros((n, 3))
    e = corrupt_increments(model, zero, zero, np.full(n, dt), rng)
    noise_th = (e.dtheta - e.gyro_bias * dt) / math.sqrt(dt)
    noise_dv = (e.dvel - e.accel_bias * dt) / math.sqrt(dt)
    assert noise_th.std(axis=0) == pytest.approx(np.full(3, model.arw), rel=0.03)
    assert noise_dv.std(axis=0) == pytest.approx(np.full(3, model.vrw), rel=0.03)
    # turn-on bias spread over many seeded units (±15 %)
    tb = np.array([corrupt_increments(model, zero[:10], zero[:10], np.full(10, dt),
                                      np.random.default_rng(s)).gyro_bias[0] for s in range(600)])
    expected = math.hypot(model.gyro_turn_on, model.gyro_in_run)
    assert tb.std() == pytest.approx(expected, rel=0.15)
    # scale factor applied to the true increments
    ones = np.ones((n, 3)) * dt
    e2 = corrupt_increments(ImuModel(arw=0, vrw=0, gyro_turn_on=0, accel_turn_on=0, gyro_in_run=0,
                                     accel_in_run=0, gyro_scale=0.01, misalignment=0),
                            ones, ones, np.full(n, dt), np.random.default_rng(3))
    assert np.allclose(e2.dtheta[0], e2.gyro_matrix @ ones[0])


def test_gnss_white_multipath_nlos_outage_statistics(rng) -> None:
    t = np.arange(0, 20_000, 0.2)
    quiet = GnssModel(multipath_h=0.0, multipath_v=0.0, nlos_rate=0.0, outage_rate=0.0)
    e = simulate_gnss(quiet, t, np.ones(len(t), bool), rng)
    assert e.pos_error[:, :2].std() == pytest.approx(quiet.white_h, rel=0.03)
    assert e.pos_error[:, 2].std() == pytest.approx(quiet.white_v, rel=0.03)
    mp = GnssModel(white_h=0.0, white_v=0.0, nlos_rate=0.0, outage_rate=0.0, multipath_tau_moving=10.0)
    e = simulate_gnss(mp, t, np.ones(len(t), bool), rng)
    assert e.pos_error[:, 0].std() == pytest.approx(mp.multipath_h, rel=0.1)
    assert _tau_from_lag1(e.pos_error[:, 0], 0.2) == pytest.approx(10.0, rel=0.15)
    ev = GnssModel(nlos_rate=1 / 100, outage_rate=1 / 200)
    e = simulate_gnss(ev, t, np.ones(len(t), bool), rng)
    # occupancy of (possibly overlapping) Poisson windows: 1 - exp(-rate * mean duration)
    assert e.nlos.mean() == pytest.approx(1 - math.exp(-32.5 / 100), abs=0.05)
    assert (~e.valid).mean() == pytest.approx(1 - math.exp(-11.0 / 200), abs=0.02)
    assert np.abs(e.pos_error[e.nlos, :2]).max() > 5.0
    # the velocity noise and the receiver's reported velocity σ, in and out of NLOS
    assert e.vel_error[~e.nlos].std() == pytest.approx(ev.velocity_white, rel=0.03)
    assert e.vel_error[e.nlos].std() == pytest.approx(math.hypot(ev.velocity_white, ev.velocity_nlos), rel=0.03)
    assert np.abs(e.vel_error[e.nlos].mean(axis=0)).max() < 0.05  # zero-mean, as the filters assume
    assert np.allclose(e.reported_sigma_v[~e.nlos], ev.velocity_white)
    ratio = e.reported_sigma_v[e.nlos] / math.hypot(ev.velocity_white, ev.velocity_nlos)
    assert np.median(ratio) == pytest.approx(1.0, abs=0.05) and np.std(np.log(ratio)) > 0.2  # mis-scaled
    cm = common_mode_error(t, 1.5, 600.0, rng)
    assert cm.shape == (len(t), 3)


def test_gnss_nlos_bias_and_reported_sigma_in_closed_form(rng) -> None:
    """An NLOS episode adds a horizontal bias of size U(min, max) in a uniform direction and
    0.3 of it downward (the fix rises); the receiver reports σ = sqrt(white² + multipath²) per
    axis, mis-scaled by a log-normal factor of median 1."""
    t = np.arange(0, 100_000, 0.2)
    m = GnssModel(white_h=1e-6, white_v=1e-6, multipath_h=1e-6, multipath_v=1e-6, nlos_rate=1 / 300,
                  outage_rate=0.0)
    e = simulate_gnss(m, t, np.ones(len(t), bool), rng)
    b = e.pos_error[e.nlos]
    mag = np.hypot(b[:, 0], b[:, 1])
    # episodes seldom overlap (then their biases add as vectors and their heights as sizes)
    up = -b[:, 2]  # NED: the fix rises
    assert up.min() >= 0.3 * m.nlos_bias_min - 1e-3 and (up >= 0.3 * mag - 1e-3).all()
    single = np.isclose(up, 0.3 * mag, atol=1e-3)
    assert single.mean() > 0.8
    assert mag[single].min() >= m.nlos_bias_min - 1e-3 and mag[single].max() <= m.nlos_bias_max + 1e-3
    ang = np.arctan2(b[single, 1], b[single, 0])
    assert abs(np.mean(np.cos(ang))) < 0.15 and abs(np.mean(np.sin(ang))) < 0.15  # no preferred direction
    q = GnssModel(white_h=0.6, white_v=0.9, multipath_h=0.8, multipath_v=1.2, nlos_rate=0.0, outage_rate=0.0)
    e = simulate_gnss(q, t[:20_000], np.ones(20_000, bool), rng)
    ratio = e.reported_sigma / np.array([1.0, 1.0, 1.5])  # sqrt(0.6² + 0.8²), sqrt(0.9² + 1.2²)
    assert np.allclose(ratio[:, 0], ratio[:, 2]) and np.allclose(ratio[:, 0], ratio[:, 1])
    assert np.median(ratio[:, 0]) == pytest.approx(1.0, abs=0.02)


def test_uwb_los_nlos_outliers_and_success(rng) -> None:
    model = UwbModel()
    n = 400_000
    t = np.arange(n) / model.rate
    r = simulate_pair(model, t, np.full(n, 20.0), rng)
    clean = r.delivered & ~r.nlos & ~r.outlier
    assert (r.range[clean] - 20.0).std() == pytest.approx(model.sigma_los, rel=0.03)
    occ = model.nlos_enter / (model.nlos_enter + model.nlos_exit)
    assert r.nlos[r.delivered].mean() == pytest.approx(occ, rel=0.15)
    assert r.outlier[r.delivered].mean() == pytest.approx(model.outlier_prob, rel=0.15)
    bias = r.range[r.nlos & ~r.outlier] - 20.0
    assert model.nlos_bias_min - 0.3 < bias.mean() < model.nlos_bias_max
    for d, p in ((30.0, 0.95), (100.0, 0.5)):
        rr = simulate_pair(model, t[:50_000], np.full(50_000, d), rng)
        assert rr.delivered.mean() == pytest.approx(p, abs=0.01)
    far = simulate_pair(model, t[:1000], np.full(1000, model.max_range + 1), rng)
    assert not far.delivered.any()



def test_uwb_outliers_go_both_ways_within_their_size(rng) -> None:
    """A gross outlier adds ±U(outlier_min, outlier_max) (then the range is kept positive):
    at 40 m true range, half the outliers are short and half long, each error's size within
    the bounds (plus LOS noise and an NLOS bias), and uniform: its mean is the interval's."""
    model = UwbModel(outlier_prob=0.2, nlos_enter=0.0)
    n = 100_000
    r = simulate_pair(model, np.arange(n) / model.rate, np.full(n, 40.0), rng)
    err = r.range[r.outlier] - 40.0
    assert len(err) > 15_000
    assert (err < 0).mean() == pytest.approx(0.5, abs=0.02)
    slack = 5 * model.sigma_los
    assert (np.abs(err) >= model.outlier_min - slack).all() and (np.abs(err) <= model.outlier_max + slack).all()
    assert np.abs(err).mean() == pytest.approx(0.5 * (model.outlier_min + model.outlier_max), rel=0.02)
    close = simulate_pair(model, np.arange(n) / model.rate, np.full(n, 2.0), rng)
    assert (close.range[close.delivered] >= 0).all()  # a short outlier at 2 m stays a distance


def test_radio_without_jitter_and_at_its_range_limit(rng) -> None:
    """No jitter: every latency is ``latency_min``; the range limit is inclusive, and past it
    nothing arrives whatever the loss; no loss: everything within range arrives."""
    model = RadioModel(loss=0.0, ge_p_good_to_bad=0.0, jitter_mean=0.0, stale_prob=0.0, max_range=100.0)
    t = np.arange(1000) * 0.2
    d = simulate_link(model, t, np.full(1000, 100.0), rng)
    assert d.delivered.all() and np.allclose(d.t_arrive - t, model.latency_min, atol=1e-12)
    assert not simulate_link(model, t, np.full(1000, 100.001), rng).delivered.any()
    jit = simulate_link(RadioModel(loss=0.0, ge_p_good_to_bad=0.0, stale_prob=0.0), t, np.full(1000, 5.0), rng)
    lat = jit.t_arrive - t
    assert lat.min() >= 0.001 - 1e-12 and lat.max() <= 0.020 + 1e-12 and lat.std() > 0.001  # float sums

    # without bursts the long-run loss is the good state's
    assert RadioModel(loss=0.3, ge_p_good_to_bad=0.0, ge_p_bad_to_good=0.0).expected_loss() == 0.3


@pytest.mark.parametrize("error", [0.02, 0.4])
def test_lane_camera_misreads_for_the_configured_share_of_the_time(error: float, rng) -> None:
    """The misread chain's stationary share is ``error`` (its entry probability is set from the
    exit one), with episodes of mean length ``error_tau``, at a small and a large error."""
    from slcp.geo.lane_markings import DIVIDER

    model = LaneCameraModel(error=error, error_tau=1.0, unseen=0.0)
    n = 200_000
    out = simulate_markings(model, np.full((n, 2), DIVIDER), rng)
    wrong = out[:, 0] != DIVIDER
    assert wrong.mean() == pytest.approx(error, rel=0.1)
    starts = np.count_nonzero(wrong[1:] & ~wrong[:-1])
    assert wrong.sum() / starts / model.rate == pytest.approx(model.error_tau, rel=0.1)


def test_radio_loss_burstiness_latency_and_range(rng) -> None:
    model = RadioModel()
    n = 300_000
    t = np.arange(n) * 0.2
    d = simulate_link(model, t, np.full(n, 50.0), rng)
    assert 1 - d.delivered.mean() == pytest.approx(model.expected_loss(), rel=0.05)
    lat = (d.t_arrive - d.t_send)[d.delivered & ~d.stale]
    assert lat.min() >= model.latency_min - 1e-9 and lat.max() <= model.latency_max + 1e-9
    assert d.stale[d.delivered].mean() == pytest.approx(model.stale_prob, rel=0.2)
    stale_lat = (d.t_arrive - d.t_send)[d.stale]
    assert np.all((stale_lat >= 0.1) & (stale_lat <= 0.3))
    # bursts: losses cluster (lag-1 correlation of the loss indicator > 0)
    lost = (~d.delivered).astype(float)
    assert np.corrcoef(lost[:-1], lost[1:])[0, 1] > 0.2
    bern = simulate_link(RadioModel(loss=0.2, ge_p_good_to_bad=0.0), t, np.full(n, 50.0), rng)
    assert 1 - bern.delivered.mean() == pytest.approx(0.2, abs=0.005)
    assert not simulate_link(model, t[:100], np.full(100, model.max_range + 1), rng).delivered.any()


def test_lane_camera_error_share_episodes_and_unseen(rng) -> None:
    model = LaneCameraModel(error=0.05, error_tau=2.0, unseen=0.1)
    n = 400_000
    truth = np.tile([BOUNDARY, DIVIDER], (n, 1))
    truth[:1000] = UNSEEN  # inside the junction: nothing to see, nothing reported
    out = simulate_markings(model, truth, rng)
    assert np.all(out[:1000] == UNSEEN)
    seen = out[1000:, 0] != UNSEEN
    assert (~seen).mean() == pytest.approx(0.1, abs=0.005)
    wrong = out[1000:, 0] == DIVIDER
    assert wrong[seen].mean() == pytest.approx(0.05, rel=0.15)
    # episodes: a wrong frame is followed by another wrong one with P = exp(-dt/tau)-ish
    w = np.zeros(n - 1000, bool)  # errors before the unseen mask (re-simulate with unseen = 0)
    w[:] = simulate_markings(LaneCameraModel(error=0.05, error_tau=2.0, unseen=0.0), truth[1000:],
                             np.random.default_rng(3))[:, 0] == DIVIDER
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], w.astype(int), [0]]))))[::2]
    assert runs.mean() / model.rate == pytest.approx(2.0, rel=0.15)


def test_seeded_models_are_bit_identical() -> None:
    t = np.arange(0, 600, 0.2)
    a = simulate_gnss(GnssModel(), t, np.ones(len(t), bool), np.random.default_rng(5))
    b = simulate_gnss(GnssModel(), t, np.ones(len(t), bool), np.random.default_rng(5))
    assert np.array_equal(a.pos_error, b.pos_error) and np.array_equal(a.valid, b.valid)
    u1 = simulate_pair(UwbModel(), t, np.full(len(t), 40.0), np.random.default_rng(9))
    u2 = simulate_pair(UwbModel(), t, np.full(len(t), 40.0), np.random.default_rng(9))
    assert np.array_equal(u1.range, u2.range, equal_nan=True)


@pytest.mark.parametrize("cls, field, value, match", [
    (ImuModel, "arw", -1.0, "ImuModel.arw must be >= 0"),
    (ImuModel, "bias_tau", 0.0, "ImuModel.bias_tau must be > 0"),
    (GnssModel, "nlos_bias_max", 1.0, "nlos_bias_min must not exceed nlos_bias_max"),
    *[(GnssModel, f, -0.1, f"GnssModel.{f} must be >= 0") for f in ("white_h", "white_v", "multipath_h",
                                                                    "multipath_v", "nlos_rate")],
    (UwbModel, "outlier_prob", 1.5, "UwbModel.outlier_prob must be in"),
    (UwbModel, "rate", 500.0, "<= 100 Hz"),
    (RadioModel, "loss", float("nan"), "RadioModel.loss must be a number"),
    (LaneCameraModel, "error", 0.5, r"LaneCameraModel.error must be in \[0, 0.5\)"),
    (LaneCameraModel, "enabled", 1, "LaneCameraModel.enabled must be true or false"),
])
def test_bad_parameters_name_the_field(cls, field, value, match) -> None:
    with pytest.raises(ValueError, match=match):
        cls(**{field: value})


@pytest.mark.parametrize("phi", [0.0, 0.5, 0.99998, 1.0])
def test_the_ar1_recursion_is_scipys_lfilter_bit_for_bit(phi) -> None:
    """The Gauss-Markov recursion without scipy.signal: the same operations as lfilter's, so
    the same bits (the seeded sensor data does not move)."""
    from scipy.signal import lfilter

    w = np.random.default_rng(5).normal(size=(3000, 3))
    x = ar1_filter(w, phi)
    assert np.array_equal(x, lfilter([1.0], [1.0, -phi], w, axis=0))
    assert np.array_equal(w, np.random.default_rng(5).normal(size=(3000, 3)))  # input left alone
    assert ar1_filter(np.zeros((0, 2)), phi).shape == (0, 2)


def test_imu_misalignment_is_a_small_rotation_and_the_biases_are_independent_per_axis() -> None:
    """The error matrices are I + diag(scale) + [m]×: their off-diagonal part is exactly
    skew-symmetric, for the gyro and the accelerometer, in every seeded unit; and each axis has
    its own in-run bias: with no turn-on bias, the three axes' Gauss-Markov walks are
    uncorrelated (|r| < 0.1 over 200 correlation times)."""
    model = ImuModel(misalignment=0.01, gyro_scale=0.003, accel_scale=0.003)
    n, dt = 20_000, 0.01
    zero = np.zeros((n, 3))
    for seed in range(5):
        e = corrupt_increments(model, zero[:10], zero[:10], np.full(10, dt), np.random.default_rng(seed))
        for mat in (e.gyro_matrix, e.accel_matrix):
            off = mat - np.diag(np.diag(mat))
            np.testing.assert_array_equal(off, -off.T)
            assert np.abs(off).max() > 0
    quiet = ImuModel(arw=0, vrw=0, gyro_turn_on=0, accel_turn_on=0, bias_tau=1.0)
    e = corrupt_increments(quiet, zero, zero, np.full(n, dt), np.random.default_rng(7))
    for bias in (e.gyro_bias, e.accel_bias):
        r = np.corrcoef(bias.T)
        assert np.abs(r[np.triu_indices(3, 1)]).max() < 0.1, r


@pytest.mark.parametrize("field", ["rate", "error_tau"])
def test_a_camera_model_needs_a_positive_rate_and_error_time(field: str) -> None:
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match=field):
            LaneCameraModel(**{field: bad})


def test_two_state_markov_takes_certain_transitions_and_names_a_bad_probability(rng) -> None:
    """p = 1 is a probability: with p_enter = p_exit = 1 the chain alternates every step. A
    value outside [0, 1] is refused, naming the parameter."""
    s = two_state_markov(10, 1.0, 1.0, rng, start=False)
    np.testing.assert_array_equal(s, [False, True] * 5)
    for kw, name in (({"p_enter": 1.5, "p_exit": 0.1}, "p_enter"), ({"p_enter": 0.1, "p_exit": -0.2}, "p_exit")):
        with pytest.raises(ValueError, match=name):
            two_state_markov(10, rng=rng, **kw)
