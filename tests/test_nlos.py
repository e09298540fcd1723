"""The UWB NLOS classifier: its posterior against numerical integration, its far tail against
scipy, its steady prior against the Markov chain's matrix exponential, its calibration on seeded
Monte-Carlo links, and its use by the CI range update."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, linalg, stats

from agent.range_gate import NlosModel
from hw_emulation.sensors.processes import two_state_markov

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
    from agent.neighbours import NeighbourState
    from agent.nav import earth
    from test_methods import ORIGIN, _stopped_filter

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

    from agent.range_gate import _log_lower_tail

    for x in (-30.0, -37.5, -60.0, -1e3):
        assert _log_lower_tail(x) == pytest.approx(float(special.log_ndtr(x)), rel=1e-9)
