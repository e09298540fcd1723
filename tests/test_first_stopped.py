"""First-stopped detection from own estimate, map and neighbour beacons (no truth)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.agent.first_stopped import ApproachLane, FirstStoppedDetector, NeighbourView, StopTracker
from slcp.agent.nav.measurements.stop_line import Line2D, StopGapModel, StopLineApproach
from slcp.geo.lane_markings import BOUNDARY, DIVIDER, UNSEEN, LaneEdges, MarkingWindow, marking_classes

GAP = StopGapModel(1.5, 0.3, 1.75, 0.15, 2.5)


def _lanes():
    # northbound single lane (stop line at north = -11), eastbound two lanes sharing a stop line
    nb = ApproachLane("NB", StopLineApproach(Line2D((-11.0, 0.0), (0.0, 1.0)), Line2D((-11.0, 0.0), (1.0, 0.0))), 3.5)
    ebl = ApproachLane("EB_L", StopLineApproach(Line2D((0.0, -8.0), (1.0, 0.0)), Line2D((0.0, -8.0), (0.0, 1.0))), 3.5)
    ebr = ApproachLane("EB_R", StopLineApproach(Line2D((0.0, -8.0), (1.0, 0.0)), Line2D((-3.5, -8.0), (0.0, 1.0))), 3.5)
    return {"NB": nb, "EB_L": ebl, "EB_R": ebr}


def test_first_vehicle_of_a_queue_is_detected_and_the_second_is_not() -> None:
    det = FirstStoppedDetector(_lanes(), GAP)
    cov = np.eye(2) * 1.0
    first = np.array([-11.0 - 4.0, 1.75])   # reference point 4 m behind the line
    second = np.array([-11.0 - 11.0, 1.75])  # 7 m further back
    d1 = det.decide(first, cov, 0.0, 3.0, [NeighbourView("B", second, True)])
    d2 = det.decide(second, cov, 0.0, 3.0, [NeighbourView("A", first, True)])
    assert d1.first and d1.lane == "NB" and not d1.along_only
    assert not d2.first and d2.reason == "not near a stop line"  # outside the gate at σ = 1 m
    # with σ = 3 m the second vehicle is inside the gate: the neighbour ahead vetoes
    d2 = det.decide(second, cov * 9.0, 0.0, 3.0, [NeighbourView("A", first, True)])
    assert not d2.first and "may be ahead" in d2.reason
    # a neighbour claiming first in my lane vetoes, even if its estimate looks behind me
    d3 = det.decide(first, cov, 0.0, 3.0, [NeighbourView("B", second, True, claims_first=True)])
    assert not d3.first


def test_moving_wrong_heading_or_far_from_the_line() -> None:
    det = FirstStoppedDetector(_lanes(), GAP)
    cov = np.eye(2)
    p = np.array([-15.0, 1.75])
    assert det.decide(p, cov, 0.0, 0.1, []).reason == "moving"
    assert not det.decide(p, cov, math.pi, 3.0, []).first           # heading south: not this approach
    assert not det.decide(np.array([-60.0, 1.75]), cov, 0.0, 3.0, []).first


def test_ambiguous_adjacent_lanes_give_an_along_only_fix() -> None:
    det = FirstStoppedDetector(_lanes(), GAP)
    p = np.array([-1.75, -12.0])  # in EB_L, but with 3 m lateral sigma EB_R is possible too
    d = det.decide(p, np.diag([9.0, 1.0]), math.pi / 2, 3.0, [])
    assert d.first and d.along_only
    d = det.decide(p, np.diag([0.04, 0.04]), math.pi / 2, 3.0, [])
    assert d.first and not d.along_only and d.lane == "EB_L"


def _queue(err_ahead: float):
    """Leader A stops 4 m behind the NB stop line; follower B stops 7 m behind A. Both estimates
    carry a 3 m σ; ``err_ahead`` moves B's beacon forward (an along-track error)."""
    a = np.array([-15.0, 1.75])
    b = np.array([-22.0 + err_ahead, 1.75])
    return a, b, np.eye(2) * 9.0


def test_a_follower_that_stops_after_me_does_not_veto_even_if_its_estimate_looks_ahead() -> None:
    a, b, cov = _queue(err_ahead=8.0)  # B's beacon is 1 m *ahead* of A
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    for k in range(30):  # 6 s at 5 Hz: A at rest from t = 0; B moving until t = 2 s, then at rest
        t = 0.2 * k
        tr.observe_neighbour("B", t, 2.0 if t < 2.0 else 0.0, False)
        dec, _ = tr.decide(t, a, cov, 0.0, 0.0, {"B": b})
    assert dec.first and tr.claim


def test_a_neighbour_already_at_rest_when_first_heard_vetoes_and_the_veto_sticks() -> None:
    a, b, cov = _queue(err_ahead=0.0)
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    tr.observe_neighbour("A", 0.0, 0.0, True)  # first heard at rest: counts as stopped before me
    for k in range(10):
        dec, _ = tr.decide(0.2 * k, b, cov, 0.0, 0.0, {"A": a})
    assert not dec.first and tr.vetoed == "A"
    # the leader drives off at the green: B, still at rest 7 m back, must not claim the stop line
    for k in range(10, 20):
        tr.observe_neighbour("A", 0.2 * k, 3.0, False)
        dec, _ = tr.decide(0.2 * k, b, cov, 0.0, 0.0, {"A": a + [10.0, 0.0]})
    assert not dec.first and "stopped behind A" in dec.reason
    # once B moves and stops again at the line with nobody ahead, it may claim
    tr.decide(4.2, b, cov, 0.0, 2.0, {})
    for k in range(22, 30):
        dec, _ = tr.decide(0.2 * k, a, cov, 0.0, 0.0, {})
    assert dec.first


def test_a_claim_ends_as_soon_as_the_vehicle_moves_and_neighbour_noise_does_not_restart_a_stop() -> None:
    a, b, cov = _queue(err_ahead=0.0)
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    for k in range(10):
        tr.observe_neighbour("B", 0.2 * k, 0.35 if k % 2 else 0.1, False)  # noise around the threshold
        dec, _ = tr.decide(0.2 * k, b, cov, 0.0, 0.0, {})
    assert dec.first
    assert tr._nb["B"].stopped_since == -np.inf  # first heard at rest, never "restarted" by noise
    dec, changed = tr.decide(2.2, b, cov, 0.0, 0.15, {})
    assert not dec.first and changed


def test_imu_rest_is_told_from_constant_acceleration_and_turning() -> None:
    from slcp.agent.nav.motion import StationarityMonitor, ZuptGate

    g = np.array([0.0, 0.0, -9.81])  # specific force at rest, level FRD
    dt = 0.01
    rng = np.random.default_rng(0)

    def feed(f_b, w_b):
        m = StationarityMonitor()
        for _ in range(60):
            m.push(w_b * dt + rng.normal(0, 1e-5, 3), f_b * dt + rng.normal(0, 5e-5, 3), dt, np.eye(3))
        return m

    rest = feed(g, np.zeros(3))
    assert rest.stationary
    assert not feed(g + [1.0, 0.0, 0.0], np.zeros(3)).stationary        # steady 1 m/s² forward
    assert not feed(g, np.array([0.0, 0.0, np.radians(5.0)])).stationary  # turning at 5 °/s
    # a batch resolved with one DCM is the same as its samples one by one
    c = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    th, dv = rng.normal(0, 1e-3, (60, 3)), g * dt + rng.normal(0, 0.02, (60, 3))
    dts = dt + rng.normal(0, 1e-4, 60)
    one, many = StationarityMonitor(), StationarityMonitor()
    for k in range(60):
        one.push(th[k], dv[k], dts[k], c)
    many.push_batch(th[:25], dv[:25], dts[:25], c)
    many.push_batch(th[25:], dv[25:], dts[25:], c)
    for x, y in ((one._w, many._w), (one._f, many._f), (one._fn, many._fn)):
        np.testing.assert_allclose(np.array(x), np.array(y), rtol=1e-12, atol=1e-15)
    assert one.stationary == many.stationary
    gate = ZuptGate()
    gate.gnss(10.0)
    assert not gate.due(10.2, rest, 0.05)    # GNSS still arriving: Doppler does the job
    assert not gate.due(11.0, rest, 5.0)     # the INS says "moving": cruising looks like rest
    assert gate.due(11.0, rest, 0.3)
    assert not gate.due(11.05, rest, 0.3)    # at most every 0.1 s
    # after a long GNSS gap the INS speed is uncertain: 0.98 ± 2 m/s may be a car creeping
    # at 2.4 m/s (constant speed looks like rest to the IMU); the σ is evaluated only if needed
    assert not gate.due(12.0, rest, 0.98, lambda: 2.0)
    assert not gate.due(12.0, rest, 0.3, 0.4)  # 0.3 + 2 * 0.4 >= 1
    assert gate.due(12.0, rest, 0.3, 0.2)
    assert not gate.due(13.0, rest, 5.0, lambda: 1 / 0)  # ruled out before the σ is needed


def test_speed_sigma_is_the_standard_deviation_along_the_velocity() -> None:
    from slcp.agent.nav.motion import speed_sigma

    cov = np.diag([4.0, 0.25, 9.0])
    assert speed_sigma(np.array([3.0, 0.0, 1.0]), cov) == pytest.approx(2.0)
    assert speed_sigma(np.array([0.0, -3.0, 0.0]), cov) == pytest.approx(0.5)
    v = np.array([1.0, 1.0, 0.0])
    assert speed_sigma(v, cov) == pytest.approx(np.sqrt((4.0 + 0.25) / 2))
    assert speed_sigma(np.zeros(3), cov) == pytest.approx(2.0)  # at rest: the larger axis
    rng = np.random.default_rng(3)  # against the sample σ of the speed of perturbed velocities
    c = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.0], [0.0, 0.0, 1.0]])
    v = np.array([5.0, 2.0, 0.0])
    speeds = np.hypot(*(v[:2] + rng.multivariate_normal(np.zeros(2), c[:2, :2], 200_000)).T)
    assert speed_sigma(v, c) == pytest.approx(speeds.std(), rel=0.01)


def test_side_by_side_heads_of_two_lanes_both_claim_when_their_ranges_show_them_abreast() -> None:
    """Eastbound, two lanes, lateral σ 3 m (either could be in either lane). E1 (left lane) claims
    first; E3 beside it stopped a little earlier. On beacons alone E1 may be ahead of E3 in E3's
    lane, so E3 is held off (and the hold sticks). UWB ranges of 3.5 m -- no two cars of one lane
    stand that close -- show E1 beside E3: E3 claims, and a hold taken before the ranges came
    is lifted. A gross short outlier among range samples of a real leader 7 m ahead changes
    nothing (the median)."""
    e3, e1 = np.array([-5.25, -12.0]), np.array([-1.75, -12.0])
    cov = np.diag([9.0, 1.0])
    sigma_uwb = 0.1

    def run(ranges: list[float] | None, t0: float = 0.0, tr: StopTracker | None = None):
        tr = tr or StopTracker(FirstStoppedDetector(_lanes(), GAP))
        for k in range(10):
            t = t0 + 0.1 * k
            tr.observe_neighbour("E1", t, 0.0, True)
            if ranges is not None:
                tr.observe_range("E1", t, ranges[k % len(ranges)], sigma_uwb)
            dec, _ = tr.decide(t, e3, cov, math.pi / 2, 0.0, {"E1": e1})
        return dec, tr

    dec, tr = run(None)
    assert not dec.first and tr.vetoed == "E1"
    dec, _ = run([3.5, 3.6, 3.45])
    assert dec.first and dec.along_only
    dec, tr = run([3.5, 3.6, 3.45], t0=2.0, tr=tr)  # the earlier hold is lifted by the ranges
    assert dec.first and tr.vetoed is None
    dec, _ = run([7.0, 1.2, 7.1, 6.9])  # a real leader, one short outlier: still held off
    assert not dec.first
    dec, _ = run([4.9])  # 4.9 m + 2.5 σ is not surely shorter than a same-lane queue: held off
    assert not dec.first


def test_map_marking_classes_name_the_lanes_of_a_two_lane_approach() -> None:
    det = FirstStoppedDetector(_lanes(), GAP)
    assert det.marks == {"NB": (BOUNDARY, BOUNDARY), "EB_L": (BOUNDARY, DIVIDER), "EB_R": (DIVIDER, BOUNDARY)}
    # three lanes of one direction: the middle one has dividers on both sides
    edges = {f"L{k}": LaneEdges(np.array([0.0, -3.5 * k]), np.array([1.0, 0.0]), 3.5) for k in range(3)}
    assert marking_classes(edges) == {"L0": (DIVIDER, BOUNDARY), "L1": (DIVIDER, DIVIDER), "L2": (BOUNDARY, DIVIDER)}
    # an opposing lane beside mine (its left line is my left line) is no divider
    edges["opp"] = LaneEdges(np.array([0.0, -7.0]), np.array([-1.0, 0.0]), 3.5)
    assert marking_classes(edges)["L2"] == (BOUNDARY, DIVIDER)


def test_marking_window_settles_on_a_clear_majority_of_enough_frames() -> None:
    w = MarkingWindow(window=2.0, min_frames=5, agreement=0.8)
    for k in range(4):
        w.observe(0.2 * k, BOUNDARY, DIVIDER)
    assert w.settled(0.6) == (UNSEEN, UNSEEN)  # four frames are not enough
    w.observe(0.8, BOUNDARY, 7)  # a class the receiver does not know counts as unseen
    assert w.settled(0.8) == (BOUNDARY, UNSEEN)
    for k in range(5, 10):
        w.observe(0.2 * k, BOUNDARY, BOUNDARY)  # the right side now split 4 : 5
    assert w.settled(1.8) == (BOUNDARY, UNSEEN)
    assert w.settled(10.0) == (UNSEEN, UNSEEN)  # nothing recent


def test_camera_markings_pick_the_lane_an_ambiguous_stop_line_fix_could_not() -> None:
    det = FirstStoppedDetector(_lanes(), GAP)
    p, cov = np.array([-1.75, -12.0]), np.diag([9.0, 1.0])  # 3 m lateral σ: either lane
    d = det.decide(p, cov, math.pi / 2, 3.0, [], markings=(BOUNDARY, DIVIDER))
    assert d.first and not d.along_only and d.lane == "EB_L"
    d = det.decide(p, cov, math.pi / 2, 3.0, [], markings=(DIVIDER, UNSEEN))  # one side suffices
    assert d.first and not d.along_only and d.lane == "EB_R"
    for marks in ((UNSEEN, UNSEEN), (BOUNDARY, BOUNDARY)):  # silent, or matching no candidate
        d = det.decide(p, cov, math.pi / 2, 3.0, [], markings=marks)
        assert d.first and d.along_only


def test_a_stops_lane_named_by_the_markings_holds_until_the_vehicle_moves() -> None:
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    p, cov = np.array([-1.75, -12.0]), np.diag([9.0, 1.0])

    def drive(t0: float, t1: float, marks: tuple[int, int], speed: float):
        dec = None
        for k in range(int(round((t1 - t0) / 0.1))):
            t = t0 + 0.1 * k
            if k % 2 == 0:
                tr.observe_markings(t, *marks)
            dec, _ = tr.decide(t, p, cov, math.pi / 2, speed, {})
        return dec

    dec = drive(0.0, 3.0, (BOUNDARY, DIVIDER), 0.0)
    assert dec.first and dec.lane == "EB_L" and not dec.along_only
    dec = drive(3.0, 8.0, (DIVIDER, BOUNDARY), 0.0)  # a long camera error during the stop
    assert dec.first and dec.lane == "EB_L"
    drive(8.0, 8.5, (DIVIDER, BOUNDARY), 5.0)  # moves off, and stops again
    dec = drive(8.5, 11.0, (DIVIDER, BOUNDARY), 0.0)
    assert dec.first and dec.lane == "EB_R"


def test_a_neighbour_a_little_behind_me_holds_me_off_only_while_the_estimates_are_poor() -> None:
    """E3 heads the right lane with a stop-line fix (σ 0.15 / 0.3 m). E2, second in the left lane
    (lateral σ 1.5 m: it might be in E3's lane), looks 2.5 m farther from the line. A car ahead
    of E3 in its lane would stand ≥ 5 m closer: with E2's along σ of 1.2 m that is ruled out, so
    E3 stays first; with a GNSS-level 3.5 m it is not, and E3 is held off. E2 looking 2.5 m
    *closer* holds E3 off even with good estimates."""
    det = FirstStoppedDetector(_lanes(), GAP)
    e3 = np.array([-5.25, -12.0])
    cov = np.diag([0.15**2, 0.3**2])
    for e2_east, along_sigma, first in ((-14.5, 1.2, True), (-14.5, 3.5, False), (-9.5, 1.2, False)):
        nb = NeighbourView("E2", np.array([-1.75, e2_east]), True, stopped_since=-math.inf,
                           cov_ne=np.diag([1.5**2, along_sigma**2]))
        d = det.decide(e3, cov, math.pi / 2, 3.0, [nb], stopped_since=0.0, markings=(DIVIDER, BOUNDARY))
        assert d.first is first, (e2_east, along_sigma)


def test_a_follower_lost_for_a_moment_keeps_its_place_in_the_queue_order() -> None:
    """Head H stops first; F stops behind it 2 s later, its beacon 2 m behind H's (σ 3 m: not
    clearly behind). F's radio goes silent, F is forgotten, then heard again at rest: it still
    came to rest after H, so H stays first (it used to become "first heard at rest", i.e.
    stopped before H, and hold H off)."""
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    h, f = np.array([-15.0, 1.75]), np.array([-17.0, 1.75])
    cov = np.eye(2) * 9.0
    dec = None
    for k in range(60):
        t = 0.1 * k
        if t < 3.0 or t >= 4.0:
            tr.observe_neighbour("F", t, 5.0 if t < 2.0 else 0.0, False)
        if abs(t - 3.0) < 1e-9:
            tr.forget("F")
        dec, _ = tr.decide(t, h, cov, 0.0, 0.0, {"F": f} if not 3.0 <= t < 4.0 else {}, {"F": cov})
    assert dec.first and tr.vetoed is None


def test_my_own_estimate_3_sigma_to_the_side_of_a_single_lane_still_finds_its_stop_line() -> None:
    det = FirstStoppedDetector(_lanes(), GAP)
    p = np.array([-15.0, 1.75 + 3.0 * 3.0 + 1.75])  # 3 σ (σ 3 m) right of the lane's right edge
    d = det.decide(p, np.eye(2) * 9.0, 0.0, 3.0, [])
    assert d.first and d.lane == "NB"
    assert not det.decide(p + np.array([0.0, 2.0 * 3.0]), np.eye(2) * 9.0, 0.0, 3.0, []).first  # 5 σ: no


def test_the_geometry_free_moving_decision_is_the_full_decision() -> None:
    """``first_stopped_step`` skips the geometry while ``moving_decision`` answers: over a drive,
    stop, claim, veto and drive-off, a tracker that takes that path decides exactly as one that
    always runs the full decision, and both paths are exercised."""
    a, b, cov = _queue(err_ahead=0.0)
    full, quick = StopTracker(FirstStoppedDetector(_lanes(), GAP)), StopTracker(FirstStoppedDetector(_lanes(), GAP))
    speeds = [8.0, 5.0, 2.0, 0.5, 0.15, 0.05] + [0.0] * 12 + [0.12, 0.08] + [0.0] * 6 + [1.0, 3.0] + [0.0] * 6
    paths = set()
    for k, v in enumerate(speeds):
        t = 0.1 * k
        nb = {"A": a} if 8 <= k < 22 else {}  # a leader heard for a while, then gone
        for tr in (full, quick):
            tr.observe_neighbour("A", t, 0.0 if k < 24 else 3.0, False)
        want = full.decide(t, b, cov, 0.0, v, nb)
        got = quick.moving_decision(t, v)
        paths.add(got is None)
        if got is None:
            got = quick.decide(t, b, cov, 0.0, v, nb)
        assert got == want, (k, got, want)
        assert (quick.since, quick.claim, quick.vetoed, quick.lane) == (full.since, full.claim, full.vetoed, full.lane)
    assert paths == {True, False} and full.claim  # claimed again after the drive-off


def test_three_recent_ranges_are_enough_to_show_a_neighbour_beside_me() -> None:
    """``beside`` takes the median of at least three ranges of the last ``range_window``: two
    short ranges prove nothing, a third does; ranges older than the window no longer count."""
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    for k in range(2):
        tr.observe_range("E1", 0.1 * k, 3.5, 0.1)
    assert not tr.beside("E1", 0.1)
    tr.observe_range("E1", 0.2, 3.5, 0.1)
    assert tr.beside("E1", 0.2)
    assert not tr.beside("E1", 0.2 + tr.s.range_window + 0.05)  # the first one fell out of the window
    assert not tr.beside("E9", 0.2)


def test_a_speed_within_the_stop_hysteresis_is_moving_for_the_decision() -> None:
    """Between ``stop_speed`` and twice it the rest keeps its start (a stop is not restarted by
    noise), but the vehicle is not at rest: the geometry-free decision says "moving" and a claim
    ends, however long the vehicle stood before."""
    a, b, cov = _queue(err_ahead=0.0)
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    for k in range(10):
        dec, _ = tr.decide(0.2 * k, b, cov, 0.0, 0.0, {})
    assert dec.first and tr.since == 0.0
    slow = 1.5 * tr.s.stop_speed
    quick = tr.moving_decision(2.0, slow)
    assert quick is not None and quick[0].reason == "moving" and quick[1]
    assert tr.since == 0.0  # kept: a return below stop_speed continues this stop
    assert tr.moving_decision(2.2, 0.0) is None  # at rest for 2.2 s


def test_a_veto_lifted_while_the_vehicle_creeps_does_not_make_it_first() -> None:
    """Held off by E1 (possibly ahead in its lane), E3 creeps at a speed within the stop's
    hysteresis (above stop_speed, below twice it) when ranges show E1 beside it: the veto goes,
    but a vehicle that moves is not at rest, so no claim until it stands again."""
    e3, e1 = np.array([-5.25, -12.0]), np.array([-1.75, -12.0])
    cov = np.diag([9.0, 1.0])
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    for k in range(10):
        tr.observe_neighbour("E1", 0.1 * k, 0.0, True)
        dec, _ = tr.decide(0.1 * k, e3, cov, math.pi / 2, 0.0, {"E1": e1})
    assert not dec.first and tr.vetoed == "E1"
    creep = 1.5 * tr.s.stop_speed
    claims = []
    for k in range(10, 20):
        t = 0.1 * k
        tr.observe_neighbour("E1", t, 0.0, True)
        tr.observe_range("E1", t, 3.5, 0.1)
        dec, _ = tr.decide(t, e3, cov, math.pi / 2, creep, {"E1": e1})
        claims.append(dec.first)
    assert tr.vetoed is None and not any(claims)  # not even at the step that lifts the veto
    dec, _ = tr.decide(2.0, e3, cov, math.pi / 2, 0.0, {"E1": e1})
    assert dec.first  # at rest again (its stop kept its start through the creep)


def test_at_rest_for_exactly_min_stationary_is_long_enough() -> None:
    """"At rest for at least ``min_stationary``": a vehicle standing since 0.5 s is still
    "moving" at 0.625 s and is decided with the geometry from 0.75 s (times exact in binary)."""
    from slcp.agent.first_stopped import DetectorSettings

    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP, DetectorSettings(min_stationary=0.25)))
    assert tr.moving_decision(0.5, 0.0)[0].reason == "moving"
    assert tr.moving_decision(0.625, 0.0)[0].reason == "moving"
    assert tr.moving_decision(0.75, 0.0) is None


def test_each_agents_diagnostics_say_why_it_claims_first_stopped_or_not(tmp_path) -> None:
    """paper-1 (V1 and V2 queue northbound, V1 first; V0 turns away) in process: each agent's
    diagnostics carry its stop-line method's latest decision reason, through the codec: V1's is
    "first stopped", V2's names V1, V0's is never a claim."""
    from slcp.deploy.inprocess import run_inprocess
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth
    from slcp.transport.codec import decode, encode
    from slcp.transport.messages import Diagnostics

    from conftest import short_scenario

    truth = build_truth(load_scenario(short_scenario(tmp_path, "paper-1", 30.0)))
    reasons: dict[str, list[str]] = {v: [] for v in truth.vehicles}

    def on_output(v: str, m) -> None:
        if isinstance(m, Diagnostics):
            reasons[v].append(decode(encode(m)).status["decisions"]["SL-SP"])

    run_inprocess(truth, seed=0, methods=("SL-SP",), on_output=on_output)
    assert reasons["V0"][0] == "moving" and "first stopped" not in reasons["V0"]
    assert reasons["V1"][-1] == "first stopped"
    assert "V1" in reasons["V2"][-1] and "first stopped" not in reasons["V2"]


def _stand_near(me: np.ndarray, other: np.ndarray, speed, ranges, steps: int = 40) -> tuple[StopTracker, list]:
    """I stand at ``me`` on NB (σ 3 m along) and hear neighbour "A" at ``other`` (beacon) with
    beacon speed ``speed(t)`` and UWB range ``ranges(t)``, at 10 Hz from t = 0. Returns the
    tracker and the decisions."""
    cov = np.diag([9.0, 1.0])
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    out = []
    for k in range(steps):
        t = 0.1 * k
        tr.observe_neighbour("A", t, speed(t), False)
        tr.observe_range("A", t, ranges(t), 0.1)
        out.append(tr.decide(t, me, cov, 0.0, 0.0, {"A": other})[0])
    return tr, out


def _stand_behind_a_drifting_leader(ranges) -> tuple[StopTracker, list]:
    """I stand at ``b``, the leader's beacon at ``a`` 7 m ahead is inside my gates; its beacons
    say it drives at 1 m/s (its own estimate runs away) while ``ranges(t)`` gives the range."""
    a, b, _ = _queue(err_ahead=0.0)
    return _stand_near(b, a, lambda t: 1.0, ranges)


def test_a_leader_whose_beacon_drifts_but_whose_ranges_stand_still_holds_me_off() -> None:
    """A leader standing at the line in a GNSS outage may report a velocity that runs away; its
    range to me, relative, shows it standing. Until I have stood for ``still_window`` it makes
    me wait (no claim, no veto); then its ranges, within their noise, count it as stopped and it
    holds me off for the stop. Without the range rule, the beacon's "moving" let the second of
    the queue claim the head's stop line (rush-hour seed 15, S2: 6 m off at a σ of 0.3 m)."""
    rng = np.random.default_rng(3)
    noise = {round(0.1 * k, 1): float(rng.normal(0.0, 0.1)) for k in range(40)}
    tr, decisions = _stand_behind_a_drifting_leader(lambda t: 7.0 + noise[round(t, 1)])
    w = tr.s.still_window
    early = [d for k, d in enumerate(decisions) if tr.s.min_stationary <= 0.1 * k < w]
    assert early and all(not d.first and d.reason == "neighbour A may be ahead (moving?)" for d in early)
    assert not any(d.first for d in decisions)
    assert tr.vetoed == "A" and decisions[-1].reason == "stopped behind A"
    # one gross outlier in the window changes nothing (one range at each end is left out)
    tr2, decisions2 = _stand_behind_a_drifting_leader(lambda t: 7.0 + (25.0 if abs(t - 3.0) < 0.05 else 0.0))
    assert tr2.vetoed == "A" and not any(d.first for d in decisions2)


def test_a_neighbour_driving_away_is_waited_for_then_let_go() -> None:
    """A neighbour ahead whose beacon says moving and whose range grows (it really drives off,
    0.5 m/s): I wait while its ranges since my stop stay within their noise, and claim once they
    show it moving; it never vetoes the stop."""
    tr, decisions = _stand_behind_a_drifting_leader(lambda t: 7.0 + 0.5 * t)
    first = next(k for k, d in enumerate(decisions) if d.first)
    noise_band = 2.0 * tr.s.k_sigma * 0.1  # the spread the ranges may have and still stand
    assert 0.1 * first == pytest.approx(noise_band / 0.5 + 0.2, abs=0.25)  # one range at each end left out
    assert all(d.first for d in decisions[first:]) and tr.vetoed is None


def test_a_follower_closing_in_does_not_hold_the_head_back() -> None:
    """The second of a queue still rolling in behind the head (its beacon moving, its estimate
    beside the head's: GNSS errors) is behind by the queue order once it stands; while it rolls
    in, its closing range shows it moving relative to the head, so the head does not wait."""
    a, _, _ = _queue(err_ahead=0.0)
    tr, decisions = _stand_near(a, a + np.array([-1.3, 0.0]), lambda t: 1.0 - t, lambda t: 8.2 - 1.2 * t, steps=10)
    assert decisions[-1].first and tr.range_motion("A", 0.9) == "moving"


def test_range_motion_needs_enough_ranges_since_my_stop_and_my_own_rest() -> None:
    """``range_motion``: nothing before I stand or without ranges; "unsure" before I have stood
    for ``still_window`` or with too few ranges or too short a span of them; "moving" beyond
    2 k σ of spread (ranges from before my stop do not count); "still" otherwise."""
    tr = StopTracker(FirstStoppedDetector(_lanes(), GAP))
    w, k_sigma = tr.s.still_window, tr.s.k_sigma
    tr.observe_range("A", -1.0, 20.0, 0.1)  # before my stop: not counted
    assert tr.range_motion("A", 0.0) == ""  # not at rest
    assert tr.moving_decision(0.0, 0.0) is not None and tr.since == 0.0
    for i in range(21):
        tr.observe_range("A", 0.1 * i, 7.0 + (0.0 if i % 2 else 2.0 * k_sigma * 0.1 - 0.01), 0.1)  # within 2 k σ
    assert tr.range_motion("A", w) == "still" and tr.range_motion("A", w - 0.1) == "unsure"
    assert tr.range_motion("B", w) == ""
    for i in range(5):
        tr.observe_range("C", 1.9 + 0.02 * i, 7.0, 0.1)  # five ranges over 0.08 s: too short a span
    assert tr.range_motion("C", w) == "unsure"
    for i in range(21):
        tr.observe_range("D", 0.1 * i, 7.0 + (0.0 if i % 2 else 2.0 * k_sigma * 0.1 + 0.02), 0.1)
    assert tr.range_motion("D", w) == "moving"
