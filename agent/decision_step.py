"""One first-stopped decision of a stop-line method, and the stop-line fix and lane row it
brings (:func:`first_stopped_step`, run by the engine at the decision rate)."""

from __future__ import annotations

import math

import numpy as np
import pymap3d

from slcp.geo.lane_markings import UNSEEN, MarkingWindow

from .first_stopped import ApproachLane, Decision, StopTracker
from .lane_map import LaneMap
from .methods import MethodFilter
from .nav.rotation import quat_to_euler
from .neighbours import NeighbourTable

#: classified camera reports a side needs before its class names a lane for the lane row (2 s
#: at 5 Hz): a lane row holds the vehicle in the lane it names, so a camera error must not
#: settle within the window
LANE_MARKING_FRAMES = 10


def lane_row_markings(window: MarkingWindow, t: float) -> tuple[int, int]:
    """The camera's (left, right) classes at sensor time ``t`` [s] that may name a lane for the
    lane row: both sides settled over :data:`LANE_MARKING_FRAMES` reports, or nothing. One
    side is not enough: a side's error episode can outlast the window, and then the other
    side's gaps let the wrong side name the neighbouring lane alone, and the lane row then
    holds the vehicle in the wrong lane for the rest of the run."""
    marks = window.settled(t, LANE_MARKING_FRAMES)
    return (UNSEEN, UNSEEN) if UNSEEN in marks else marks


def first_stopped_step(tracker: StopTracker, f: MethodFilter, table: NeighbourTable,
                       lanes: dict[str, ApproachLane], origin_llh: tuple[float, float, float],
                       t: float, ghosts: dict | None = None,
                       lane_map: LaneMap | None = None) -> tuple[Decision, bool]:
    """One first-stopped decision for filter ``f`` at sensor time ``t`` [s] from its own estimate,
    the map (``lanes``, frame at ``origin_llh``) and the neighbours' beacons in ``table``; a claim
    applies the stop-line fix (a new claim at once). Returns the decision and whether it changed.
    With ``lane_map`` (every lane of the site), it also applies the lane-keeping row when due.

    ``ghosts`` maps neighbours lost recently (silent, or their process gone) to their last known
    (llh (3,), NED covariance (3, 3) [m²]): they count as standing there, so that a vehicle that
    cannot hear the queue ahead of it does not take the stop line."""
    st = f.filter.state
    known = {o: (table.entries[o].llh, table.entries[o].cov) for o in table.vehicles()}
    for o, (llh, cov) in (ghosts or {}).items():
        if o not in known:
            known[o] = (llh, cov)
            # standing there: since it was last seen coming to rest, since now if it was last
            # seen moving, or "forever" if it was never seen (observe_neighbour's rules)
            tracker.observe_neighbour(o, t, 0.0, False)
    speed = float(np.hypot(st.v[0], st.v[1]))
    # driving: "moving" needs no geometry (the same decision, for a fraction of the cost)
    quick = tracker.moving_decision(t, speed)
    if quick is not None:
        dec, changed = quick
    else:
        ne = np.array(pymap3d.geodetic2ned(st.lat, st.lon, st.h, *origin_llh, deg=False)[:2])
        nb_ne = {}
        if known:  # one vectorised conversion for all neighbours
            llh = np.array([v[0] for v in known.values()])
            n, e, _ = pymap3d.geodetic2ned(llh[:, 0], llh[:, 1], llh[:, 2], *origin_llh, deg=False)
            nb_ne = {o: np.array([n[i], e[i]]) for i, o in enumerate(known)}
        nb_cov = {o: cov[:2, :2] for o, (_, cov) in known.items()}
        dec, changed = tracker.decide(t, ne, f.position_cov[:2, :2], float(quat_to_euler(st.q)[2]),
                                      speed, nb_ne, nb_cov)
    if changed:
        f.last_stop_line = -math.inf
    if tracker.since is None:  # moving: the stop is over
        f.end_stop()
    if dec.first:
        f.stop_line(lanes[dec.lane].approach, along_only=dec.along_only, stop_id=tracker.since, lane=dec.lane)
    if lane_map is not None and f.lane_due():
        st = f.filter.state
        ne_now = np.array(pymap3d.geodetic2ned(st.lat, st.lon, st.h, *origin_llh, deg=False)[:2])
        hit = lane_map.locate(ne_now, f.position_cov[:2, :2], float(quat_to_euler(st.q)[2]),
                              lane_row_markings(tracker.markings, t), f.yaw_sigma, current=f.lane)
        f.lane_line(hit.lane if hit else None, hit.left_line if hit else None)
    return dec, changed
