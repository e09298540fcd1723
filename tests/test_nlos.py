"""The UWB NLOS classifier: its posterior against numerical integration, its far tail against
scipy, its steady prior against the Markov chain's matrix exponential, its calibration on seeded
Monte-Carlo links, and its use by the CI range update. The per-link NLOS tracker: step for step
on an episode, the chain's closed-form decay, passing and braking cars, outliers, and its
calibration on links drawn by the emulator."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, linalg, stats

from slcp.agent.range_gate import NlosModel
from slcp.hw_emulation.sensors.processes import two_state_markov

MODEL = NlosModel(enter=0.02, exit=0.2, bias_min=0.3, bias_max=3.0)  # the scenarios' UWB model


@pytest.mark.parametrize("nu,var,prior", [(0.1, 0.04, 0.09), (0.9, 0.09, 0.09), (2.85, 0.46, 0.09),
                                          (2.0, 4.0, 0.5), (-2.7, 0.5, 0.9), (5.0, 0.2, 0.3)])
def test_posterior_matches_numerical_integration(nu: float, var: float, prior: float) -> None:
    s = math.sqrt(var)
    a, c = MODEL.bias_min, MODEL.bias_max
    dens = lambda b: stats.norm.pdf(nu - b, scale=s) / (c - a)  # noqa: E731
    l_nlos = integrate.quad(dens, a, c, points=[min(max(nu, a), c)])[0]
    l_los = stats.norm.pdf(nu, scale=s)
    want = prior * l_nlos / (prior * l_nlos + (1 - prior) * l_los)
    assert MODEL.posterior(prior, nu, var) == pytest.approx(want, rel=1e-6, abs=1e-12)


def test_far_innovations_do_not_break_the_posterior() -> None:
    assert MODEL.posterior(0.09, 40.0, 0.01) == 1.0  # only a bias (or worse) explains it
    assert MODEL.posterior(0.09, -40.0, 0.01) == 0.0  # NLOS cannot shorten a range
    assert MODEL.posterior(0.0, 2.0, 0.1) == 0.0 and MODEL.posterior(1.0, 0.0, 0.1) == 1.0
    with pytest.raises(ValueError):
        NlosModel(0.02, 0.0, 0.3, 3.0)


def test_steady_prior_is_the_chains_long_run_share() -> None:
    q = np.array([[-MODEL.enter, MODEL.enter], [MODEL.exit, -MODEL.exit]])  # LOS, NLOS
    assert (np.array([1.0, 0.0]) @ linalg.expm(q * 1e3))[1] == pytest.approx(MODEL.steady, rel=1e-9)


def test_classifier_is_calibrated_and_rejects_what_it_should() -> None:
    """Seeded links as the emulator draws them (10 Hz, an episode's bias uniform in 0.3-3 m),
    each with its own innovation variance: clean ranges are rarely rejected, large biases
    almost always where the innovation's σ is 0.5 m or less; and among ranges given
    probability p of NLOS, a share p is NLOS."""
    rng = np.random.default_rng(7)
    dt = 0.1
    cols: dict[str, list] = {"p": [], "nlos": [], "bias": [], "rej": [], "var": []}
    for _ in range(400):
        var = float(rng.uniform(0.02, 1.0))
        n = 300
        nlos = two_state_markov(n, MODEL.enter * dt, MODEL.exit * dt, rng)
        starts = np.flatnonzero(nlos & ~np.concatenate([[False], nlos[:-1]]))
        ep = np.cumsum(np.isin(np.arange(n), starts))
        bias = np.where(nlos, rng.uniform(MODEL.bias_min, MODEL.bias_max, len(starts) + 1)[ep], 0.0)
        for x in bias + rng.normal(0.0, math.sqrt(var), n):
            cols["rej"].append(MODEL.classify(float(x), var))
            cols["p"].append(MODEL.posterior(MODEL.steady, float(x), var))
            cols["var"].append(var)
        cols["nlos"].append(nlos)
        cols["bias"].append(bias)
    p, rej, var = (np.array(cols[k]) for k in ("p", "rej", "var"))
    nlos, bias = np.concatenate(cols["nlos"]), np.concatenate(cols["bias"])
    assert rej[~nlos].mean() < 0.01  # clean ranges wrongly rejected
    assert rej[(bias > 1.5) & (var <= 0.25)].mean() > 0.95  # biases that would move a vehicle metres
    assert np.array_equal(rej, p > 0.5)
    assert abs(p.mean() - nlos.mean()) < 0.015
    for lo, hi in ((0.0, 0.1), (0.1, 0.5), (0.5, 0.9), (0.9, 1.0)):
        sel = (p >= lo) & (p < hi)
        assert sel.sum() > 200
        assert abs(nlos[sel].mean() - p[sel].mean()) < 0.05, (lo, hi)


def test_a_link_that_starts_in_nlos_is_not_fused() -> None:
    """After its stop-line fix a vehicle knows its place to 0.2 m; a neighbour's first range
    2.5 m too long (a link that starts in NLOS: no jump for the rate gate) is classified and
    left out, a clean one is fused; the paper's rule has no classifier."""
    from test_methods import ORIGIN, _stopped_filter

    from slcp.agent.neighbours import NeighbourState
    from slcp.geo import earth

    rm, _ = earth.radii(ORIGIN[0])
    outcomes = {}
    for fusion in ("split-ci", "paper"):
        for measured in (20.0, 22.5):
            f, approach, _, true_llh = _stopped_filter("SL-CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0,
                                                       uwb_nlos=MODEL, fusion=fusion)
            assert f.stop_line(approach).accepted
            nb = NeighbourState("V2", true_llh + np.array([-20.0 / (rm + 50), 0.0, 0.0]), np.eye(3) * 0.01, 0.05)
            outcomes[(fusion, measured)] = f.range(nb, measured)
    assert outcomes[("split-ci", 20.0)] == "fused" and outcomes[("split-ci", 22.5)] == "gate_nlos"
    assert outcomes[("paper", 22.5)] != "gate_nlos"


def test_the_far_tail_matches_scipy() -> None:
    """Where Φ underflows, the agent's own log-tail series (an agent process loads no scipy)."""
    from scipy import special

    from slcp.agent.range_gate import _log_lower_tail

    for x in (-30.0, -37.5, -60.0, -1e3):
        assert _log_lower_tail(x) == pytest.approx(float(special.log_ndtr(x)), rel=1e-9)


# --- the per-link tracker ------------------------------------------------------------------

def _tracker():
    from slcp.agent.range_gate import NlosLinkTracker

    model = NlosModel(MODEL.enter, MODEL.exit, MODEL.bias_min, MODEL.bias_max, 0.007, 3.0, 30.0)
    return NlosLinkTracker(model, 0.07)


def test_the_link_tracker_follows_an_episode_step_for_step() -> None:
    """A standing pair 20 m apart, 10 Hz: 5 s clean, 3 s with a 1.2 m NLOS bias, 5 s clean.
    The step up makes the link NLOS at once with the step as its bias; the step down ends it;
    a clean link's NLOS probability decays from the chain's steady share."""
    rng = np.random.default_rng(3)
    tr = _tracker()
    t = np.arange(0.0, 13.0, 0.1)
    bias = np.where((t >= 5.0) & (t < 8.0), 1.2, 0.0)
    beliefs = [tr.belief("V2", float(tk), 20.0 + b + float(rng.normal(0.0, 0.07)), 0.0, standing=True)
               for tk, b in zip(t, bias)]
    p = np.array([b.p_nlos for b in beliefs])
    assert p[0] == pytest.approx(MODEL.steady)
    # no step for 4 s: the odds of NLOS fall as the chain says (each 0.1 s, an episode that
    # would have ended but did not, against one that would have started but did not)
    e = math.exp(-(MODEL.enter + MODEL.exit) * 0.1)
    per_step = (MODEL.steady + (1 - MODEL.steady) * e) / (1 - MODEL.steady * (1 - e))
    odds = p[:50] / (1 - p[:50])
    assert odds[49] / odds[10] == pytest.approx(per_step**39, rel=0.02) and p[49] < 0.1
    assert p[50] > 0.99 and np.all(p[50:80] > 0.99)
    assert math.sqrt(beliefs[50].bias_mean_square) == pytest.approx(1.2, abs=0.25)
    assert p[80] < 0.01 and np.all(p[80:] < 0.01)
    assert not any(b.outlier for b in beliefs)


def test_passing_cars_and_outliers_on_the_link_tracker() -> None:
    """Two cars pass each other at 15 m/s, 2 m apart: the range rate reverses within 0.3 s.
    With the relative speed the level's prediction follows it (no range taken for an outlier,
    no NLOS); without it, the track still follows the range after the pass instead of
    sticking. A gross 10 m error is an outlier and leaves the track as it was."""
    t = np.arange(0.0, 4.0, 0.1)
    x = 30.0 - 15.0 * t
    d = np.hypot(x, 2.0)
    rate = -15.0 * x / d
    tr = _tracker()
    bs = [tr.belief("V2", float(tk), float(dk), float(rk), 225.0) for tk, dk, rk in zip(t, d, rate)]
    assert not any(b.outlier for b in bs) and max(b.p_nlos for b in bs) <= MODEL.steady + 1e-12
    tr = _tracker()
    bs = [tr.belief("V2", float(tk), float(dk), float(rk)) for tk, dk, rk in zip(t, d, rate)]
    assert sum(b.outlier for b in bs) <= 2 and abs(tr._links["V2"].r - d[-1]) < 0.1
    tr = _tracker()
    for tk in np.arange(0.0, 2.0, 0.1):
        tr.belief("V2", float(tk), 20.0, 0.0)
    before = tr.belief("V2", 2.0, 20.0, 0.0)
    out = tr.belief("V2", 2.1, 30.0, 0.0)
    # an outlier leaves the link's belief as it was: its NLOS probability and bias
    assert out.outlier and out.p_nlos == pytest.approx(tr._links["V2"].p)
    assert out.bias_mean_square == pytest.approx(tr._links["V2"].b2)
    after = tr.belief("V2", 2.2, 20.0, 0.0)
    assert not after.outlier and after.p_nlos <= before.p_nlos


def test_the_link_tracker_is_calibrated_on_emulated_links() -> None:
    """Seeded links drawn by the emulator's UWB model (two cars closing at 0-12 m/s and
    passing, the estimates' range rate off by 0.2 m/s and given with that σ): among ranges
    given probability p of NLOS, a share p is NLOS; most NLOS ranges are found from the series
    alone, few clean ones are taken for NLOS, and the gross outliers are flagged."""
    from slcp.agent.range_gate import NlosLinkTracker
    from slcp.hw_emulation.sensors.uwb import UwbModel, simulate_pair

    u = UwbModel()
    model = NlosModel(u.nlos_enter, u.nlos_exit, u.nlos_bias_min, u.nlos_bias_max,
                      u.outlier_prob, u.outlier_min, u.outlier_max)
    rng = np.random.default_rng(11)
    p, nlos, outlier, flagged = [], [], [], []
    t = np.arange(0.0, 60.0, 0.1)
    for _ in range(120):
        v, off = rng.uniform(0.0, 12.0), rng.uniform(2.0, 10.0)
        x = 30.0 - v * t
        d = np.hypot(x, off)
        rr = simulate_pair(u, t, d, rng)
        tr = NlosLinkTracker(model, u.sigma_los)
        for i in np.flatnonzero(rr.delivered):
            b = tr.belief("j", float(t[i]), float(rr.range[i]), float(-v * x[i] / d[i] + rng.normal(0.0, 0.2)), v * v,
                          rate_var=0.04)
            p.append(b.p_nlos)
            flagged.append(b.outlier)
            nlos.append(rr.nlos[i])
            outlier.append(rr.outlier[i])
    p, nlos, outlier, flagged = (np.array(a) for a in (p, nlos, outlier, flagged))
    clean = ~nlos & ~outlier
    assert flagged[outlier].mean() > 0.95 and flagged[clean].mean() < 0.001
    scored = ~flagged & ~outlier
    assert (p[nlos & scored] > 0.5).mean() > 0.65
    assert (p[clean & scored] > 0.5).mean() < 0.01
    for lo, hi in ((0.0, 0.1), (0.9, 1.01)):
        sel = scored & (p >= lo) & (p < hi)
        assert sel.sum() > 1000, (lo, hi)
        assert abs(nlos[sel].mean() - p[sel].mean()) < 0.05, (lo, hi, nlos[sel].mean(), p[sel].mean())
    # the undecided: few, mostly sparse far links (gaps of seconds) where a step hides in the
    # level's prediction; there p understates the NLOS share (the range keeps its p · E[b²])
    sel = scored & (p >= 0.1) & (p < 0.9)
    assert sel.mean() < 0.03 and 0.1 < nlos[sel].mean() < 0.95


def test_a_known_link_rejects_an_episode_the_estimates_cannot_see() -> None:
    """A vehicle 2 m off at σ 4 m ranges at 10 Hz to a standing neighbour 20 m north: the
    innovation against the estimates cannot tell a 0.8 m NLOS bias from its position error,
    but the link's own series sees the step. With the tracker the biased ranges are refused;
    without it they are kept."""
    from test_methods import ORIGIN, _stopped_filter

    from slcp.agent.neighbours import NeighbourState
    from slcp.geo import earth

    rm, _ = earth.radii(ORIGIN[0])
    zero, dt = np.zeros(3), 0.01
    outcomes = {}
    for tracking in (True, False):
        f, _, _, true_llh = _stopped_filter("CP", offset_ne=(2.0, 0.0), range_min_sigmas=0.0, uwb_nlos=MODEL,
                                            nlos_link_tracking=tracking)
        g = np.array([0.0, 0.0, -earth.gravity(ORIGIN[0], 50.0)]) * dt
        nb = NeighbourState("V2", true_llh + np.array([20.0 / (rm + 50), 0.0, 0.0]), np.eye(3) * 0.04, 0.05)
        rng = np.random.default_rng(5)
        out = []
        for k in range(60):
            for _ in range(10):
                f.propagate(zero, g, dt)
            out.append(f.range(nb, 20.0 + (0.8 if k >= 40 else 0.0) + float(rng.normal(0.0, 0.05))))
        outcomes[tracking] = out
    assert all(
        o == "gate_nlos" for o in outcomes[True][41:]
    )  # the first is the rate gate's? no: a 0.8 m step passes it
    assert "gate_nlos" not in outcomes[False][40:]


def test_braking_towards_each_other_is_no_step_with_the_inertial_rate() -> None:
    """Two cars 70 m apart on one road brake towards each other from 12 m/s at 8 m/s²: the
    range rate goes from -24 to 0 m/s in 1.5 s. Given the range rate of the two inertial
    velocities (σ 0.3 m/s) at every range, the track follows it and no clean range looks like
    a step, while a 0.6 m NLOS bias that starts in the middle of the braking is found at once."""
    t = np.arange(0.0, 4.0, 0.1)
    v = np.maximum(12.0 - 8.0 * np.maximum(t - 1.0, 0.0), 0.0)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * 0.1)])
    d = 70.0 - 2.0 * x
    rng = np.random.default_rng(2)
    noise = rng.normal(0.0, 0.07, len(t))
    rate = -2.0 * v + rng.normal(0.0, 0.3, len(t))
    for bias in (0.0, 0.6):
        tr = _tracker()
        measured = d + noise + np.where(t >= 1.75, bias, 0.0)
        p = np.array([tr.belief("V2", float(tk), float(r), float(rr), float((2 * vk) ** 2), rate_var=0.09).p_nlos
                      for tk, r, rr, vk in zip(t, measured, rate, v)])
        assert p[t < 1.75].max() <= MODEL.steady + 1e-9
        if bias:
            assert p[t >= 1.75].min() > 0.9
        else:
            assert p.max() <= MODEL.steady + 1e-9


def test_an_nlos_model_accepts_outliers_from_any_non_negative_size() -> None:
    import dataclasses

    assert dataclasses.replace(MODEL, outlier_min=0.5).outlier_min == 0.5
    with pytest.raises(ValueError):
        dataclasses.replace(MODEL, outlier_min=-0.5)


def test_the_normal_probability_between_two_bounds_in_both_tails() -> None:
    """``_cdf_between(a, b)`` = P(a < X < b) for X ~ N(0, 1), against quadrature of the density,
    with both bounds below zero, both above, and one each side, out into the far tails."""
    from slcp.agent.range_gate import _cdf_between

    pts = (-40.0, -8.0, -3.0, -1.0, -0.2, 0.0, 0.3, 2.0, 7.0, 40.0)
    for i, a in enumerate(pts):
        for b in pts[i + 1:]:
            want = integrate.quad(stats.norm.pdf, a, b, epsabs=0.0, epsrel=1e-11, limit=200)[0]
            assert _cdf_between(a, b) == pytest.approx(want, rel=1e-9, abs=1e-300), (a, b)


def test_a_range_continues_its_track_within_three_sigma_plus_the_rate_uncertainty() -> None:
    """A range continues the track when it is within 3 σ of the prediction, σ² = 2 σ_uwb² +
    q dt³/3 (the relative acceleration's random walk), plus the range-rate uncertainty × dt."""
    tr = _tracker()
    for dt in (0.1, 1.0):
        limit = 3.0 * math.sqrt(2.0 * tr.sigma**2 + tr.accel_psd * dt**3 / 3.0) + tr.rate_sigma * dt
        for rate in (0.0, -4.0):
            start = 20.0 + rate * dt
            assert tr._agrees(0.0, 20.0, dt, start + 0.99 * limit, rate)
            assert tr._agrees(0.0, 20.0, dt, start - 0.99 * limit, rate)
            assert not tr._agrees(0.0, 20.0, dt, start + 1.01 * limit, rate)
    assert not tr._agrees(1.0, 20.0, 1.0, 20.0, 0.0)  # no time between: no continuation


def test_an_outlier_out_of_order_leaves_the_links_belief() -> None:
    """A gross range stamped before the link's last one is scored, not kept: an outlier that
    reports the link's NLOS probability and bias as they are."""
    tr = _tracker()
    for tk in np.arange(0.0, 2.0, 0.1):
        tr.belief("V2", float(tk), 20.0, 0.0)
    lk = tr._links["V2"]
    out = tr.belief("V2", 1.85, 35.0, 0.0)
    assert out.outlier and out.p_nlos == lk.p and out.bias_mean_square == lk.b2


def test_an_nlos_bias_may_start_at_zero() -> None:
    import dataclasses

    assert dataclasses.replace(MODEL, bias_min=0.0).bias_min == 0.0
    with pytest.raises(ValueError):
        dataclasses.replace(MODEL, bias_min=-0.1)
