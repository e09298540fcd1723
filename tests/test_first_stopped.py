"""First-stopped detection from own estimate, map and neighbour beacons (no truth)."""

from __future__ import annotations

import math

import numpy as np

from agent.first_stopped import ApproachLane, FirstStoppedDetector, NeighbourView
from agent.nav.measurements.stop_line import Line2D, StopGapModel, StopLineApproach

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
    assert det.decide(p, cov, 0.0, 0.4, []).reason == "moving"
    assert not det.decide(p, cov, math.pi, 3.0, []).first           # heading south: not this approach
    assert not det.decide(np.array([-60.0, 1.75]), cov, 0.0, 3.0, []).first


def test_ambiguous_adjacent_lanes_give_an_along_only_fix() -> None:
    det = FirstStoppedDetector(_lanes(), GAP)
    p = np.array([-1.75, -12.0])  # in EB_L, but with 3 m lateral sigma EB_R is possible too
    d = det.decide(p, np.diag([9.0, 1.0]), math.pi / 2, 3.0, [])
    assert d.first and d.along_only
    d = det.decide(p, np.diag([0.04, 0.04]), math.pi / 2, 3.0, [])
    assert d.first and not d.along_only and d.lane == "EB_L"
