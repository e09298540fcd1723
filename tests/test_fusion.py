"""Split covariance intersection and plain CI against closed forms and Monte-Carlo."""

from __future__ import annotations

import numpy as np
import pytest

from slcp.agent.nav.fusion import _posterior_trace, best_omega, split_ci_update
from slcp.agent.nav.kalman import Measurement, kalman_update

IDX = np.array([0, 1])


def _spd(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return scale * (a @ a.T / n + np.eye(n) * 0.1)


def test_with_nothing_dependent_split_ci_is_the_kalman_update() -> None:
    rng = np.random.default_rng(1)
    P = _spd(rng, 5)
    m = Measurement(rng.normal(size=2), rng.normal(size=(2, 5)), _spd(rng, 2, 0.5))
    dx, P_post, Pi_post, res = split_ci_update(P, P.copy(), m, np.zeros((2, 2)), IDX)
    dx_k, P_k, _ = kalman_update(P, m)
    assert np.allclose(dx, dx_k, atol=1e-6) and np.allclose(P_post, P_k, atol=1e-6)
    assert np.allclose(Pi_post, P_post, atol=1e-6)  # all of it stays independent


def test_ci_of_an_estimate_with_itself_gains_nothing_while_the_paper_rule_halves_it() -> None:
    P = np.diag([4.0, 1.0])
    H = np.eye(2)
    m = Measurement(np.zeros(2), H, np.eye(2) * 1e-12)
    _, P_ci, _, res = split_ci_update(P, np.zeros((2, 2)), m, P.copy(), IDX)
    _, P_naive, _ = kalman_update(P, Measurement(np.zeros(2), H, P.copy()))
    assert np.trace(P_ci) == pytest.approx(np.trace(P), rel=2e-3)
    assert np.trace(P_naive) == pytest.approx(np.trace(P) / 2)


def test_omega_minimises_the_posterior_trace() -> None:
    rng = np.random.default_rng(2)
    P, Pi = _spd(rng, 4), _spd(rng, 4, 0.3)
    H, Rd, Ri = rng.normal(size=(1, 4)), np.array([[0.7]]), np.array([[0.05]])
    w = best_omega(P, Pi, H, Rd, Ri, IDX)
    grid = np.linspace(0.001, 0.999, 999)
    best = grid[np.argmin([_posterior_trace(P, Pi, H, Rd, Ri, IDX, g) for g in grid])]
    assert w == pytest.approx(best, abs=3e-3)


def test_split_ci_is_consistent_for_unknown_correlation_where_the_kalman_rule_is_not() -> None:
    """Two estimates of a 2-D position with strongly correlated errors (ρ = 0.9, the correlation
    unknown to the fusion) plus an independent white measurement part: NEES of split CI stays at or
    below the dimension; the independent (paper) rule is overconfident."""
    rng = np.random.default_rng(3)
    n_mc = 4000
    P = np.diag([4.0, 1.0])
    Rd = np.diag([2.0, 3.0])
    Ri = np.eye(2) * 0.25
    rho = 0.9
    L = np.linalg.cholesky(np.block([[P, rho * np.sqrt(P) @ np.sqrt(Rd)], [rho * np.sqrt(Rd) @ np.sqrt(P), Rd]]))
    nees_ci, nees_kf = [], []
    for _ in range(n_mc):
        e = L @ rng.normal(size=4)
        e_own, e_other = e[:2], e[2:]
        z = e_own - (e_other + rng.normal(size=2) * 0.5)  # own minus the other's measurement
        m = Measurement(z, np.eye(2), Ri)
        dx, Pc, _, _ = split_ci_update(P, np.zeros((2, 2)), m, Rd, IDX)
        r = e_own - dx
        nees_ci.append(r @ np.linalg.solve(Pc, r))
        dxk, Pk, _ = kalman_update(P, Measurement(z, np.eye(2), Rd + Ri))
        rk = e_own - dxk
        nees_kf.append(rk @ np.linalg.solve(Pk, rk))
    assert np.mean(nees_ci) <= 2.0 * 1.05
    assert np.mean(nees_kf) > 2.0 * 1.5


@pytest.mark.parametrize("m", [1, 2])
def test_precomputed_trace_equals_the_explicit_posterior(m: int) -> None:
    from slcp.agent.nav.fusion import _trace_fn

    rng = np.random.default_rng(4)
    Pd, Pi = _spd(rng, 6), _spd(rng, 6, 0.5)
    H, Rd, Ri = rng.normal(size=(m, 6)), _spd(rng, m, 0.7), _spd(rng, m, 0.1)
    f = _trace_fn(Pd, Pi, H, Rd, Ri, IDX)
    for w in (0.05, 0.3, 0.7, 0.95):
        P1, R1 = Pd / w + Pi, Rd / (1 - w) + Ri
        _, P_post, _ = kalman_update(P1, Measurement(np.zeros(m), H, R1))
        assert f(w) == pytest.approx(np.trace(P_post[np.ix_(IDX, IDX)]), rel=1e-9)


@pytest.mark.parametrize("m", [1, 2])
def test_plain_gain_bounds_split_ci_so_the_screen_changes_no_decision(m: int) -> None:
    """Node selection screens a range by its plain Kalman gain before the ω search: that gain
    bounds every ω's, so what the screen skips the search would have skipped too."""
    from slcp.agent.nav.fusion import _trace_fn, naive_gain

    rng = np.random.default_rng(7)
    skipped = 0
    for _ in range(200):
        scale = 10.0 ** rng.uniform(-2, 1, 2)
        Pd, Pi = _spd(rng, 6, scale[0]), _spd(rng, 6, scale[1])
        H, Rd, Ri = rng.normal(size=(m, 6)), _spd(rng, m, rng.uniform(0.1, 5)), _spd(rng, m, 0.05)
        P = Pd + Pi
        prior = float(np.trace(P[np.ix_(IDX, IDX)]))
        f = _trace_fn(Pd, Pi, H, Rd, Ri, IDX)
        ci_gain = prior - f(best_omega(Pd, Pi, H, Rd, Ri, IDX))
        assert naive_gain(P, H, Rd + Ri, IDX) >= ci_gain - 1e-9 * prior
        for min_gain in (0.01, 0.1, 0.3):
            dx, Pp, Pip, res = split_ci_update(P, Pi, Measurement(np.zeros(m), H, Ri, "r"), Rd, IDX,
                                               min_gain=min_gain)
            assert res.skipped == (ci_gain < min_gain * prior)
            skipped += res.skipped
            if res.skipped:  # nothing applied, and the result says so
                assert Pp is P and Pip is Pi and not dx.any() and not res.dx.any()
                assert not res.accepted and res.dof == m and res.name == "r" and res.gain is None
                assert np.isnan(res.nis) and res.dx.shape == (6,)
            else:
                assert res.accepted and res.gain.shape == (6, m) and 0.0 < res.omega < 1.0
    assert 0 < skipped < 600  # both outcomes occur


@pytest.mark.slow
def test_the_exact_scalar_screen_agrees_with_a_dense_search_over_omega() -> None:
    """For a scalar measurement the screen decides "does some ω gain more than T" in closed form
    (a cubic's maximum); a dense grid over ω must agree wherever the grid's best is clearly on
    one side of T, including the common case where every ω loses (the best is ω → 1)."""
    from slcp.agent.nav.fusion import OMEGA_MAX, OMEGA_MIN, _scalar_terms, _scalar_trace_fn, scalar_gain_exceeds

    rng = np.random.default_rng(11)
    grid = np.concatenate([np.geomspace(OMEGA_MIN, 0.5, 4000), 1.0 - np.geomspace(0.5, 1.0 - OMEGA_MAX, 4000)])
    outcomes = set()
    for _ in range(300):
        scale = 10.0 ** rng.uniform(-3, 1, 2)
        Pd, Pi = _spd(rng, 6, scale[0]), _spd(rng, 6, scale[1])
        H = rng.normal(size=(1, 6))
        Rd, Ri = np.array([[10.0 ** rng.uniform(-2, 2)]]), np.array([[10.0 ** rng.uniform(-3, 0)]])
        terms = _scalar_terms(Pd, Pi, H, Rd, Ri, IDX)
        f = _scalar_trace_fn(terms)
        prior = terms[0] + terms[1]
        best = prior - min(f(w) for w in grid)
        for frac in (-0.01, 1e-4, 0.01, 0.1):
            T = frac * prior
            if abs(best - T) < 1e-6 * prior:
                continue  # too close to call on a grid
            assert scalar_gain_exceeds(terms, T) == (best > T)
            outcomes.add(best > T)
    assert outcomes == {True, False}


@pytest.mark.parametrize("unshared", [False, True])
def test_unshared_states_stay_out_of_the_inflation(unshared: bool) -> None:
    """Repeated split-CI ranges in the horizontal inflate the dependent part of every state by
    1/ω, the vertical channel included, which no range observes and nothing shrinks; declared
    unshared, the vertical keeps its variance."""
    from slcp.agent.nav.error_model import ImuNoise
    from slcp.agent.nav.ins_filter import InsFilter

    from conftest import moving_state

    rng = np.random.default_rng(7)
    A = rng.normal(size=(15, 15))
    P0 = A @ A.T / 15 + np.eye(15)
    flt = InsFilter(moving_state(), P0.copy(), ImuNoise(1e-4, 1e-3, 1e-5, 3600.0, 1e-3, 3600.0), t=0.0)
    flt.track_independent(dependent=0.5 * P0, unshared=(5, 8) if unshared else ())
    H = np.zeros((1, 15))
    H[0, 6:8] = (0.6, 0.8)  # a horizontal line of sight on the position
    for _ in range(20):
        flt.update_split_ci(Measurement(np.zeros(1), H, np.array([[0.01]])), np.array([[0.5]]))
    if unshared:
        assert flt.P[8, 8] <= P0[8, 8] + 1e-9 and flt.P[5, 5] <= P0[5, 5] + 1e-9
    else:
        assert flt.P[8, 8] > 1.1 * P0[8, 8]
    # the independent part stays a part: P − P_ind ⪰ 0
    assert np.linalg.eigvalsh(flt.P - flt.P_ind).min() > -1e-9


def test_a_gated_split_ci_update_changes_nothing_and_says_why() -> None:
    """A range far outside its χ² gate: the priors come back unchanged, with the NIS that
    rejected it, its dimension and name, and the ω it was weighed with."""
    rng = np.random.default_rng(3)
    Pd, Pi = _spd(rng, 6, 1.0), _spd(rng, 6, 0.5)
    P = Pd + Pi
    H, Rd, Ri = rng.normal(size=(1, 6)), np.array([[0.5]]), np.array([[0.01]])
    dx, Pp, Pip, res = split_ci_update(P, Pi, Measurement(np.array([1e3]), H, Ri, "range"), Rd, IDX,
                                       gate_probability=0.999)
    assert Pp is P and Pip is Pi and not dx.any() and not res.dx.any() and res.dx.shape == (6,)
    assert not res.accepted and res.name == "range" and res.dof == 1 and res.gain is None
    assert res.nis > 1e4 and 0.0 < res.omega < 1.0
