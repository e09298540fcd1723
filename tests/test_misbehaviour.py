"""Misbehaviour detection: closed-form cases of each test, a seeded Monte-Carlo of honest beacons
and ranges that must never be flagged, the attack transforms, and attacks on a running fleet."""

from __future__ import annotations

import numpy as np
import pytest

from slcp.agent.misbehaviour import MisbehaviourDetector
from slcp.geo import earth
from slcp.hw_emulation.attacks import ATTACKS, Attack
from slcp.transport.messages import Beacon

ORIGIN = np.array([0.7, 2.0, 50.0])


def at(n: float, e: float) -> np.ndarray:
    return earth.offset_llh(ORIGIN, np.array([n, e, 0.0]))


def honest_drive(rng: np.random.Generator, det: MisbehaviourDetector, vid: str, n: int = 300, sigma: float = 2.0):
    """A neighbour driving east at 10 m/s past a receiver standing 15 m north of its path, with
    beacons (5 Hz) whose errors are a slowly varying bias within the claimed σ, and ranges (10 Hz)
    with UWB noise 0.1 m measured between the true positions. Returns the strike count."""
    cov = np.diag([sigma**2, sigma**2, 4.0])
    bias = np.zeros(2)
    own_true = np.array([15.0, 0.0])
    own_bias = rng.normal(0.0, 3.0, 2)
    strikes = 0
    for k in range(n):
        t = 0.1 * k
        truth = np.array([0.0, -150.0 + 10.0 * t])
        if k % 2 == 0:
            bias = 0.98 * bias + rng.normal(0.0, sigma * np.sqrt(1 - 0.98**2), 2)
            claimed = truth + bias
            strikes += det.beacon(vid, "CP", t, at(*claimed), np.array([0.0, 10.0, 0.0]), cov) is not None
        r = float(np.hypot(*(truth - own_true))) + rng.normal(0.0, 0.1)
        own = own_true + own_bias
        strikes += det.range(vid, t, r, at(*own), np.diag([9.0, 9.0, 9.0]), 0.1) is not None
    return strikes


def test_honest_neighbours_are_not_flagged() -> None:
    det = MisbehaviourDetector()
    rng = np.random.default_rng(1)
    strikes = sum(honest_drive(rng, det, f"V{k}") for k in range(20))  # 20 drives, 6000 ranges, 3000 beacons
    assert not det.events, det.events
    assert strikes <= 3  # 5σ-level tests: essentially never


def test_an_implausible_covariance_is_flagged_at_once_and_cleared_after_hold() -> None:
    det = MisbehaviourDetector(hold=10.0)
    assert det.beacon("V9", "CP", 1.0, at(0, 0), np.zeros(3), np.diag([1e-4, 1e-4, 1e-4])) == "covariance"
    assert det.excluded("V9", 1.0) and det.flagged["V9"][1] == "implausible covariance"
    assert det.excluded("V9", 10.9) and not det.excluded("V9", 11.1)
    assert det.counters["cleared"] == 1
    # not positive semi-definite
    assert det.beacon("V8", "CP", 1.0, at(0, 0), np.zeros(3), np.diag([4.0, -1.0, 1.0])) == "covariance"


def test_position_jumps_the_velocity_cannot_explain_are_flagged_after_three_strikes() -> None:
    det = MisbehaviourDetector()
    cov = np.diag([1.0, 1.0, 1.0])
    det.beacon("V9", "CP", 0.0, at(0, 0), np.array([0.0, 10.0, 0.0]), cov)
    det.beacon("V9", "CP", 0.2, at(0, 2), np.array([0.0, 10.0, 0.0]), cov)  # 10 m/s east: consistent
    assert not det.events
    for k, jump in enumerate((40.0, -30.0, 55.0)):
        det.beacon("V9", "CP", 0.4 + 0.2 * k, at(jump, 4 + 2 * k), np.array([0.0, 10.0, 0.0]), cov)
    assert det.excluded("V9", 0.8) and det.flagged["V9"][1] == "motion inconsistent"
    assert det.counters["motion_strikes"] == 3


def test_a_velocity_change_no_vehicle_can_make_is_a_strike() -> None:
    det = MisbehaviourDetector(max_accel=10.0, velocity_step=1.0)
    cov = np.diag([1.0, 1.0, 1.0])
    det.beacon("V9", "CP", 0.0, at(0, 0), np.array([0.0, 10.0, 0.0]), cov)
    # braking at 5 m/s² (a hard but ordinary stop): fine
    assert det.beacon("V9", "CP", 0.2, at(0, 1.9), np.array([0.0, 9.0, 0.0]), cov) is None
    # from 9 m/s to standing still within 0.2 s (45 m/s²): the eventual-stop signature
    assert det.beacon("V9", "CP", 0.4, at(0, 2.8), np.zeros(3), cov) == "acceleration"
    assert det.counters["acceleration_strikes"] == 1 and not det.flagged  # one strike alone flags nobody


def test_a_claimed_position_off_the_measured_range_is_flagged() -> None:
    det = MisbehaviourDetector()
    cov = np.diag([0.25, 0.25, 1.0])
    for k in range(10):
        t = 0.1 * k
        if k % 2 == 0:
            det.beacon("V9", "CP", t, at(60.0, 0.0), np.zeros(3), cov)  # claims 60 m north of me
        det.range("V9", t, 20.0, at(0.0, 0.0), np.diag([0.25, 0.25, 1.0]), 0.1)  # measured: 20 m
    assert det.excluded("V9", 0.9) and det.flagged["V9"][1] == "range inconsistent"
    assert det.counters["range_strikes"] == 10  # every range of the ten counted, not just the last
    # an NLOS-length excess (a longer range, within the allowance) is no evidence
    det2 = MisbehaviourDetector(nlos_bias=3.0)
    det2.beacon("V9", "CP", 0.0, at(20.0, 0.0), np.zeros(3), cov)
    assert det2.range("V9", 0.0, 22.9, at(0.0, 0.0), np.diag([0.25, 0.25, 1.0]), 0.1) is None


def test_the_range_test_weighs_both_covariances_at_its_threshold() -> None:
    """Near its 10σ threshold: σ² = σ_uwb² + uᵀ(P_own + P_nb)u along the line of sight. A
    receiver whose own estimate is uncertain along the line (4 m²) accepts a 15 m short range
    that the neighbour's claim (0.25 m²) alone would fail, and fails one 10% beyond 10σ; the
    same with the roles swapped; the cross-track variance does not count."""
    sig = 0.1
    for own, nb in (((4.0, 0.25), (0.25, 0.25)), ((0.25, 0.25), (4.0, 0.25))):
        var = sig**2 + own[0] + nb[0]  # the neighbour is due north: u = (1, 0, 0)
        k10 = 10.0 * np.sqrt(var)
        for resid, expect in ((-0.9 * k10, None), (-1.1 * k10, "range")):
            det = MisbehaviourDetector()
            det.beacon("V9", "CP", 0.0, at(40.0, 0.0), np.zeros(3), np.diag([nb[0], 100.0, 1.0]))
            got = det.range("V9", 0.0, 40.0 + resid, at(0.0, 0.0), np.diag([own[0], 50.0, 1.0]), sig)
            assert got == expect, (own, nb, resid)
    # a positive residual is allowed the NLOS bias first: 10σ + nlos_bias passes, beyond it fails
    var = sig**2 + 0.5
    for excess, expect in ((3.0 + 9.9 * np.sqrt(var), None), (3.0 + 10.1 * np.sqrt(var), "range")):
        det = MisbehaviourDetector(nlos_bias=3.0)
        det.beacon("V9", "CP", 0.0, at(40.0, 0.0), np.zeros(3), np.diag([0.25, 1.0, 1.0]))
        assert det.range("V9", 0.0, 40.0 + excess, at(0.0, 0.0), np.diag([0.25, 1.0, 1.0]), sig) == expect


@pytest.mark.parametrize("cov, flagged", [
    (np.diag([1.0, 1.0, 1.0]), False),
    (np.array([[1.0, 0.99, 0], [0.99, 1.0, 0], [0, 0, 1.0]]), False),  # smallest eigenvalue 0.01 m²
    (np.array([[1.0, 0.999, 0], [0.999, 1.0, 0], [0, 0, 1.0]]), True),  # 0.001 m² < 0.05² m²
    (np.array([[1.0, 0.9985, 0], [0.9985, 1.0, 0], [0, 0, 1.0]]), True),  # 0.0015 m²: σ 3.9 cm
    (np.array([[1.0, 0.997, 0], [0.997, 1.0, 0], [0, 0, 1.0]]), False),  # 0.003 m²: σ 5.5 cm
    (np.array([[4.0, 1.99, 0], [2.01, 1.0, 0], [0, 0, 1.0]]), True),  # an asymmetric block: its symmetric part
    (np.array([[0.0026, 0, 0], [0, 9.0, 0], [0, 0, 1.0]]), False),
    (np.array([[9.0, 0, 0], [0, 0.0024, 0], [0, 0, 1.0]]), True),
    (np.array([[1.0, 2.0, 0], [2.0, 1.0, 0], [0, 0, 1.0]]), True),  # not positive semi-definite
    (np.array([[np.nan, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]), True),
])
def test_the_covariance_test_is_on_the_smallest_horizontal_eigenvalue(cov, flagged: bool) -> None:
    """σ_min of the horizontal block against ``min_sigma`` (5 cm), checked against numpy's
    eigenvalues: a thin ellipse is as implausible as a small circle, whatever its diagonal."""
    sym = 0.5 * (cov[:2, :2] + cov[:2, :2].T)
    lam = np.linalg.eigvalsh(sym)[0] if np.isfinite(sym).all() else np.nan
    assert flagged == (not lam >= 0.05**2)  # the cases are on the side of the threshold they say
    det = MisbehaviourDetector()
    got = det.beacon("V9", "CP", 0.0, ORIGIN, np.zeros(3), cov)
    assert (got == "covariance") == flagged
    assert det.excluded("V9", 0.0) == flagged


@pytest.mark.parametrize("rate_test", [False, True])
def test_a_range_jump_the_claims_do_not_show_fails_the_range_rate_test(rate_test: bool) -> None:
    """A range that jumps by 7 m within half a second while the claimed distance stays (and
    other beacon streams keep coming) is within the absolute test's bound (my own σ is 3 m) but
    not the range-rate test's; the test runs only when enabled."""
    det = MisbehaviourDetector(rate_test=rate_test)
    cov = np.diag([1.0, 1.0, 4.0])
    own_cov = np.diag([9.0, 9.0, 9.0])
    for k in range(10):
        t = 0.1 * k
        if k % 2 == 0:
            for stream in ("CP", "SL-CP"):  # two streams: the history is kept per neighbour
                det.beacon("V9", stream, t, at(20.0, 0.0), np.zeros(3), cov)
        assert det.range("V9", t, 20.0 + 0.05 * (-1) ** k, at(0.0, 0.0), own_cov, 0.1) is None
    out = det.range("V9", 1.0, 27.0, at(0.0, 0.0), own_cov, 0.1)
    assert out == ("range rate" if rate_test else None)


@pytest.mark.parametrize("kind", ATTACKS)
def test_each_attack_changes_the_beacon_as_veremi_defines_it(kind) -> None:
    rng = np.random.default_rng(0)
    b = Beacon("V2", 1, "CP", 10.0, at(5.0, 5.0), np.array([0.0, 8.0, 0.0]), np.diag([4.0, 4.0, 9.0]))
    a = Attack("V2", kind, start=10.0)
    assert Attack("V2", kind, start=11.0).apply(b, ORIGIN, rng) is b  # before the start
    assert a.apply(Beacon("V1", *list(vars(b).values())[1:]), ORIGIN, rng).vehicle == "V1"
    f1, f2 = a.apply(b, ORIGIN, rng), a.apply(b, ORIGIN, rng)
    moved = lambda f: float(np.hypot(*earth.ned_offset(*f.llh, *b.llh)[:2]))  # noqa: E731
    if kind == "overconfident":
        assert np.allclose(f1.cov_pos, b.cov_pos * 1e-4) and moved(f1) == 0.0
    elif kind == "constant_offset":
        assert moved(f1) == pytest.approx(np.hypot(250.0, 150.0), rel=1e-6) and moved(f2) == pytest.approx(moved(f1))
    elif kind == "random_offset":
        assert 0 < moved(f1) <= 70 * np.sqrt(2) and moved(f1) != pytest.approx(moved(f2))
    elif kind == "random_position":
        assert not np.allclose(f1.llh, f2.llh)
    elif kind == "constant_position":
        assert np.allclose(f1.llh, f2.llh) and moved(f1) > 0
    else:  # eventual stop: frozen where it was, standing
        assert np.allclose(f1.llh, b.llh) and np.all(f1.v_ned == 0.0)
    with pytest.raises(ValueError, match="unknown attack"):
        Attack("V2", "teleport", 1.0)
    assert Attack.parse("V2:random_offset@12.5") == Attack("V2", "random_offset", 12.5)
    with pytest.raises(ValueError, match="VEHICLE:KIND@START_S"):
        Attack.parse("V2-random_offset")


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("kind", ["constant_offset", "random_position", "overconfident"])
def test_attacks_on_a_running_fleet_are_detected_within_a_second(kind) -> None:
    from slcp.deploy.attack_eval import evaluate_attack

    run = evaluate_attack("paper-1", kind, seed=2, after=2.0)
    print(kind, run["attacker"], run["start_s"], run["receivers"])
    assert run["receivers"], "nobody heard the attacker"
    for v, r in run["receivers"].items():
        assert r["detected"], (v, r)
    assert run["honest_excluded"] == 0 and run["honest_beacons"] > 100


def test_the_motion_tests_in_closed_form() -> None:
    """The sudden-stop test allows a braking of ``max_accel dt + velocity_step``; the motion χ²
    weighs both axes with the acceleration allowance and the covariances' correlation: the
    same 1.2 m mismatch fails across a thin, correlated ellipse and passes along it."""
    cov = np.diag([0.003, 0.003, 1.0])  # σ 5.5 cm: the acceleration allowance (0.12 m) dominates
    still, fast = np.zeros(3), np.array([3.1, 0.0, 0.0])
    det = MisbehaviourDetector()
    det.beacon("V9", "CP", 0.0, at(0.0, 0.0), fast, cov)
    # 3.1 -> 0.2 m/s in 0.2 s: 2.9 m/s below the 10·0.2 + 1 = 3 m/s allowed
    assert det.beacon("V9", "CP", 0.2, at(0.33, 0.0), np.array([0.2, 0.0, 0.0]), cov) is None
    det = MisbehaviourDetector()
    det.beacon("V9", "CP", 0.0, at(0.0, 0.0), np.array([3.2, 0.0, 0.0]), cov)
    assert det.beacon("V9", "CP", 0.2, at(0.33, 0.0), np.array([0.1, 0.0, 0.0]), cov) == "acceleration"  # 3.1 m/s
    # a 5 m jump east of where a standing vehicle was, with small covariances: a motion strike
    det = MisbehaviourDetector()
    det.beacon("V9", "CP", 0.0, at(0.0, 0.0), still, cov)
    assert det.beacon("V9", "CP", 0.2, at(0.0, 5.0), still, cov) == "motion"
    assert det.beacon("V9", "CP", 0.4, at(0.0, 5.0), still, cov) is None
    # 0.5 m off per axis in 0.2 s: inside the allowance (χ² 12 per axis), outside without it (42)
    for d in ((0.5, 5.0), (0.0, 5.5)):
        assert det.beacon("V9", "CP", 0.6 + 0.2 * (d[1] == 5.5), at(*d), still, cov) is None, d
    # correlated covariances (ρ = 0.98): thin across (1, -1), long along (1, 1)
    corr = np.array([[1.0, 0.98, 0.0], [0.98, 1.0, 0.0], [0.0, 0.0, 1.0]]) * 0.5
    for d, expect in (((0.85, 0.85), None), ((0.85, -0.85), "motion")):
        det = MisbehaviourDetector()
        det.beacon("V9", "CP", 0.0, at(0.0, 0.0), still, corr)
        assert det.beacon("V9", "CP", 0.2, at(*d), still, corr) == expect, d


def test_the_range_rate_test_waits_for_a_reference_old_enough() -> None:
    """The rate test compares with a range at least ``rate_window[0]`` old: a 9 m jump 0.1 s into
    a neighbour's ranges has no reference yet (the absolute test, 10σ of 3.2 m, passes it); the
    same jump 0.5 s in fails."""
    cov, own_cov = np.diag([1.0, 1.0, 4.0]), np.diag([9.0, 9.0, 9.0])
    t0 = 30.0  # ages are differences of sensor times
    for late, want in ((False, None), (True, "range rate")):
        det = MisbehaviourDetector(rate_test=True)
        det.beacon("V9", "CP", t0, at(20.0, 0.0), np.zeros(3), cov)
        assert det.range("V9", t0, 20.0, at(0.0, 0.0), own_cov, 0.1) is None
        t = t0 + (0.5 if late else 0.1)
        det.beacon("V9", "CP", t - 0.05, at(20.0, 0.0), np.zeros(3), cov)
        assert det.range("V9", t, 29.0, at(0.0, 0.0), own_cov, 0.1) == want, late


def test_a_switch_of_reference_stream_starts_the_range_history_afresh() -> None:
    """Ranges are checked against one stream per neighbour, CP once it is heard. The distances
    kept for the rate test belong to the old stream (here SL-CP, 8 m off CP's claim, both within
    their σ): after the switch they are dropped, and the first CP range is no range-rate jump."""
    cov, own_cov = np.diag([9.0, 9.0, 4.0]), np.diag([9.0, 9.0, 9.0])
    det = MisbehaviourDetector(rate_test=True)
    for k in range(6):
        t = 0.1 * k
        det.beacon("V9", "SL-CP", t, at(20.0, 0.0), np.zeros(3), cov)
        assert det.range("V9", t, 20.0, at(0.0, 0.0), own_cov, 0.1) is None
    det.beacon("V9", "CP", 0.6, at(28.0, 0.0), np.zeros(3), cov)
    assert det.range("V9", 0.6, 20.0, at(0.0, 0.0), own_cov, 0.1) is None
    assert det.counters["range_strikes"] == 0


@pytest.mark.parametrize("times, flagged", [((0.0, 0.5, 1.0), True), ((0.0, 0.5, 1.25), False)])
def test_three_strikes_within_the_window_ends_included_flag(times, flagged: bool) -> None:
    """``strikes`` failed tests within ``window`` s flag a neighbour: three strikes spanning
    exactly the window (1 s; times exact in binary) do, three spanning more do not."""
    det = MisbehaviourDetector()
    cov = np.diag([1.0, 1.0, 1.0])
    for t in times:
        det.beacon("V9", "CP", t, at(20.0, 0.0), np.zeros(3), cov)
        assert det.range("V9", t, 60.0, at(0.0, 0.0), 0.01 * cov, 0.1) == "range"
    assert det.excluded("V9", times[-1]) == flagged


def test_the_range_rate_reference_may_be_exactly_the_window_old() -> None:
    """References for the range-rate test are kept up to ``rate_window[1]`` (1 s) old, that age
    included: against the range of exactly 1 s ago the 10 m step fails (threshold 3 + 5 σ, σ
    0.72 m over 1 s); against the half-second-old one it would pass (5 m, threshold 5.9 m)."""
    det = MisbehaviourDetector(rate_test=True)
    cov, own = np.diag([1.0, 1.0, 1.0]), np.diag([9.0, 9.0, 9.0])
    for t, resid in ((0.0, 0.0), (0.5, 5.0)):
        det.beacon("V9", "CP", t, at(20.0, 0.0), np.zeros(3), cov)
        assert det.range("V9", t, 20.0 + resid, at(0.0, 0.0), own, 0.1) is None
    det.beacon("V9", "CP", 1.0, at(20.0, 0.0), np.zeros(3), cov)
    assert det.range("V9", 1.0, 30.0, at(0.0, 0.0), own, 0.1) == "range rate"


@pytest.mark.parametrize("v0, strike", [(3.0, None), (3.25, "acceleration")])
def test_the_sudden_stop_test_applies_from_above_stop_from(v0: float, strike) -> None:
    """From above ``stop_from`` (3 m/s) to standing within 0.125 s: a strike; from exactly
    3 m/s, not (speeds exact in binary; the drop beats max_accel dt + step = 2.25 m/s both times)."""
    det = MisbehaviourDetector(max_accel=10.0, velocity_step=1.0)
    cov = np.diag([1.0, 1.0, 1.0])
    det.beacon("V9", "CP", 0.0, at(0, 0), np.array([0.0, v0, 0.0]), cov)
    assert det.beacon("V9", "CP", 0.125, at(0, v0 * 0.0625), np.zeros(3), cov) == strike


def test_a_moving_claim_is_judged_where_its_velocity_takes_it() -> None:
    """A neighbour driving at (30, 10, 2) m/s NED. Its next beacon 0.2 s later and a range 0.25
    s after a beacon are judged at the point its velocity takes it, on the ellipsoid's curvature:
    the truth here is pymap3d's exact conversion, not the detector's first-order formulas. Each
    check straddles its threshold by 1 % (the motion χ² along either axis, the range's 10σ), so
    a sign, an axis or a radius of curvature wrong in either check shows (north: R_M, not R_N,
    6 m in 0.2 s, makes 2 cm)."""
    import pymap3d

    v = np.array([30.0, 10.0, 2.0])
    dt, tau, sig = 0.2, 0.25, 0.1

    def ned(d: np.ndarray, ref: np.ndarray = ORIGIN) -> np.ndarray:
        return np.array(pymap3d.ned2geodetic(*d, *ref, deg=False))

    cov = np.diag([0.003, 0.003, 1.0])
    s = 2 * 0.003 + (0.5 * MisbehaviourDetector().accel * dt * dt) ** 2  # per axis: diagonal S
    for axis in (0, 1):
        for scale, expect in ((0.99, None), (1.01, "motion")):
            off = np.zeros(3)
            off[axis] = np.sqrt(MisbehaviourDetector().motion_chi2 * s * scale)
            det = MisbehaviourDetector()
            det.beacon("V9", "CP", 0.0, ORIGIN, v, cov)
            assert det.beacon("V9", "CP", dt, ned(v * dt + off), v, cov) == expect, (axis, scale)
    # the range: the receiver 30 m south, 40 m west and 10 m below where the neighbour is at tau
    there = ned(v * tau)
    own = ned(np.array([-30.0, -40.0, 10.0]), there)
    dist = float(np.linalg.norm(np.subtract(pymap3d.geodetic2ecef(*there, deg=False),
                                            pymap3d.geodetic2ecef(*own, deg=False))))
    k10 = 10.0 * np.sqrt(sig**2 + 0.04 + 0.01)  # isotropic covariances: any line of sight
    for scale, expect in ((0.99, None), (1.01, "range")):
        det = MisbehaviourDetector()
        det.beacon("V9", "CP", 0.0, ORIGIN, v, np.diag([0.01, 0.01, 0.01]))
        assert det.range("V9", tau, dist - scale * k10, own, np.diag([0.04, 0.04, 0.04]), sig) == expect, scale
