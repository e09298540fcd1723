"""The lane-keeping row of the SL methods: lane association, one shared lateral-offset state,
its reset between lanes, and its place in the bound."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.agent.lane_map import LaneMap
from slcp.agent.methods import FilterSettings, MethodFilter, MethodSpec, initial_state
from slcp.agent.nav.measurements.stop_line import Line2D, StopGapModel, StopLineApproach, stop_line_position
from slcp.deploy.agent_configs import lane_map
from slcp.deploy.bound import posterior_crlb
from slcp.geo import earth
from slcp.geo.lane_markings import BOUNDARY, DIVIDER, UNSEEN
from slcp.hw_emulation.scenario import load_scenario
from slcp.hw_emulation.truth import build_truth

from conftest import MEMS_NOISE

ORIGIN = (math.radians(39.95), math.radians(116.32), 50.0)
#: the shipped intersection: Minzu Univ. West Rd one lane each way (north-south), Weigongcun
#: Rd two lanes each way (east-west)
SITE = lane_map(load_scenario("paper-2"))


def test_a_single_lane_of_my_direction_is_found_and_the_oncoming_lane_is_not() -> None:
    wide = np.eye(2) * 3.0**2
    hit = SITE.locate(np.array([-60.0, 2.5]), wide, 0.0)
    assert hit is not None and hit.lane == "NB_in"
    assert hit.left_line.signed_distance(np.array([-60.0, 1.75])) == pytest.approx(1.75)
    # facing south at the same place: the southbound lane (the estimate is 4 m off it)
    assert SITE.locate(np.array([-60.0, 2.5]), wide, math.pi).lane == "SB_out"
    assert SITE.locate(np.array([-60.0, 2.5]), wide, math.radians(25.0)) is None  # turning
    # a heading not yet known (a vehicle that started standing) is no heading
    assert SITE.locate(np.array([-60.0, 2.5]), wide, 0.0, yaw_sigma=math.radians(12.0)) is None
    assert SITE.locate(np.array([-60.0, 2.5]), wide, 0.0, yaw_sigma=math.radians(8.0)).lane == "NB_in"
    assert SITE.locate(np.array([-60.0, 40.0]), wide, 0.0) is None  # off the road


def test_side_by_side_lanes_need_the_camera() -> None:
    """Eastbound, two lanes: with a lateral σ of metres only the marking classes name one."""
    ne, wide = np.array([-2.5, -80.0]), np.eye(2) * 2.0**2
    assert SITE.locate(ne, wide, math.pi / 2) is None
    assert SITE.locate(ne, wide, math.pi / 2, (BOUNDARY, DIVIDER)).lane == "EB_in_L"
    assert SITE.locate(ne, wide, math.pi / 2, (DIVIDER, BOUNDARY)).lane == "EB_in_R"
    assert SITE.locate(ne, wide, math.pi / 2, (UNSEEN, DIVIDER)).lane == "EB_in_L"  # one side is enough
    assert SITE.locate(ne, wide, math.pi / 2, (BOUNDARY, BOUNDARY)) is None  # matches neither
    # a good estimate inside one lane needs no camera
    assert SITE.locate(np.array([-5.3, -80.0]), np.eye(2) * 0.2**2, math.pi / 2).lane == "EB_in_R"


def test_the_lane_a_vehicle_keeps_stays_its_lane_while_it_still_matches() -> None:
    """Eastbound, two lanes, no markings seen: an estimate metres wide matches both and names
    neither, unless the vehicle keeps one of them already; a lane it does not match any more,
    or whose markings the camera contradicts, is not kept."""
    ne, wide = np.array([-2.5, -80.0]), np.eye(2) * 2.0**2
    assert SITE.locate(ne, wide, math.pi / 2) is None
    assert SITE.locate(ne, wide, math.pi / 2, current="EB_in_L").lane == "EB_in_L"
    assert SITE.locate(ne, wide, math.pi / 2, current="EB_in_R").lane == "EB_in_R"
    assert SITE.locate(ne, wide, math.pi / 2, (DIVIDER, BOUNDARY), current="EB_in_L").lane == "EB_in_R"
    assert SITE.locate(ne, wide, math.pi / 2, current="NB_in") is None  # not a match here
    # far into the left lane with a good estimate: the right lane does not match any more
    assert SITE.locate(np.array([-1.0, -80.0]), np.eye(2) * 0.2**2, math.pi / 2, current="EB_in_R").lane == "EB_in_L"


def test_the_lane_end_is_widened_by_the_along_track_sigma() -> None:
    """NB_in ends at the stop line (north -11): a queue head estimated 3 m past it is still in
    its lane when its along-track σ is metres, not when it is decimetres."""
    ne = np.array([-8.0, 1.8])
    assert SITE.locate(ne, np.diag([3.0**2, 0.3**2]), 0.0).lane == "NB_in"
    assert SITE.locate(ne, np.diag([0.3**2, 0.3**2]), 0.0) is None


def test_polyline_lanes_and_bad_input() -> None:
    bend = LaneMap({"A": (np.array([[0.0, 0.0], [100.0, 0.0], [200.0, 100.0]]), 3.5)})
    hit = bend.locate(np.array([150.0, 51.0]), np.eye(2), math.pi / 4)
    assert hit is not None and hit.left_line.direction == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)))
    assert bend.left_line_at("A", np.array([50.0, 1.0])).direction == pytest.approx((1.0, 0.0))
    with pytest.raises(ValueError, match="lane 'B'"):
        LaneMap({"B": (np.array([[0.0, 0.0]]), 3.5)})
    with pytest.raises(ValueError, match="width"):
        LaneMap({"B": (np.array([[0.0, 0.0], [1.0, 0.0]]), 0.0)})
    with pytest.raises(KeyError):
        bend.left_line_at("nope", np.zeros(2))


APPROACH = StopLineApproach(Line2D((0.0, 0.0), (0.0, 1.0)), Line2D((0.0, -1.75), (1.0, 0.0)))  # north-bound
GAP = StopGapModel(1.5, 0.2, 1.75, 0.12, 2.5)


def _filter(method: str = "SL-SP", **settings) -> MethodFilter:
    p, _ = stop_line_position(APPROACH, GAP)
    rm, rn = earth.radii(ORIGIN[0])
    llh = np.array([ORIGIN[0] + p[0] / (rm + 50), ORIGIN[1] + p[1] / ((rn + 50) * math.cos(ORIGIN[0])), 50.0])
    st = initial_state(llh, np.zeros(3), np.array([0.0, 0.0, -9.8]))
    return MethodFilter(MethodSpec.of(method), st, np.array([4.0, 4.0, 6.0]),
                        FilterSettings(MEMS_NOISE, **settings), 0.0, GAP, ORIGIN)


def _stand(f: MethodFilter, seconds: float) -> None:
    zero, dt = np.zeros(3), 0.01
    g = np.array([0.0, 0.0, -earth.gravity(ORIGIN[0], 50.0)]) * dt
    for _ in range(int(round(seconds / dt))):
        f.propagate(zero, g, dt)


def test_lane_rows_and_the_stop_line_share_one_lateral_offset() -> None:
    """The map alone cannot tell where in the lane the driver keeps: after many lane rows and
    full stop-line fixes the cross-track σ stays at the driver's σ_yb. Had the stop line's
    lateral row its own offset state (as without the lane row), the two would count d_l twice
    and the σ would drop to σ_yb / √2."""
    f = _filter()
    for _k in range(20):
        _stand(f, 1.0)
        assert f.lane_line("NB_in", APPROACH.left_lane_line).accepted
    s_lane = math.sqrt(f.position_cov[1, 1])
    assert s_lane == pytest.approx(GAP.sigma_yb, rel=0.02)
    for _k in range(20):
        _stand(f, 1.05)
        f.stop_line(APPROACH, stop_id=0.0, lane="NB_in")
        assert f.lane_line("NB_in", APPROACH.left_lane_line) is None  # the full fix holds d_l
    assert f.counters["stop_line"] == 20 and f.counters["lane_line"] == 20
    assert math.sqrt(f.position_cov[1, 1]) >= 0.98 * GAP.sigma_yb
    assert math.sqrt(f.position_cov[0, 0]) == pytest.approx(GAP.sigma_xb, rel=0.05)


@pytest.mark.parametrize("fusion", ["source-ci", "split-ci"])
def test_the_offset_is_redrawn_in_a_new_lane_and_after_losing_the_lane(fusion: str) -> None:
    f = _filter("SL-CP", fusion=fusion)
    flt = f.filter
    if fusion == "source-ci":  # some information from a neighbour, which the lane row correlates too
        flt.flush_covariance()
        flt.sources.add(frozenset({"V2"}), 0.1 * flt.P)
    k = flt.extra_offset + f._lane.start
    others = np.setdiff1d(np.arange(flt.n), [k])
    f.lane_line("NB_in", APPROACH.left_lane_line)
    flt.flush_covariance()
    assert np.abs(flt.P[k, others]).max() > 1e-3
    _stand(f, 1.0)
    f.lane_line(None)  # lost for 1 s: kept
    assert np.abs(flt.P[k, others]).max() > 1e-3
    _stand(f, 1.5)
    f.lane_line(None)  # lost for 2.5 s: redrawn
    # in P and in its parts: split CI's independent part, or source CI's stored components
    # (the redrawn offset is the own component's, the implicit rest)
    parts = [(flt.P_ind, GAP.sigma_yb**2)] if fusion == "split-ci" else [(C, 0.0) for C in flt.sources.parts]
    assert len(parts) >= 1
    for P, var in [(flt.P, GAP.sigma_yb**2)] + parts:
        assert np.allclose(P[k, others], 0.0) and P[k, k] == pytest.approx(var)
    f.lane_line("NB_in", APPROACH.left_lane_line)
    f.lane_line("other", APPROACH.left_lane_line)  # a new lane: redrawn before its row
    assert f.counters["lane_line"] == 3


def test_a_lane_row_the_estimate_disagrees_with_releases_the_lane() -> None:
    """The lane a vehicle keeps (which :meth:`LaneMap.locate` then prefers) is let go when its
    row fails the χ² gate, here a lane line 10 m off: the next lane starts afresh."""
    f = _filter()
    assert f.lane_line("NB_in", APPROACH.left_lane_line).accepted and f.lane == "NB_in"
    far = Line2D((0.0, -11.75), (1.0, 0.0))
    res = f.lane_line("NB_in", far)
    assert not res.accepted and f.lane is None and f.counters["lane_line_rejected"] == 1
    assert f.lane_line("NB_in", APPROACH.left_lane_line).accepted and f.lane == "NB_in"


def test_only_sl_methods_with_the_constraint_keep_to_the_lane() -> None:
    assert _filter("SP").lane_line("NB_in", APPROACH.left_lane_line) is None
    assert _filter("CP").lane_line("NB_in", APPROACH.left_lane_line) is None
    off = _filter("SL-CP", lane_constraint=False)
    assert not off.lane_due() and off.lane_line("NB_in", APPROACH.left_lane_line) is None
    assert _filter("SL-SP").lane_due()


def test_the_bound_holds_the_lane_information() -> None:
    """With the lane rows the SL bound is tighter than without, never looser; the SP and CP
    bounds do not change."""
    truth = build_truth(load_scenario("paper-1"))
    with_lane = posterior_crlb(truth, ("SP", "SL-SP"), rate=1.0)
    without = posterior_crlb(truth, ("SP", "SL-SP"), rate=1.0, lane_constraint=False)
    for vid in truth.vehicles:
        a, b = with_lane.sigma_h("SL-SP", vid), without.sigma_h("SL-SP", vid)
        assert np.all(a <= b + 1e-9)
        assert np.allclose(with_lane.sigma_h("SP", vid), without.sigma_h("SP", vid))
    # V2 queues behind V1 on a north-south lane: its cross-track (east) is held to about σ_yb
    east = {
        k: np.median(np.sqrt(b.cov[("SL-SP", "V2")][:, 1, 1])) for k, b in (("with", with_lane), ("without", without))
    }
    assert east["with"] < 0.5 < east["without"], east


def test_a_one_second_camera_error_does_not_name_a_lane_for_the_lane_row() -> None:
    """Five frames settle a class for the first-stopped detector; a lane row, which holds the
    vehicle in the lane it names, waits for ten (2 s at 5 Hz): a 1 s camera error at the start
    (rush-hour E2, seed 6) no longer names the wrong lane."""
    from slcp.agent.decision_step import LANE_MARKING_FRAMES
    from slcp.geo.lane_markings import MarkingWindow

    w = MarkingWindow()
    for k in range(5):  # 1 s of wrong reports (the right lane's classes)
        w.observe(0.2 * k, DIVIDER, BOUNDARY)
    assert w.settled(0.8) == (DIVIDER, BOUNDARY)
    assert w.settled(0.8, LANE_MARKING_FRAMES) == (UNSEEN, UNSEEN)
    for k in range(5, 15):  # then 2 s of right ones (the left lane's)
        w.observe(0.2 * k, BOUNDARY, DIVIDER)
    assert w.settled(2.8, LANE_MARKING_FRAMES) == (BOUNDARY, DIVIDER)


def test_one_settled_side_does_not_name_a_lane_for_the_lane_row() -> None:
    """rush-hour E2's camera in seed 6, in the left lane of two (boundary, divider): from 1.4 s
    the right side reads boundary for 0.4 s and the left side divider for 2.6 s (one error
    episode each), with unseen frames. At every check time, whatever the phase of the checks
    against the frames, the lane row's classes never name the right lane; they name the left
    lane once both sides have settled again (with a vehicle that has not yet taken a lane: the
    lateral σ stays at 2.5 m)."""
    from slcp.agent.decision_step import lane_row_markings
    from slcp.geo.lane_markings import MarkingWindow

    reports = [(BOUNDARY, DIVIDER)] * 7 + [(BOUNDARY, BOUNDARY)] * 2 + [(DIVIDER, BOUNDARY)] * 2 \
        + [(DIVIDER, UNSEEN)] + [(DIVIDER, DIVIDER)] * 11 + [(BOUNDARY, DIVIDER)] * 25
    ne, wide = np.array([-2.5, -80.0]), np.eye(2) * 2.5**2
    first_named = []
    for phase in np.arange(0.0, 0.2, 0.02):
        w = MarkingWindow()
        k = 0
        named = []
        for check in np.arange(phase, 9.0, 1.0):
            while k < len(reports) and 0.2 * k <= check:
                w.observe(0.2 * k, *reports[k])
                k += 1
            hit = SITE.locate(ne, wide, math.pi / 2, lane_row_markings(w, check))
            assert hit is None or hit.lane == "EB_in_L", (phase, check)
            if hit is not None:
                named.append(check)
        first_named.append(min(named))
    assert max(first_named) < 7.5
    # the fleet's check at 4.1 s: ten left reports settle "divider", nine right ones nothing;
    # one settled side named the right lane
    w = MarkingWindow()
    for k in range(11, 21):
        w.observe(0.2 * k, *reports[k])
    assert w.settled(4.1, 10) == (DIVIDER, UNSEEN)
    assert SITE.locate(ne, wide, math.pi / 2, w.settled(4.1, 10)).lane == "EB_in_R"
    assert lane_row_markings(w, 4.1) == (UNSEEN, UNSEEN)
