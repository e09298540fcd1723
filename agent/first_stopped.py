"""Deciding "I am the first stopped vehicle of my lane" from the vehicle's own data, the map
and the neighbours' beacons (no truth).

A wrong "first" (really second in the queue, ~7 m back) is a catastrophic error for the stop-line
fix, so the decision is conservative:

1. stationary for at least ``min_stationary`` seconds;
2. associated to approach lanes: heading within ``heading_tol`` of the lane, laterally inside the
   lane up to ``lane_k_sigma`` position σ, and behind the stop line by no more than
   ``l0 + m_xb + 3 σ_xb + k_sigma σ_along + margin``;
3. no stopped neighbour within ``neighbour_range`` (beacon distance, widened by my σ) inside
   one of those lanes (laterally, and not past its stop line, gates widened by both σ) that is
   not clearly behind (its distance to the stop line must exceed mine by
   ``behind_margin``, or by less when both estimates are good: a vehicle ahead of me in my
   lane stands at least ``min_queue_spacing`` closer to the line, so a neighbour whose
   distance exceeds mine by ``ahead_k_sigma`` σ of the difference minus that spacing cannot be
   it),
   and no such neighbour claiming to be first, *unless* it stopped clearly
   after me (``order_tol``): in a queue the leader stops before its followers, so a neighbour
   that came to rest after me is behind me or in another lane. A neighbour first heard already
   stopped counts as stopped before me. Nor does a neighbour count whose UWB ranges of the last
   ``range_window`` seconds (at least three) have a median shorter than ``min_queue_spacing`` by
   ``k_sigma`` range σ: two vehicles queued in one lane stand at least a vehicle length plus
   the standstill gap apart, so that neighbour stands beside me, in another lane. The range is
   relative, so errors common to both GNSS positions do not enter; it settles side-by-side
   queues on multi-lane approaches, where the beacon positions cannot tell the lanes apart and
   each head would otherwise hold the other off its stop line.

   A neighbour is "stopped" when its beacon says so (speed below ``neighbour_stop_speed``), or
   when its UWB ranges stayed still while I stood: over the last ``still_window`` seconds (at
   least ``still_min_ranges`` ranges spanning three quarters of it) they spread by no more than
   their noise allows (``k_sigma`` range σ either way, one range at each end left out). Two
   vehicles at rest keep their distance, and a passing one cannot hold it for seconds; the range
   is relative, so a neighbour whose own estimate drifts (a GNSS outage while it stands, its INS
   velocity running away) still counts as standing where its beacon puts it, instead of as a
   car driving by, which is what let the second of a queue claim the head's stop line. Until I
   have stood for ``still_window``, a neighbour whose beacon says "moving" and whose ranges
   since I came to rest stay within their noise is *unsure*: where a stopped one would hold me
   off, it makes me wait (no claim, and no veto for the stop), until its ranges say "still"
   or show it moving relative to me (a follower closing in behind me, a car driving off).

:class:`StopTracker` keeps the bookkeeping around the detector (own stationarity, when each
neighbour came to rest, the current claim); the agent runtime and the in-process runner share it.

If several adjacent lanes sharing the stop line match (lateral uncertainty larger than a lane),
the lane markings the camera settled on (:mod:`geo.lane_markings`) pick the lane whose
classes they match; the candidates they rule out are no longer "my lane" for the neighbour rule
either. Without a settled camera report that names one lane, the decision is *along-only*: the
stop line fixes the along-track position, not the lane. A stop's lane, once named by the
markings, is kept until the vehicle moves (a camera error later in the stop cannot move it).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from slcp.geo.lane_markings import UNSEEN, LaneEdges, MarkingWindow, consistent, marking_classes

from .nav.measurements.stop_line import StopGapModel, StopLineApproach
from .nav.rotation import wrap_angle


@dataclass(frozen=True)
class ApproachLane:
    id: str
    approach: StopLineApproach
    width: float


@dataclass(frozen=True)
class DetectorSettings:
    min_stationary: float = 0.2  #: [s] at rest before a claim
    heading_tol: float = math.radians(30.0)
    k_sigma: float = 2.5
    #: [σ] how far outside a lane (across it) my own estimate may stand and still be in it:
    #: wider than along it, since a GNSS estimate 3 σ to the side happens in a long run and on a
    #: single-lane approach there is no other lane to mistake; heading, the along-track gate
    #: and the neighbour rules still apply
    lane_k_sigma: float = 3.5
    margin: float = 2.0
    neighbour_range: float = 15.0  #: [m] plus k_sigma times my horizontal σ
    behind_margin: float = 3.0
    #: [σ] a neighbour less than behind_margin farther from the line than me is ruled out as a
    #: car ahead of me in my lane if ahead_k_sigma σ of the difference is less than the spacing
    ahead_k_sigma: float = 3.5
    order_tol: float = 0.5  #: [s] a neighbour at rest this much later than me is behind me
    stop_speed: float = 0.1  #: [m/s] own filter speed below which the vehicle is at rest
    neighbour_stop_speed: float = 0.3  #: [m/s] beacon speed below which a neighbour is at rest
    #: [m] smallest distance between the reference points of two vehicles queued in one lane
    #: (the leader's length behind its reference point, the standstill gap, my reference point's
    #: distance behind my front: 2.1 + 2.0 + 2.5 = 6.6 m for the scenarios' 4.6 m cars)
    min_queue_spacing: float = 5.0
    range_window: float = 1.0  #: [s] UWB ranges this recent say whether a neighbour is beside me
    #: [s] UWB ranges this recent, all within their noise while I stand, say a neighbour stands
    still_window: float = 2.0
    still_min_ranges: int = 5


@dataclass(frozen=True)
class NeighbourView:
    """A neighbour as seen from its latest beacon (map frame)."""

    vehicle: str
    ne: np.ndarray
    stopped: bool
    claims_first: bool = False
    #: sensor time [s] at which it came to rest; -inf if first heard at rest, None if moving
    stopped_since: float | None = None
    cov_ne: np.ndarray | None = None  #: (2, 2) [m²] its beacon's horizontal covariance
    #: its recent UWB ranges prove it closer than two vehicles queued in one lane can stand
    beside: bool = False
    #: its beacon says moving, and its ranges cannot tell yet whether it stands (see the module
    #: docstring): it may hold me back for now, but not veto the stop
    unsure: bool = False


@dataclass(frozen=True)
class Decision:
    first: bool
    lane: str | None
    along_only: bool
    reason: str
    vetoed_by: str | None = None  #: the neighbour that may be ahead, if that is the reason


class FirstStoppedDetector:
    def __init__(self, lanes: dict[str, ApproachLane], gap: StopGapModel,
                 settings: DetectorSettings = DetectorSettings()) -> None:
        self.lanes = lanes
        self.gap = gap
        self.s = settings
        #: (left, right) marking classes each approach lane implies (see :mod:`geo.lane_markings`)
        self.marks = marking_classes({lid: LaneEdges(np.asarray(ln.approach.left_lane_line.point),
                                                     ln.approach.travel_direction, ln.width)
                                      for lid, ln in lanes.items()})

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
            k_lat = self.s.lane_k_sigma
            if not -k_lat * s_lat <= right <= lane.width + k_lat * s_lat:
                continue
            out.append((lid, behind))
        return out

    def decide(self, ne: np.ndarray, cov_ne: np.ndarray, yaw: float, stationary_for: float,
               neighbours: list[NeighbourView], stopped_since: float | None = None,
               markings: tuple[int, int] = (UNSEEN, UNSEEN)) -> Decision:
        """Decide for a vehicle at ``ne`` (map NED [m], (2,)) with covariance ``cov_ne`` (2, 2)
        [m²], heading ``yaw`` [rad], at rest for ``stationary_for`` s since ``stopped_since``
        (sensor time; None disables the queue-order rule), its camera having settled on the
        (left, right) marking classes ``markings``."""
        if stationary_for < self.s.min_stationary:
            return Decision(False, None, False, "moving")
        cands = self.candidates(ne, cov_ne, yaw)
        if not cands:
            return Decision(False, None, False, "not near a stop line")
        if len(cands) > 1:
            named = [c for c in cands if consistent(self.marks[c[0]], markings)]
            cands = named or cands
        reach = self.s.neighbour_range + self.s.k_sigma * math.sqrt(max(float(np.trace(cov_ne)), 0.0))
        waiting = None  # an unsure neighbour that may be ahead: no claim yet, but no veto
        for nb in neighbours:
            if not (nb.stopped or nb.unsure) or nb.beside or float(np.hypot(*(nb.ne - ne))) > reach:
                continue
            if (stopped_since is not None and nb.stopped_since is not None
                    and nb.stopped_since > stopped_since + self.s.order_tol):
                continue  # came to rest after me: behind me in my lane, or in another lane
            for lid, behind in cands:
                lane = self.lanes[lid]
                nb_behind, nb_right = self._geometry(lane, nb.ne)
                # only a neighbour inside this lane and not past its stop line can be ahead of me
                # (gates widened by both σ: estimates 3 σ off happen, and a leader that dropped
                # out of my lane on its estimate would let me claim wrongly)
                c = cov_ne + (nb.cov_ne if nb.cov_ne is not None else 0.0)
                n_s, n_r = lane.approach.stop_line_normal(), lane.approach.left_lane_line.right_normal
                s_diff = math.sqrt(max(float(n_s @ c @ n_s), 0.0))
                tol_a = self.s.k_sigma * s_diff + self.s.margin
                tol_l = self.s.k_sigma * math.sqrt(max(float(n_r @ c @ n_r), 0.0))
                if not (-tol_l <= nb_right <= lane.width + tol_l and nb_behind >= -tol_a):
                    continue
                # ahead of me in my lane, it would stand at least min_queue_spacing closer to the
                # line: it holds me off while the estimates allow that (ahead_k_sigma σ of the
                # difference), and never when it is behind_margin or more farther back
                ahead_by = min(self.s.behind_margin, self.s.ahead_k_sigma * s_diff - self.s.min_queue_spacing)
                if nb.claims_first or nb_behind < behind + ahead_by:
                    if nb.stopped:
                        return Decision(False, None, False, f"neighbour {nb.vehicle} may be ahead", nb.vehicle)
                    waiting = waiting or nb.vehicle  # a stopped neighbour further on still vetoes
                    break
        if waiting is not None:
            return Decision(False, None, False, f"neighbour {waiting} may be ahead (moving?)")
        lid = min(cands, key=lambda c: c[1])[0]
        return Decision(True, lid, len(cands) > 1, "first stopped" + (" (lane ambiguous)" if len(cands) > 1 else ""))


@dataclass
class _NeighbourStop:
    t: float
    speed: float
    claims_first: bool
    stopped_since: float | None


class StopTracker:
    """Bookkeeping around :class:`FirstStoppedDetector` for one filter of one vehicle.

    Feed it the neighbours' beacons (:meth:`observe_neighbour`) and call :meth:`decide` at the
    decision rate with the filter's own estimate. It tracks when this vehicle and each neighbour
    came to rest (sensor time) and holds the current claim.
    """

    def __init__(self, detector: FirstStoppedDetector) -> None:
        self.detector = detector
        self.s = detector.s
        self.since: float | None = None
        self.claim = False
        self.lane: str | None = None
        self.along_only = False
        self.vetoed: str | None = None  #: neighbour that was ahead of me during this stop
        self._nb: dict[str, _NeighbourStop] = {}
        self._ranges: dict[str, deque[tuple[float, float]]] = {}  #: vehicle -> (t, range + k σ)
        self._range_sigma: dict[str, float] = {}  #: vehicle -> its ranges' noise σ [m]
        self.markings = MarkingWindow()  #: the camera's recent lane-marking reports
        self._stop_marks: tuple[int, int] | None = None  #: markings that named this stop's lane

    def observe_markings(self, t: float, left: int, right: int) -> None:
        """The camera's (left, right) lane-marking classes at sensor time ``t`` [s]."""
        self.markings.observe(t, left, right)

    def observe_range(self, vehicle: str, t: float, range_m: float, sigma: float) -> None:
        """A UWB range [m] to ``vehicle`` at sensor time ``t`` [s] with noise σ ``sigma`` [m]."""
        if not math.isfinite(range_m):
            return
        q = self._ranges.setdefault(vehicle, deque(maxlen=64))
        q.append((t, range_m + self.s.k_sigma * sigma))
        self._range_sigma[vehicle] = sigma
        while q and q[0][0] < t - max(self.s.range_window, self.s.still_window):
            q.popleft()

    def beside(self, vehicle: str, t: float) -> bool:
        """Whether ``vehicle``'s recent ranges prove it closer than a same-lane queue allows."""
        recent = sorted(r for tr, r in self._ranges.get(vehicle, ()) if t - self.s.range_window <= tr <= t + 0.5)
        # the median: a gross outlier (either sign) cannot move it; an NLOS bias (positive) only
        # makes the neighbour look farther, which errs on the safe side (statistics.median's
        # arithmetic, without its overhead: this runs for every neighbour at every decision)
        n = len(recent)
        if n < 3:
            return False
        median = recent[n // 2] if n % 2 else (recent[n // 2 - 1] + recent[n // 2]) / 2
        return median < self.s.min_queue_spacing

    def range_motion(self, vehicle: str, t: float) -> str:
        """What ``vehicle``'s UWB ranges since I came to rest (the last ``still_window`` seconds
        of them) say of it: ``"still"`` (enough ranges over the window, within their noise, and I
        stood through it), ``"moving"`` (they spread beyond their noise: it moves relative to
        me), ``"unsure"`` (within their noise so far, too few to tell) or ``""`` (none, or I
        am not at rest). See the module docstring."""
        window = self.s.still_window
        if self.since is None:
            return ""
        start = max(self.since, t - window)
        recent = [(tr, r) for tr, r in self._ranges.get(vehicle, ()) if start <= tr <= t + 0.5]
        if not recent:
            return ""
        values = sorted(r for _, r in recent)
        if len(values) >= self.s.still_min_ranges:
            values = values[1:-1]  # a gross outlier at either end cannot decide
        if values[-1] - values[0] > 2.0 * self.s.k_sigma * self._range_sigma[vehicle]:
            return "moving"
        mature = (t - self.since >= window and len(recent) >= self.s.still_min_ranges
                  and recent[-1][0] - recent[0][0] >= 0.75 * window)
        return "still" if mature else "unsure"

    def observe_neighbour(self, vehicle: str, t: float, speed: float, claims_first: bool) -> None:
        """A beacon of ``vehicle`` at sensor time ``t`` [s] with horizontal ``speed`` [m/s]."""
        old = self._nb.get(vehicle)
        if old is not None and t < old.t:
            return
        was = old.stopped_since if old is not None else None
        if speed < self.s.neighbour_stop_speed:
            since = -math.inf if old is None else (was if was is not None else t)
        elif speed < 2.0 * self.s.neighbour_stop_speed and old is not None:
            since = was  # hysteresis: velocity noise does not restart a neighbour's stop
        else:
            since = None
        self._nb[vehicle] = _NeighbourStop(t, speed, claims_first, since)

    def forget(self, vehicle: str) -> None:
        """``vehicle`` is gone (silent, its process lost, or excluded): its ranges are dropped,
        but not when it came to rest, so that a neighbour heard again, or remembered as a ghost,
        keeps its place in the order of the queue (a short radio gap made the second of a queue
        "first heard at rest", i.e. stopped before the head, and held the head off)."""
        self._ranges.pop(vehicle, None)
        self._range_sigma.pop(vehicle, None)

    def moving_decision(self, t: float, speed: float) -> tuple[Decision, bool] | None:
        """Update the rest bookkeeping with the own filter speed [m/s] at sensor time ``t`` [s];
        if the vehicle has not been at rest for ``min_stationary`` and holds no veto, return
        what :meth:`decide` returns then ("moving", without any geometry), else None.

        The caller can then skip the map and neighbour geometry, most of a decision's cost,
        whenever the vehicle drives (:func:`agent.decision_step.first_stopped_step`)."""
        if speed < self.s.stop_speed:
            if self.since is None:
                self.since, self.vetoed, self._stop_marks = t, None, None
        elif speed >= 2.0 * self.s.stop_speed:
            self.since, self.vetoed, self._stop_marks = None, None, None
        if self.vetoed is not None:
            return None
        still = t - self.since if self.since is not None and speed < self.s.stop_speed else 0.0
        if still >= self.s.min_stationary:
            return None
        changed = self.claim
        self.claim, self.lane, self.along_only = False, None, False
        return Decision(False, None, False, "moving"), changed

    def decide(self, t: float, ne: np.ndarray, cov_ne: np.ndarray, yaw: float, speed: float,
               neighbour_ne: dict[str, np.ndarray],
               neighbour_cov: dict[str, np.ndarray] | None = None) -> tuple[Decision, bool]:
        """Decide at sensor time ``t`` [s]; ``neighbour_ne`` maps each neighbour heard to its beacon
        position (map NED [m], (2,)), ``neighbour_cov`` to its horizontal covariance ((2, 2) [m²]).
        Returns the decision and whether the claim changed."""
        quick = self.moving_decision(t, speed)
        if quick is not None:
            return quick
        if self.vetoed is not None and self.beside(self.vetoed, t):
            self.vetoed = None  # the ranges now show it beside me, not ahead of me in my lane
        if self.vetoed is not None:
            # a vehicle that stopped behind a leader stays off the stop line when the leader leaves
            dec = Decision(False, None, False, f"stopped behind {self.vetoed}")
            changed = self.claim
            self.claim, self.lane, self.along_only = False, None, False
            return dec, changed
        nbs = []
        for v, p in neighbour_ne.items():
            st = self._nb.get(v)
            if st is not None:
                motion = "" if st.stopped_since is not None else self.range_motion(v, t)
                stopped, unsure = st.stopped_since is not None or motion == "still", motion == "unsure"
                nbs.append(NeighbourView(v, p, stopped, st.claims_first, st.stopped_since,
                                         (neighbour_cov or {}).get(v), self.beside(v, t), unsure))
        # a claim ends as soon as the vehicle moves (the stop itself has hysteresis): a vehicle
        # whose veto the ranges just lifted may be creeping within that hysteresis
        still = t - self.since if self.since is not None and speed < self.s.stop_speed else 0.0
        marks = self._stop_marks or self.markings.settled(t)
        dec = self.detector.decide(ne, cov_ne, yaw, still, nbs, self.since, marks)
        if dec.vetoed_by is not None:
            self.vetoed = dec.vetoed_by
        if dec.first and not dec.along_only and marks != (UNSEEN, UNSEEN):
            self._stop_marks = marks
        changed = dec.first != self.claim or (dec.first and dec.lane != self.lane)
        self.claim, self.lane, self.along_only = dec.first, dec.lane, dec.along_only
        return dec, changed
