"""Cooperative integrity: the solution-separation test and what it does to a faulty estimate."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2
from test_methods import ORIGIN, _stopped_filter

from slcp.agent.integrity import OWN_TWIN, check_separation, separation, separation_threshold
from slcp.agent.nav.kalman import Measurement
from slcp.agent.nav.measurements.gnss import gnss_position
from slcp.geo import earth


def _offset(llh: np.ndarray, north: float, east: float) -> np.ndarray:
    rm, rn = earth.radii(float(llh[0]))
    return llh + np.array([north / (rm + llh[2]), east / ((rn + llh[2]) * math.cos(llh[0])), 0.0])


def test_separation_closed_form() -> None:
    own = np.array([ORIGIN[0], ORIGIN[1], 50.0])
    coop = _offset(own, 3.0, -4.0)
    d, nis = separation(coop, np.diag([1.0, 4.0, 9.0]), own, np.diag([3.0, 12.0, 9.0]))
    assert d == pytest.approx([3.0, -4.0], abs=1e-6)
    assert nis == pytest.approx(9.0 / 4.0 + 16.0 / 16.0, rel=1e-6)
    # correlated horizontal block: dᵀ S⁻¹ d with S the sum of the blocks
    pa, pb = np.array([[2.0, 0.5], [0.5, 1.0]]), np.array([[1.0, -0.2], [-0.2, 2.0]])
    _, nis = separation(coop, pa, own, pb)
    assert nis == pytest.approx(float(np.array([3.0, -4.0]) @ np.linalg.solve(pa + pb, [3.0, -4.0])), rel=1e-6)
    assert separation_threshold(0.05) == pytest.approx(chi2.ppf(0.95, 2))
    with pytest.raises(ValueError):
        separation_threshold(0.0)


def test_separation_of_consistent_independent_estimates_is_chi2_with_two_dof() -> None:
    rng = np.random.default_rng(7)
    truth = np.array([ORIGIN[0], ORIGIN[1], 50.0])
    pa, pb = np.array([[4.0, 1.0], [1.0, 2.0]]), np.array([[0.3, 0.0], [0.0, 0.6]])
    n, p = 20000, 0.01
    ea = rng.multivariate_normal(np.zeros(2), pa, n)
    eb = rng.multivariate_normal(np.zeros(2), pb, n)
    nis = np.array([separation(_offset(truth, *a), pa, _offset(truth, *b), pb)[1] for a, b in zip(ea, eb)])
    assert nis.mean() == pytest.approx(2.0, abs=0.06)  # σ of the mean of 20000 χ²(2): 0.014
    rate = float(np.mean(nis > separation_threshold(p)))
    assert abs(rate - p) < 4.0 * math.sqrt(p * (1 - p) / n)


def _overconfident(f, sigma: float) -> None:
    """Shrink ``f``'s horizontal position to ``sigma`` where it stands (a fault's effect)."""
    m = gnss_position(f.filter.state, f.filter.state.llh, np.diag([sigma**2, sigma**2, 1.0]))
    f.filter.update(Measurement(m.z, f.filter.full_jacobian(m.H), m.R, "fault"))


def test_a_cooperative_estimate_far_off_at_a_small_sigma_is_widened_and_recovers() -> None:
    own, approach, _, true_llh = _stopped_filter("SL-SP")
    coop, _, _, _ = _stopped_filter("SL-CP", offset_ne=(8.0, 0.5))
    assert own.stop_line(approach).accepted  # the twin stands on its stop line: 0.1 m off
    _overconfident(coop, 0.1)  # the cooperative one is 8 m off at σ 0.1 m
    var_before = np.diag(coop.position_cov)[:2].copy()
    assert check_separation(coop, own)
    assert coop.counters["integrity_resets"] == 1 and coop.counters["integrity_tests"] == 1
    d = earth.ned_offset(*coop.filter.state.llh, *own.filter.state.llh)
    # d² on the position alone and d² along (position, -GNSS error state) of each axis
    assert np.diag(coop.position_cov)[:2] == pytest.approx(var_before + 2.0 * d[:2] ** 2, rel=1e-6)
    assert not check_separation(coop, own)  # widened: the same separation is now allowed
    assert coop.stop_line(approach).accepted
    e = earth.ned_offset(*coop.filter.state.llh, *true_llh)
    assert math.hypot(e[0], e[1]) < 0.3


def test_without_the_test_the_faulty_estimate_stays_off() -> None:
    own, approach, _, true_llh = _stopped_filter("SL-SP", separation_false_alarm=None)
    coop, _, _, _ = _stopped_filter("SL-CP", offset_ne=(8.0, 0.5), separation_false_alarm=None)
    own.stop_line(approach)
    _overconfident(coop, 0.1)
    assert not check_separation(coop, own) and coop.counters["integrity_tests"] == 0
    coop.stop_line(approach)
    e = earth.ned_offset(*coop.filter.state.llh, *true_llh)
    assert math.hypot(e[0], e[1]) > 5.0  # the fix (σ 0.2 m) barely moves a σ of 0.1 m


def test_agreeing_estimates_are_left_alone() -> None:
    own, approach, _, _ = _stopped_filter("SL-SP")
    coop, _, _, _ = _stopped_filter("SL-CP")
    own.stop_line(approach)
    coop.stop_line(approach)
    cov = coop.position_cov.copy()
    assert not check_separation(coop, own)
    assert coop.counters["integrity_resets"] == 0 and coop.counters["integrity_tests"] == 1
    assert np.array_equal(coop.position_cov, cov)
    assert OWN_TWIN == {"CP": "SP", "SL-CP": "SL-SP"}


def test_the_widening_frees_the_position_from_gnss_error_states_that_took_the_fault() -> None:
    own, approach, _, true_llh = _stopped_filter("SL-SP")
    coop, _, _, _ = _stopped_filter("SL-CP", offset_ne=(8.0, 0.5))
    own.stop_line(approach)
    _overconfident(coop, 0.1)
    for _ in range(25):  # fixes at the true place: the multipath states explain the 8 m
        coop.gnss(true_llh, np.zeros(3), np.array([0.5, 0.5, 1.0]), 0.05)
    assert math.hypot(*earth.ned_offset(*coop.filter.state.llh, *true_llh)[:2]) > 6.0
    assert check_separation(coop, own)
    coop.gnss(true_llh, np.zeros(3), np.array([0.5, 0.5, 1.0]), 0.05)
    # the next fix does not pin the position where it stands: the position and the GNSS error
    # states are free to move together
    assert math.sqrt(coop.position_cov[0, 0]) > 3.0
    coop.stop_line(approach)
    assert math.hypot(*earth.ned_offset(*coop.filter.state.llh, *true_llh)[:2]) < 0.5


def test_a_lasting_disagreement_widens_once_then_holds_until_the_two_agree() -> None:
    """The twin may be the faulty one: a disagreement widens the cooperative filter once."""
    own, approach, _, _ = _stopped_filter("SL-SP", offset_ne=(9.0, 0.0))
    coop, _, _, _ = _stopped_filter("SL-CP")
    _overconfident(own, 0.1)  # the twin runs away (its GNSS on an NLOS fix, a wrong claim)
    coop.stop_line(approach)  # the cooperative one is right
    assert check_separation(coop, own)
    for _ in range(5):
        _overconfident(coop, 0.1)  # its measurements bring it back where it was
        assert not check_separation(coop, own)
    assert coop.counters["integrity_resets"] == 1 and coop.counters["integrity_held"] == 5
    twin, _, _, _ = _stopped_filter("SL-SP")  # agreeing again: the latch opens
    assert not check_separation(coop, twin) and not coop.separation_fault
    assert check_separation(coop, own) and coop.counters["integrity_resets"] == 2


def test_an_agent_without_the_twin_method_warns_that_it_has_no_integrity_test(caplog) -> None:
    """SL-CP alone has nothing to be tested against: said once, at start, in the log."""
    import logging

    from slcp.agent.runtime import Agent
    from slcp.deploy.agent_configs import agent_config
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.transport.bus import InMemoryNetwork

    scn = load_scenario("paper-1")
    with caplog.at_level(logging.WARNING, logger="slcp.agent.engine"):
        Agent(agent_config(scn, "V1", methods=("SP", "SL-CP")), InMemoryNetwork().bus())
    assert [r.getMessage() for r in caplog.records] == [
        "V1: no cooperative integrity test for SL-CP: it needs SL-SP among the methods too"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="slcp.agent.engine"):
        Agent(agent_config(scn, "V1", methods=("SP", "CP", "SL-SP", "SL-CP")), InMemoryNetwork().bus())
    assert caplog.records == []
