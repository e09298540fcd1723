"""Deciding "I am the first stopped vehicle of my lane" from the vehicle's own data, the map
and the neighbours' beacons (no truth).

A wrong "first" (really second in the queue, ~7 m back) is a catastrophic error for the stop-line
fix, so the decision is conservative:

1. stationary for at least ``min_stationary`` seconds;
2. associated to approach lanes: heading within ``heading_tol`` of the lane, laterally inside the
   lane up to ``k_sigma`` position σ, and behind the stop line by no more than
   ``l0 + m_xb + 3 σ_xb + k_sigma σ_along + margin``;
3. no stopped neighbour within ``neighbour_range`` (beacon distance) in those lanes that is not
   clearly behind (its distance to the stop line must exceed mine by ``behind_margin``), and no
   such neighbour claiming to be first.

If several adjacent lanes sharing the stop line match (lateral uncertainty larger than a lane),
the decision is *along-only*: the stop line fixes the along-track position, not the lane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .nav.measurements.stop_line import StopGapModel, StopLineApproach
from .nav.rotation import wrap_angle


@dataclass(frozen=True)
class ApproachLane:
    id: str
    approach: StopLineApproach
    width: float


@dataclass(frozen=True)
class DetectorSettings:
    min_stationary: float = 1.0
    heading_tol: float = math.radians(30.0)
    k_sigma: float = 2.5
    margin: float = 2.0
    neighbour_range: float = 12.0
    behind_margin: float = 3.0


@dataclass(frozen=True)
class NeighbourView:
    """A neighbour as seen from its latest beacon (map frame)."""

    vehicle: str
    ne: np.ndarray
    stopped: bool
    claims_first: bool = False


@dataclass(frozen=True)
class Decision:
    first: bool
    lane: str | None
    along_only: bool
    reason: str


class FirstStoppedDetector:
    def __init__(self, lanes: dict[str, ApproachLane], gap: StopGapModel,
                 settings: DetectorSettings = DetectorSettings()) -> None:
        self.lanes = lanes
        self.gap = gap
        self.s = settings

    def _geometry(self, lane: ApproachLane, ne: np.ndarray) -> tuple[float, float]:
        """Distance behind the stop line and distance right of the left lane line [m]."""
        a = lane.approach
        behind = -float(a.stop_line_normal() @ (ne - np.asarray(a.stop_line.point)))
        right = a.left_lane_line.signed_distance(ne)
        return behind, right

    def candidates(self, ne: np.ndarray, cov_ne: np.ndarray, yaw: float) -> list[tuple[str, float]]:
        """Lanes the vehicle may stand in, with its distance behind their stop line."""
        out = []
        for lid, lane in self.lanes.items():
            a = lane.approach
            u = a.travel_direction
            if abs(wrap_angle(yaw - math.atan2(u[1], u[0]))) > self.s.heading_tol:
                continue
            n_s = a.stop_line_normal()
            n_r = a.left_lane_line.right_normal
            s_along = math.sqrt(max(float(n_s @ cov_ne @ n_s), 0.0))
            s_lat = math.sqrt(max(float(n_r @ cov_ne @ n_r), 0.0))
            behind, right = self._geometry(lane, ne)
            g = self.gap
            gate = g.l0 + g.m_xb + 3 * g.sigma_xb + self.s.k_sigma * s_along + self.s.margin
            if not -self.s.margin - self.s.k_sigma * s_along <= behind <= gate:
                continue
            if not -self.s.k_sigma * s_lat <= right <= lane.width + self.s.k_sigma * s_lat:
                continue
            out.append((lid, behind))
        return out

    def decide(self, ne: np.ndarray, cov_ne: np.ndarray, yaw: float, stationary_for: float,
               neighbours: list[NeighbourView]) -> Decision:
        if stationary_for < self.s.min_stationary:
            return Decision(False, None, False, "moving")
        cands = self.candidates(ne, cov_ne, yaw)
        if not cands:
            return Decision(False, None, False, "not near a stop line")
        for nb in neighbours:
            if not nb.stopped or float(np.hypot(*(nb.ne - ne))) > self.s.neighbour_range:
                continue
            for lid, behind in cands:
                nb_behind, nb_right = self._geometry(self.lanes[lid], nb.ne)
                if nb.claims_first or nb_behind < behind + self.s.behind_margin:
                    return Decision(False, None, False, f"neighbour {nb.vehicle} may be ahead")
        lid = min(cands, key=lambda c: c[1])[0]
        return Decision(True, lid, len(cands) > 1, "first stopped" + (" (lane ambiguous)" if len(cands) > 1 else ""))
