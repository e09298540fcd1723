"""The four methods as pure filters: what each fuses, and the stop-line and range updates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.agent.methods import METHODS, FilterSettings, MethodFilter, MethodSpec, initial_state
from slcp.agent.nav.measurements.stop_line import Line2D, StopGapModel, StopLineApproach, stop_line_position
from slcp.agent.nav.rotation import quat_to_euler
from slcp.agent.neighbours import NeighbourState
from slcp.geo import earth

from conftest import MEMS_NOISE

ORIGIN = (math.radians(39.95), math.radians(116.32), 50.0)


def test_method_specs() -> None:
    assert [(m.stop_line, m.ranges) for m in map(MethodSpec.of, METHODS)] == [
        (False, False), (True, False), (False, True), (True, True)]
    with pytest.raises(ValueError, match="unknown method"):
        MethodSpec.of("XP")


def _stopped_filter(
    method: str, offset_ne=(3.0, -2.0), **settings
) -> tuple[MethodFilter, StopLineApproach, StopGapModel, np.ndarray]:
    approach = StopLineApproach(Line2D((0.0, 0.0), (0.0, 1.0)), Line2D((0.0, -1.75), (1.0, 0.0)))  # north-bound
    gap = StopGapModel(1.5, 0.2, 1.75, 0.1, 2.5)
    p_true, _ = stop_line_position(approach, gap)
    rm, rn = earth.radii(ORIGIN[0])
    true_llh = np.array(
        [ORIGIN[0] + p_true[0] / (rm + 50), ORIGIN[1] + p_true[1] / ((rn + 50) * math.cos(ORIGIN[0])), 50.0]
    )
    est_llh = true_llh + np.array([offset_ne[0] / (rm + 50), offset_ne[1] / ((rn + 50) * math.cos(ORIGIN[0])), 0.0])
    st = initial_state(est_llh, np.zeros(3), np.array([0.0, 0.0, -9.8]))
    f = MethodFilter(
        MethodSpec.of(method), st, np.array([4.0, 4.0, 6.0]), FilterSettings(MEMS_NOISE, **settings), 0.0, gap, ORIGIN
    )
    return f, approach, gap, true_llh


def test_stop_line_fix_pulls_a_stopped_vehicle_onto_its_place() -> None:
    f, approach, _, true_llh = _stopped_filter("SL-SP")
    assert f.stop_line(approach).accepted
    e = earth.ned_offset(*f.filter.state.llh, *true_llh)
    sig = np.sqrt(np.diag(f.filter.position_cov))
    # prior 4 m, fix σ 0.2/0.1 m: the posterior sits within a few σ_fix of the true place
    assert math.hypot(e[0], e[1]) < 0.1 and sig[0] < 0.25 and sig[1] < 0.15
    assert f.stop_line(approach) is None  # rate-limited
    sp, approach, _, _ = _stopped_filter("SP")
    assert sp.stop_line(approach) is None  # SP never uses it


def test_range_update_and_gates() -> None:
    f, _, _, true_llh = _stopped_filter("CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0)
    rm, _ = earth.radii(ORIGIN[0])
    nb = NeighbourState("V2", true_llh + np.array([-7.0 / (rm + 50), 0.0, 0.0]), np.eye(3) * 0.01, 0.05)
    assert f.range(nb, 7.0) == "fused" and f.counters["ranges"] == 1
    assert f.range(nb, 500.0) == "gate_physical"
    assert f.range(nb, 37.0) == "gate_rate"  # a 30 m jump that two standing cars cannot make
    assert f.counters["ranges_rejected"] == 2
    fresh, _, _, _ = _stopped_filter("CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0)
    assert fresh.range(nb, 37.0) == "gate_nis"  # no range track yet: the χ² gate catches it
    sp, _, _, _ = _stopped_filter("SP")
    assert sp.range(nb, 7.0) is None


def test_a_range_too_near_for_the_linearisation_waits() -> None:
    """σ 4 m across the line of sight: at 7 m the estimated direction is meaningless, so the
    range is not fused (nor counted as rejected); at 30 m (7.5 σ) it is."""
    rm, _ = earth.radii(ORIGIN[0])
    for dist, outcome in ((7.0, "skipped_near"), (30.0, "fused")):
        f, _, _, true_llh = _stopped_filter("CP", offset_ne=(0.0, 0.0))
        nb = NeighbourState("V2", true_llh + np.array([-dist / (rm + 50), 0.0, 0.0]), np.eye(3) * 0.01, 0.05)
        assert f.range(nb, dist) == outcome
        assert f.counters["ranges_rejected"] == 0
    assert f.counters["ranges"] == 1
    near, _, _, _ = _stopped_filter("CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0)
    assert near.range(NeighbourState("V2", true_llh + np.array([-7.0 / (rm + 50), 0.0, 0.0]), np.eye(3) * 0.01, 0.05),
                      7.0) == "fused"


def test_range_rate_gate_follows_motion_and_restarts() -> None:
    from slcp.agent.range_gate import RangeRateGate

    g = RangeRateGate()
    assert g.check("B", 0.0, 20.0, -5.0)
    assert g.check("B", 0.1, 19.5, -5.0)        # closing at 5 m/s: as predicted
    assert not g.check("B", 0.2, 24.0, -5.0)    # an isolated 5 m jump
    assert g.check("B", 0.3, 18.5, -5.0)        # back on the track
    assert not g.check("B", 0.4, 20.0, -5.0)    # a 2 m NLOS bias starts: one range lost...
    assert g.check("B", 0.5, 19.5, -5.0)        # ...then the new level is followed
    assert g.check("B", 5.0, 60.0, 0.0)         # after a long gap the track restarts



def test_range_rate_gate_width_in_closed_form_and_forget() -> None:
    """The gate at elapsed time dt is ``max_jump + k σ_rate dt`` around the predicted range,
    both edges inclusive; the track keeps to the neighbour; ``forget`` starts it anew."""
    from slcp.agent.range_gate import RangeRateGate

    g = RangeRateGate(max_jump=0.5, sigma_rate=0.4, k=3.0, max_gap=2.0)
    width = 0.5 + 3.0 * 0.4 * 0.25  # 0.8 m after 0.25 s
    for edge, ok in ((width - 1e-9, True), (width + 1e-6, False), (-width + 1e-9, True), (-width - 1e-6, False)):
        g = RangeRateGate(max_jump=0.5, sigma_rate=0.4, k=3.0, max_gap=2.0)
        assert g.check("B", 10.0, 30.0, 2.0)
        assert g.check("B", 10.25, 30.5 + edge, 2.0) == ok, edge  # predicted 30.5 m
    g = RangeRateGate(max_jump=0.5, sigma_rate=0.4, k=3.0, max_gap=2.0)
    assert g.check("B", 0.0, 30.0, 0.0) and g.check("C", 0.0, 80.0, 0.0)  # one track per neighbour
    assert g.check("B", 1.99, 30.0 + 0.5 + 3.0 * 0.4 * 1.99 - 1e-6, 0.0)  # within max_gap: extrapolated
    assert not g.check("C", 0.1, 90.0, 0.0)
    g.forget("C")
    assert g.check("C", 0.2, 90.0, 0.0)  # a new track: anything goes
    assert not g.check("C", 0.3, 95.0, 0.0)


def test_a_forgotten_neighbour_leaves_no_state_in_the_misbehaviour_detector() -> None:
    """After ``forget`` (the neighbour left), a range is not checked against its old claim, and
    its next beacon starts a new motion history instead of being compared with the old one."""
    from slcp.agent.misbehaviour import MisbehaviourDetector
    from slcp.geo import earth

    o = np.array([0.7, 2.0, 50.0])
    cov = np.diag([0.25, 0.25, 1.0])
    det = MisbehaviourDetector()
    assert det.beacon("V9", "CP", 0.0, earth.offset_llh(o, np.array([60.0, 0.0, 0.0])), np.zeros(3), cov) is None
    assert det.range("V9", 0.1, 20.0, o, cov, 0.1) == "range"  # 60 m claimed, 20 m measured
    det.forget("V9")
    assert det.range("V9", 0.2, 20.0, o, cov, 0.1) is None  # nothing to check against
    # a beacon 500 m away 0.2 s later would fail the motion test against the old one
    far = earth.offset_llh(o, np.array([500.0, 0.0, 0.0]))
    assert det.beacon("V9", "CP", 0.4, far, np.zeros(3), cov) is None
    det2 = MisbehaviourDetector()
    det2.beacon("V9", "CP", 0.0, earth.offset_llh(o, np.array([60.0, 0.0, 0.0])), np.zeros(3), cov)
    assert det2.beacon("V9", "CP", 0.2, far, np.zeros(3), cov) == "motion"

def test_displacement_since_interpolates_the_recent_history() -> None:
    """The INS displacement since a past time equals the displacement accumulated since then,
    linearly interpolated in the 20 Hz history (checked against np.interp), zero outside it."""
    f, _, _, _ = _stopped_filter("CP")
    f.filter.state.v[:] = [3.0, -1.0, 0.2]
    t0 = f.t
    dth, dv = [0.0, 0.0, 0.0], [0.0, 0.0, -9.80665 * 0.01]  # specific force of a level body
    for _ in range(150):
        f.propagate(dth, dv, 0.01)
    hist = list(f._disp_hist)
    ts = [h[0] for h in hist]
    for t in (t0 - 0.1, t0, t0 + 0.333, t0 + 1.0, ts[-1] + 0.004, f.t, f.t + 1):
        got = f.displacement_since(t)
        if t < t0 or t >= f.t:
            assert np.array_equal(got, np.zeros(3))
            continue
        past = np.array([np.interp(t, ts, [h[k] for h in hist]) for k in (1, 2, 3)])
        assert np.allclose(got, np.array(f._disp) - past, atol=1e-12)
    # the vehicle moved about v·Δt (its velocity barely changes over 1.5 s of level coasting)
    assert np.allclose(
        f.displacement_since(t0 + 0.5)[:2], f.filter.state.v[:2] * (f.t - t0 - 0.5), rtol=0.05, atol=0.05
    )


def test_a_gnss_jump_is_rejected_and_a_fix_rejected_for_long_re_anchors_the_position() -> None:
    """A standing vehicle with fixes at the truth, then a 30 m NLOS jump: the χ² gate rejects
    it; if the jump lasts longer than ``gnss_reset_after``, the filter re-anchors on it (the
    right call when it was the filter that was wrong), and the counters say so."""
    f, _, _, true_llh = _stopped_filter("SP", offset_ne=(0.0, 0.0), gnss_gate=0.999)
    rm, _ = earth.radii(ORIGIN[0])
    jump = true_llh + np.array([30.0 / (rm + 50), 0.0, 0.0])
    zero, dt = np.zeros(3), 0.01
    g = np.array([0.0, 0.0, -earth.gravity(ORIGIN[0], 50.0)]) * dt

    def run(llh, seconds):
        for _k in range(int(round(seconds / 0.2))):
            for _ in range(20):
                f.propagate(zero, g, dt)
            f.gnss(llh, np.zeros(3), np.full(3, 0.5), 0.05)

    run(true_llh, 10.0)
    run(jump, 10.0)
    e = earth.ned_offset(*f.filter.state.llh, *true_llh)
    assert math.hypot(e[0], e[1]) < 1.5 and f.counters["gnss_rejected"] == 50 and f.counters["gnss_reanchored"] == 0
    run(jump, f.settings.gnss_reset_after)
    e = earth.ned_offset(*f.filter.state.llh, *jump)
    assert math.hypot(e[0], e[1]) < 1.5 and f.counters["gnss_reanchored"] == 1
    assert f.filter.position_cov[0, 0] < 9.0  # and it is sure of it again after a few fixes


def test_ranges_to_a_vague_neighbour_do_not_sharpen_a_stop_line_fix() -> None:
    """A first stopped vehicle re-fixing itself on its stop line (SL-CP, split CI) ranges at
    10 Hz to a neighbour 7 m behind whose beacon is only good to 3 m. The joint bound says the
    ranges can tell it next to nothing; its σ must not drop below that of the same vehicle
    without ranges (SL-SP). With the stop-gap states counted as independent of what the
    neighbours know, it dropped by 1-2 % within seconds (paper-1 V1, below the bound)."""
    rm, _ = earth.radii(ORIGIN[0])
    cp, approach, _, true_llh = _stopped_filter("SL-CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0, fusion="split-ci")
    sp, _, _, _ = _stopped_filter("SL-SP", offset_ne=(0.0, 0.0))
    nb = NeighbourState("V2", true_llh + np.array([-7.0 / (rm + 50), 0.0, 0.0]), np.eye(3) * 9.0, 0.05)
    zero, dt = np.zeros(3), 0.01
    g = np.array([0.0, 0.0, -earth.gravity(ORIGIN[0], 50.0)]) * dt
    for _k in range(300):  # 30 s
        for f in (cp, sp):
            for _ in range(10):
                f.propagate(zero, g, dt)
            f.stop_line(approach, stop_id=0.0)
        cp.range(nb, 7.0)
    assert cp.counters["stop_line"] >= 2 and cp.counters["ranges"] > 0
    s_cp = np.sqrt(np.trace(cp.filter.position_cov[:2, :2]))
    s_sp = np.sqrt(np.trace(sp.filter.position_cov[:2, :2]))
    assert s_cp >= 0.995 * s_sp, (s_cp, s_sp)


def test_in_a_range_to_a_vehicle_that_carries_my_own_stop_gap_error_it_cancels() -> None:
    """A follower placed from my stop-line fix carries my stop gap's error as its own: its
    beacon's sensitivity to my constants equals mine. In a range between us that error cancels,
    so the range tells me nothing about it and my sensitivity to it stays as it was (counted with
    the wrong sign, the two would add and the range would shrink it)."""
    f, approach, _, true_llh = _stopped_filter("SL-CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0,
                                               selection_hold=0.0, min_gain=0.0)
    assert f.stop_line(approach, stop_id=0.0).accepted
    mine = f.beacon_constants()
    g = np.array([c for _, c in mine])
    assert len(mine) >= 2 and np.abs(g[:, :2]).max() > 0.1  # the gap's constants move my position
    rm, _ = earth.radii(ORIGIN[0])
    cov = g.T @ g + 0.01 * np.eye(3)
    nb = NeighbourState("V2", true_llh + np.array([-7.0 / (rm + 50), 0.0, 0.0]), cov, 0.05,
                        source_labels=(frozenset({"V2"}),), source_cov=0.01 * np.eye(3)[None], constants=mine)
    before = f.filter.sources.constants[:, : len(mine)].copy()
    assert f.range(nb, 7.0) == "fused"
    np.testing.assert_allclose(f.filter.sources.constants[:, : len(mine)], before, atol=1e-9)


def test_as_consider_states_the_stop_gap_states_are_never_estimated() -> None:
    """``consider_constants``: the stop-line fix moves the position, not the gap states, whose
    error stays the stop's draw, wholly in the exact part (no own or CI share to inflate)."""
    f, approach, gap, true_llh = _stopped_filter("SL-CP", offset_ne=(1.0, -0.5), consider_constants=True)
    for _ in range(3):
        f.last_stop_line = -math.inf
        assert f.stop_line(approach, stop_id=0.0).accepted
    flt = f.filter
    k = np.arange(flt.extra_offset + f._sl.start, flt.extra_offset + f._sl.stop)
    assert np.all(flt.extra[f._sl] == 0.0)
    np.testing.assert_allclose(np.diag(flt.P)[k], [gap.sigma_xb**2, gap.sigma_yb**2])
    own = flt.sources.own(flt.P)
    assert np.abs(own[k]).max() < 1e-12 and all(np.abs(C[k]).max() < 1e-12 for C in flt.sources.parts)
    e = earth.ned_offset(*flt.state.llh, *true_llh)
    assert math.hypot(e[0], e[1]) < 0.1 and math.sqrt(flt.position_cov[0, 0]) == pytest.approx(gap.sigma_xb, rel=0.05)


@pytest.mark.parametrize("fusion", ["source-ci", "split-ci"])
def test_the_stop_gap_states_are_forgotten_when_the_stop_ends(fusion: str) -> None:
    """After a stop-line fix the gap states are correlated with the position; when the vehicle
    drives off they go back to their prior (in P and in its parts: split CI's independent one,
    source CI's components), so that no CI range can inflate them until the next stop; the
    position keeps its covariance. (Estimated gap states: ``consider_constants`` off; as consider
    states they are never correlated with the position by an update.)"""
    f, approach, gap, _ = _stopped_filter("SL-CP", offset_ne=(0.0, 0.0), fusion=fusion, consider_constants=False)
    flt = f.filter
    if fusion == "source-ci":  # some information from a neighbour, which the fix correlates too
        flt.flush_covariance()
        flt.sources.add(frozenset({"V2"}), 0.1 * flt.P)
    f.stop_line(approach, stop_id=0.0)
    k = np.arange(flt.extra_offset + f._sl.start, flt.extra_offset + f._sl.stop)
    flt.flush_covariance()
    assert np.abs(flt.P[k][:, 6:8]).max() > 1e-4  # correlated with the horizontal position
    if fusion == "source-ci":
        assert np.abs(flt.sources.parts[0][k][:, 6:8]).max() > 1e-6
    before = flt.position_cov
    f.end_stop()
    prior = np.array([gap.sigma_xb**2, gap.sigma_yb**2])
    parts = [(flt.P_ind, prior)] if fusion == "split-ci" else [(C, 0.0 * prior) for C in flt.sources.parts]
    assert len(parts) >= 1
    for P, var in [(flt.P, prior)] + parts:
        others = np.setdiff1d(np.arange(flt.n), k)
        assert np.allclose(P[np.ix_(k, others)], 0.0)
        assert np.allclose(np.diag(P)[k], var)
    assert np.allclose(flt.position_cov, before)
    assert f.stop_line(approach, stop_id=0.0).accepted  # the same stop claimed again: fixes at once


def test_a_vehicle_that_starts_standing_learns_its_heading_when_it_drives_off() -> None:
    """A vehicle stands 6 s facing east with its heading unknown (yaw 0, σ 60°), then drives
    off east at 1.5 m/s². While it stands, its yaw takes no part in the updates; the heading
    comes from the GNSS course as soon as that is good to 5°, with the velocity. Before, the
    filter turned its yaw 100° while standing, learned gyro biases of 2000 °/h, reset at
    1.5 m/s and then kept a yaw 20-40° off (rush-hour E4)."""
    rng = np.random.default_rng(3)
    rm, rn = earth.radii(ORIGIN[0])
    true_bg = np.radians([0.04, -0.03, 0.02])  # [rad/s], within the 0.05 °/s turn-on spread
    g = earth.gravity(ORIGIN[0], ORIGIN[2])
    llh0 = np.array(ORIGIN)
    st = initial_state(llh0, np.zeros(3), np.array([0.0, 0.0, -g]))
    f = MethodFilter(MethodSpec.of("SP"), st, np.array([2.0, 2.0, 3.0]),
                     FilterSettings(MEMS_NOISE, gnss_multipath_sigma=None, init_gyro_bias_sigma=math.radians(0.05)),
                     0.0, heading_known=False)
    dt, t, east, v, a = 0.01, 0.0, 0.0, 0.0, 1.5
    for k in range(1, 1201):  # 12 s
        acc = a if t >= 6.0 and v < 10.0 else 0.0
        # body x points east: forward acceleration and gravity, plus the gyro bias
        f.propagate(true_bg * dt, np.array([acc, 0.0, -g]) * dt, dt)
        east += v * dt + 0.5 * acc * dt * dt
        v += acc * dt
        t = k * dt
        if k % 20 == 0:  # GNSS at 5 Hz
            llh = np.array([ORIGIN[0] + rng.normal(0, 0.5) / (rm + ORIGIN[2]),
                            ORIGIN[1] + (east + rng.normal(0, 0.5)) / ((rn + ORIGIN[2]) * math.cos(ORIGIN[0])),
                            ORIGIN[2]])
            f.gnss(llh, np.array([0.0, v, 0.0]) + rng.normal(0, 0.05, 3), np.array([0.5, 0.5, 0.8]), 0.05)
    yaw = float(quat_to_euler(f.filter.state.q)[2])
    assert f.heading_known
    assert abs(math.degrees(yaw) - 90.0) < 3.0
    assert abs(math.degrees(yaw) - 90.0) < 3.0 * math.degrees(f.yaw_sigma) + 0.5
    sd = np.sqrt(np.diag(f.filter.P)[9:11])
    assert np.all(np.abs(f.filter.state.bg[:2] - true_bg[:2]) < 3.0 * sd), (f.filter.state.bg, sd)


def test_a_gross_range_outlier_is_gated_on_the_uninflated_spread() -> None:
    """Split CI inflates the covariances (P/ω, R_dep/(1-ω)) before its χ² gate. When most of
    what a vehicle knows is shared with its neighbours, that gate let a range 14 m long through
    (rush-hour seed 7: W1 fused one 23 m off). The range is first gated on HPHᵀ + R."""
    rm, rn = earth.radii(ORIGIN[0])
    east = np.array([0.0, 30.0 / ((rn + 50) * math.cos(ORIGIN[0])), 0.0])

    def shared_filter() -> tuple[MethodFilter, NeighbourState]:
        f, _, _, true_llh = _stopped_filter("SL-CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0, fusion="split-ci")
        f.filter.flush_covariance()
        f.filter.P_ind = f.filter.P * 0.05  # 95 % of its covariance shared with the neighbours
        return f, NeighbourState("V3", true_llh + east, np.eye(3) * 4.0, 0.05)

    f, nb = shared_filter()
    assert f.range(nb, 44.0) == "gate_nis" and f.counters["ranges"] == 0
    f, nb = shared_filter()
    f._range_gate_nis = None  # the split-CI gate alone
    assert f.range(nb, 44.0) == "fused"
    f, nb = shared_filter()
    assert f.range(nb, 31.0) == "fused"


def _stand(f: MethodFilter, seconds: float, rate: float = 100.0) -> None:
    """Propagate a standing filter (specific force straight up) for ``seconds``."""
    dt = 1.0 / rate
    for _ in range(int(round(seconds * rate))):
        f.propagate(np.zeros(3), np.array([0.0, 0.0, -9.80]) * dt, dt)


def test_a_declined_neighbour_is_weighed_again_only_when_its_decision_may_change() -> None:
    """``selection_hold``: after node selection declines a neighbour, its ranges are declined
    without weighing for ``selection_hold`` seconds, unless the neighbour's variance shrank, the
    own one grew, or the line of sight turned; the gates still see every range."""
    rm, rn = earth.radii(ORIGIN[0])
    ce = (rn + 50) * math.cos(ORIGIN[0])

    def neighbour(llh, bearing_deg: float, dist: float, var: float) -> NeighbourState:
        b = math.radians(bearing_deg)
        return NeighbourState("V2", llh + np.array([dist * math.cos(b) / (rm + 50), dist * math.sin(b) / ce, 0.0]),
                              np.eye(3) * var, 0.05)

    f, _, _, true_llh = _stopped_filter("CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0)
    useless = neighbour(true_llh, 180.0, 30.0, 1e6)  # σ 1 km: nothing to gain
    assert f.range(useless, 30.0) == "skipped" and f.counters["ranges_skipped_held"] == 0
    _stand(f, 0.1)
    assert f.range(useless, 30.0) == "skipped" and f.counters["ranges_skipped_held"] == 1
    _stand(f, 0.1)
    assert f.range(useless, 70.0) == "gate_rate"  # the gates come first: a 40 m jump
    _stand(f, 0.1)
    turned = neighbour(true_llh, 270.0, 30.0, 1e6)  # the line of sight turned by 90°: weighed
    assert f.range(turned, 30.0) == "skipped" and f.counters["ranges_skipped_held"] == 1
    _stand(f, 0.1)
    assert f.range(turned, 30.0) == "skipped" and f.counters["ranges_skipped_held"] == 2
    _stand(f, 0.1)
    # a beacon that knows far more: weighed at once, and fused
    assert f.range(neighbour(true_llh, 270.0, 30.0, 0.01), 30.0) == "fused"
    assert f.counters["ranges_skipped_held"] == 2 and f.counters["ranges_skipped"] == 4

    late, _, _, _ = _stopped_filter("CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0)
    assert late.range(useless, 30.0) == "skipped"
    _stand(late, 0.6)  # longer than the hold: weighed again
    assert late.range(useless, 30.0) == "skipped" and late.counters["ranges_skipped_held"] == 0

    grown, _, _, _ = _stopped_filter("CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0)
    assert grown.range(useless, 30.0) == "skipped"
    grown.filter.P[6:8, 6:8] *= 1.2  # the own horizontal variance grew by 20 %: weighed again
    _stand(grown, 0.1)
    assert grown.range(useless, 30.0) == "skipped" and grown.counters["ranges_skipped_held"] == 0

    every, _, _, _ = _stopped_filter("CP", offset_ne=(0.0, 0.0), range_min_sigmas=0.0, selection_hold=0.0)
    for _ in range(3):
        assert every.range(useless, 30.0) == "skipped"
        _stand(every, 0.1)
    assert every.counters["ranges_skipped_held"] == 0 and every.counters["ranges_skipped"] == 3


def test_a_run_of_intervals_is_one_call_per_interval_bit_for_bit() -> None:
    """``MethodFilter.propagate_run`` (what the engine calls for intervals with nothing inside
    them) leaves the filter, its INS displacement history and its own-IMU rates exactly as one
    :meth:`propagate` per interval does, for runs that cross covariance steps and history points."""
    rng = np.random.default_rng(7)
    st = initial_state(np.array(ORIGIN), np.array([8.0, 1.0, 0.0]), np.array([0.0, 0.0, -9.8]))
    settings = FilterSettings(MEMS_NOISE, gnss_lever_arm=(0.3, 0.0, -1.2))

    def fresh() -> MethodFilter:
        return MethodFilter(MethodSpec.of("SL-CP"), st.copy(), np.array([2.0, 2.0, 3.0]), settings, 0.0)

    n = 700
    dts = (0.01 + rng.uniform(-2e-4, 2e-4, n)).tolist()
    th = (rng.normal(0.0, 1e-3, (n, 3)) + [0.0, 0.0, 2e-3]).tolist()
    dv = (rng.normal(0.0, 2e-3, (n, 3)) + [0.01, 0.0, -0.098]).tolist()
    a, b = fresh(), fresh()
    assert a._own_imu
    for k in range(n):
        a.propagate(th[k], dv[k], dts[k])
    for lo, hi in ((0, 1), (1, 4), (4, 333), (333, 334), (334, n)):
        b.propagate_run(th[lo:hi], dv[lo:hi], dts[lo:hi])
    fa, fb = a.filter, b.filter
    assert fb.t == fa.t and fb.stats.cov_steps == fa.stats.cov_steps > 60
    assert np.array_equal(fb.P, fa.P) and np.array_equal(fb.extra, fa.extra)
    assert fb.state.llh.tolist() == fa.state.llh.tolist() and fb.state.q.tolist() == fa.state.q.tolist()
    assert list(b._disp_hist) == list(a._disp_hist) and len(a._disp_hist) > 60 and b._disp == a._disp
    assert np.array_equal(b.displacement_since(fa.t - 1.234), a.displacement_since(fa.t - 1.234))
    assert list(b.own._w) == list(a.own._w) and list(b.own._f) == list(a.own._f)
