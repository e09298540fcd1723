"""Microscopic traffic: lane following, Intelligent Driver Model car following, red-light stops.

Each vehicle follows its route (lanes joined by smooth Bézier turns) at a lateral offset drawn
from its d_l distribution in each lane, constant within the lane and correlated from lane to lane
by the vehicle's ``lateral_correlation`` (:func:`lane_offsets`). The state is advanced on a
0.1 s grid. At a red light the queue head stops with its front ``d_s`` (drawn from the vehicle's
stop-gap distribution) behind the stop line; followers queue behind it by IDM. A vehicle brakes
by IDM to stand at the end of its route, as behind a standing vehicle there. A vehicle too close
to stop comfortably when the light turns red proceeds (dilemma zone). Desired speed is capped by
the path curvature (2 m/s² lateral acceleration in turns), and a driver brakes for a turn ahead
at the rate it needs once that reaches IDM's comfortable deceleration; a driver faster than its
desired speed slows at most at that comfortable rate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slcp.geo.site import offset_polyline

from .geometry import Path, bezier_turn
from .scenario import Idm, Scenario, VehicleSpec

STEP = 0.1  #: traffic time step [s]
LAT_ACCEL_MAX = 2.0  #: lateral acceleration used to cap speed in turns [m/s²]
STOP_DECEL_MAX = 3.5  #: deceleration above which a driver runs the amber [m/s²]
STOPPED_SPEED = 0.05  #: below this a vehicle counts as stopped [m/s]
#: [m] how far ahead a driver heeds the end of its route, which stands for the edge of the
#: emulated world, not for an obstacle: enough to stop from 15 m/s at IDM's comfortable 2 m/s²
#: (56 m); any farther, IDM's interaction term, (s*/gap)², would slow free-flowing vehicles
END_LOOKAHEAD = 60.0
FIRST_STOP_GATE = 15.0  #: a stopped queue head within this of its stop line is "first stopped" [m]
#: [m] how far before a merge point two drivers heed each other: at 12 m/s, 3.3 s to open a
#: gap at the comfortable 2 m/s², about 11 m, more than IDM's desired gap at turning speeds
MERGE_HORIZON = 40.0


@dataclass
class Segment:
    """A stretch of a route: a lane or a turn connecting two lanes."""

    key: str  #: lane id, or "A>B" for the turn from lane A to lane B
    s0: float  #: start arc length on the route [m]
    s1: float  #: end arc length [m]
    stop_line: bool  #: a lane ending in a stop line (at s1)


@dataclass
class Route:
    path: Path
    segments: list[Segment]

    def segment(self, key: str) -> Segment | None:
        """The route's first segment with this key (a lane id or "A>B"), or None."""
        for seg in self.segments:
            if seg.key == key:
                return seg
        return None

    def segment_at(self, s: float) -> Segment:
        for seg in self.segments:
            if s < seg.s1:
                return seg
        return self.segments[-1]

    def next_stop_line(self, s: float) -> Segment | None:
        for seg in self.segments:
            if seg.stop_line and seg.s1 > s:
                return seg
        return None


def build_route(scn: Scenario, v: VehicleSpec, lateral_offsets: Sequence[float]) -> Route:
    """Route polyline (each lane of the route shifted right of its centre by its entry of
    ``lateral_offsets`` [m], one per lane; turns join them) and segments."""
    pts: list[np.ndarray] = []
    segs: list[Segment] = []
    s = 0.0
    lanes = [scn.lanes[x] for x in v.route]
    if len(lateral_offsets) != len(lanes):
        raise ValueError(f"{len(lateral_offsets)} lateral offsets for the {len(lanes)} lanes of {v.id}'s route")
    for i, ln in enumerate(lanes):
        cl = offset_polyline(ln.centerline, float(lateral_offsets[i]))
        if i == 0:
            pts.append(cl)
        else:
            prev = lanes[i - 1]
            turn = bezier_turn(pts[-1][-1], prev.end_heading, cl[0], ln.start_heading)
            tl = float(np.sum(np.linalg.norm(np.diff(turn, axis=0), axis=1)))
            segs.append(Segment(f"{prev.id}>{ln.id}", s, s + tl, False))
            s += tl
            pts.append(turn[1:])
            pts.append(cl[1:] if np.linalg.norm(cl[0] - turn[-1]) < 1e-9 else cl)
        ll = float(np.sum(np.linalg.norm(np.diff(cl, axis=0), axis=1)))
        segs.append(Segment(ln.id, s, s + ll, ln.stop_line))
        s += ll
    segs[-1].stop_line = False  # the end of a route is not a stop
    return Route(Path(np.vstack(pts)), segs)


@dataclass
class TrafficResult:
    """Per-vehicle arc length on its route at ``t`` (0.1 s grid) and the drawn parameters."""

    t: np.ndarray
    routes: dict[str, Route]
    s: dict[str, np.ndarray]
    v: dict[str, np.ndarray]
    stop_gap: dict[str, float]
    #: d_l in each lane of the route, the first lane's first (:func:`lane_offsets`)
    lane_lateral: dict[str, tuple[float, ...]]

    @property
    def lateral(self) -> dict[str, float]:
        """d_l in each route's first lane [m] (NaN where no offset was drawn: external
        trajectories)."""
        return {vid: d[0] if d else math.nan for vid, d in self.lane_lateral.items()}


def _idm_accel(v: float, v0: float, gap: float, dv: float, p: Idm) -> float:
    """IDM's acceleration, its free-road term bounded below by −b: a driver above the desired
    speed (a turn ahead, a start faster than wanted) slows at most at the comfortable rate, as
    in Treiber and Kesting's improved IDM; plain IDM's a (1 − (v/v0)^δ) asks for 9 m/s² at 1.7
    times v0. The interaction term (a leader, a red light) is unbounded, as in IDM."""
    s_star = p.s0 + max(0.0, v * p.T + v * dv / (2.0 * math.sqrt(p.a * p.b)))
    free = max(p.a * (1.0 - (v / v0) ** p.delta), -p.b)
    return float(free - p.a * (s_star / max(gap, 0.1)) ** 2)


def _turn_braking(route: Route, sk: float, vk: float, veh: VehicleSpec) -> tuple[float, float]:
    """The turns' hold on a driver at arc length ``sk`` and speed ``vk``: the speed it may drive
    here, √(a_lat / |κ|) capped by its desired speed [m/s], and the deceleration it needs to be
    down to that speed at every point of the turns ahead [m/s²] (0 if none). A cap on the next
    metres alone arrives as a step when a turn comes into view (IDM then brakes at 9 m/s², and
    still enters a 3 m radius at 6 m/s); a driver brakes instead, as for a stop, at the rate
    the turn needs once it reaches IDM's comfortable deceleration b."""
    b, v_d = veh.idm.b, veh.desired_speed
    horizon = max(30.0, v_d * v_d / (2.0 * b) + 10.0)  # enough to slow from the desired speed
    ahead = np.linspace(sk, sk + horizon, int(horizon / 1.0) + 1)
    kappa = np.abs(route.path.curvature(ahead))
    here = v_d if kappa[0] <= 1e-6 else min(v_d, math.sqrt(LAT_ACCEL_MAX / kappa[0]))
    bend = kappa > 1e-6
    if not bend.any():
        return here, 0.0
    vc2 = LAT_ACCEL_MAX / kappa[bend]
    dist = np.maximum(ahead[bend] - sk, 0.5)
    need = float(np.max((vk * vk - vc2) / (2.0 * dist)))
    return here, max(need, 0.0)


def driver_draws(scn: Scenario, rng: np.random.Generator) -> dict[str, tuple[float, float]]:
    """Where each driver stands in its lane, drawn from ``rng`` in the scenario's vehicle order:
    vehicle -> (stop gap d_s, lateral offset d_l) [m], from ``VehicleSpec.stop_gap`` and
    ``VehicleSpec.lateral`` (mean, σ). These are the traffic model's only random draws."""
    return {veh.id: (float(rng.normal(*veh.stop_gap)), float(rng.normal(*veh.lateral))) for veh in scn.vehicles}


def lane_offsets(scn: Scenario, draws: dict[str, tuple[float, float]],
                 rng: np.random.Generator) -> dict[str, tuple[float, ...]]:
    """Each driver's d_l in every lane of its route [m] (right of the lane's left line): in the
    first lane its draw of :func:`driver_draws`, in each next lane a new draw correlated with the
    last by ``VehicleSpec.lateral_correlation`` ρ, a first-order Gauss-Markov chain over the
    lanes: d_j = m + ρ (d_{j-1} − m) + √(1 − ρ²) σ ε_j, ε_j ~ N(0, 1), with (m, σ) the vehicle's
    ``lateral``. Drawn from ``rng`` after :func:`driver_draws`, in vehicle and route order, one
    ε per lane whatever ρ: the stop gaps and the first lanes' offsets stay those of the draws."""
    out = {}
    for veh in scn.vehicles:
        m, sigma = veh.lateral
        rho = veh.lateral_correlation
        d = [draws[veh.id][1]]
        for _ in veh.route[1:]:
            d.append(m + rho * (d[-1] - m) + math.sqrt(max(0.0, 1.0 - rho * rho)) * sigma * float(rng.normal()))
        out[veh.id] = tuple(d)
    return out


def _leader(vid: str, veh: VehicleSpec, route: Route, sk: float, vk: float, pos: dict[str, tuple[Segment, float]],
            specs: dict[str, VehicleSpec], v: dict[str, np.ndarray], k: int, t: float) -> tuple[float, float]:
    """IDM's gap [m] and closing speed [m/s] to what is ahead of vehicle ``vid`` at step ``k``
    (time ``t`` [s]): the nearest departed vehicle ahead on a segment its route also uses, or the
    end of its route. A vehicle waiting for its departure is parked off the lane: it joins the
    lane, and becomes a leader, when it departs."""
    gap, dv = math.inf, 0.0
    for oid, (oseg, os_) in pos.items():
        if oid == vid or t < specs[oid].depart:  # not yet departed: parked off the lane
            continue
        mine = route.segment(oseg.key)
        if mine is None:
            continue
        o_on_me = mine.s0 + (os_ - oseg.s0)
        # other vehicle's rear relative to my front (reference points are l0 behind fronts)
        g = (o_on_me + specs[oid].l0 - specs[oid].length) - (sk + veh.l0)
        if o_on_me > sk and g < gap:
            gap, dv = g, vk - v[oid][k]
    # the route's end: a standing obstacle the driver brakes for, to stand at the end; without
    # it the end is a wall, a stop from cruising speed in one 0.1 s step, which no vehicle makes
    # (and which the neighbours' misbehaviour checks rightly take for a forged stop)
    g = route.path.length - sk + veh.idm.s0
    if g < min(gap, END_LOOKAHEAD):
        gap, dv = g, vk
    return gap, dv


class _MergeTable:
    """Where one route joins another, per ordered pair of vehicles, worked out once."""

    def __init__(self, routes: dict[str, Route]) -> None:
        self.routes = routes
        self.pairs: dict[tuple[str, str], list[tuple[float, float]]] = {}

    def __call__(self, vid: str, oid: str) -> list[tuple[float, float]]:
        """Where ``oid``'s route joins ``vid``'s: for each segment of ``oid``'s route that
        ``vid``'s also has, in ``oid``'s order, its start on ``oid``'s route and on ``vid``'s [m]."""
        got = self.pairs.get((vid, oid))
        if got is None:
            route = self.routes[vid]
            got = [(seg.s0, mine.s0) for seg in self.routes[oid].segments
                   if (mine := route.segment(seg.key)) is not None]
            self.pairs[(vid, oid)] = got
        return got


def _merge_leader(vid: str, veh: VehicleSpec, route: Route, sk: float, vk: float,
                  pos: dict[str, tuple[Segment, float]], specs: dict[str, VehicleSpec], v: dict[str, np.ndarray],
                  k: int, t: float, held: dict[str, float],
                  merges: _MergeTable) -> tuple[float, float]:
    """IDM's gap [m] and closing speed [m/s] to the vehicle that enters a lane of ``vid``'s route
    before it, from another route (two turns into one exit lane): the one nearer to the merge
    point (ties by id), within :data:`MERGE_HORIZON` of it as ``vid`` is, free to go (not held
    by a red stop line before the merge point; ``held``: vehicle -> where its red line is) and
    not yet on a segment of ``vid``'s route (:func:`_leader` finds it there). It stands on
    ``vid``'s route at its own distance before the merge point, so that the later driver
    follows it by IDM before the merge and the handover to :func:`_leader` at the merge point
    is continuous. (inf, 0) if none."""
    gap, dv = math.inf, 0.0
    for oid, (oseg, os_) in pos.items():
        if oid == vid:
            continue
        joins = merges(vid, oid)  # most pairs never share a lane: nothing more to look at
        if not joins or t < specs[oid].depart or route.segment(oseg.key) is not None:
            continue
        for o_start, my_start in joins:
            if o_start <= os_:
                continue
            d_me, d_o = my_start - sk, o_start - os_
            if (0.0 < d_me <= MERGE_HORIZON and d_o <= MERGE_HORIZON and (d_o, oid) < (d_me, vid)
                    and held.get(oid, math.inf) > o_start):
                g = (my_start - d_o + specs[oid].l0 - specs[oid].length) - (sk + veh.l0)
                if g < gap:
                    gap, dv = g, vk - v[oid][k]
            break  # only the first lane where the other joins my route
    return gap, dv


def _red_held(scn: Scenario, routes: dict[str, Route], specs: dict[str, VehicleSpec], at: dict[str, float],
              t: float, committed: dict[tuple[str, str], bool]) -> dict[str, float]:
    """Vehicle -> where its next stop line is on its route [m], for the vehicles a red light
    holds there at time ``t`` (not committed to run the amber, front not past the line)."""
    out = {}
    for vid, route in routes.items():
        line = route.next_stop_line(at[vid])
        if (line is not None and not scn.signals.is_green(line.key, t) and not committed.get((vid, line.key), False)
                and line.s1 - (at[vid] + specs[vid].l0) > -0.5):
            out[vid] = line.s1
    return out


def simulate_traffic(scn: Scenario, rng: np.random.Generator) -> TrafficResult:
    """Run the traffic model over the scenario duration."""
    n = int(round(scn.duration / STEP)) + 1
    t = np.arange(n) * STEP
    routes, s, v, gaps = {}, {}, {}, {}
    draws = driver_draws(scn, rng)
    per_lane = lane_offsets(scn, draws, rng)
    for veh in scn.vehicles:
        d_s = draws[veh.id][0]
        # d_l is measured from the lane's left line: the centre line shifts by d_l - width/2
        shifts = [d - scn.lanes[x].width / 2.0 for d, x in zip(per_lane[veh.id], veh.route)]
        routes[veh.id] = build_route(scn, veh, shifts)
        gaps[veh.id] = max(d_s, 0.2)
        s[veh.id] = np.zeros(n)
        v[veh.id] = np.zeros(n)
        s[veh.id][0] = veh.depart_pos
        v[veh.id][0] = veh.initial_speed
    specs = {veh.id: veh for veh in scn.vehicles}
    committed: dict[tuple[str, str], bool] = {}
    # the turns' hold depends on the position and speed only: a standing vehicle reuses it
    turn_hold: dict[str, tuple[float, float, tuple[float, float]]] = {}
    merges = _MergeTable(routes)
    for k in range(n - 1):
        tk = t[k]
        pos = {vid: (routes[vid].segment_at(s[vid][k]), s[vid][k]) for vid in routes}
        red_held = _red_held(scn, routes, specs, {vid: s[vid][k] for vid in routes}, tk, committed)
        for vid, veh in specs.items():
            sk, vk = s[vid][k], v[vid][k]
            route = routes[vid]
            if tk < veh.depart:  # parked off the lane until departure
                s[vid][k + 1], v[vid][k + 1] = sk, 0.0
                continue
            gap, dv = _leader(vid, veh, route, sk, vk, pos, specs, v, k, tk)
            # red light: virtual obstacle so that the front stops d_s before the stop line
            stop = route.next_stop_line(sk)
            if stop is not None and not scn.signals.is_green(stop.key, tk):
                front_to_line = stop.s1 - (sk + veh.l0)
                key = (vid, stop.key)
                if key not in committed:
                    committed[key] = front_to_line < vk * vk / (2 * STOP_DECEL_MAX) and front_to_line < 15.0
                if not committed[key] and front_to_line > -0.5:
                    g = front_to_line - gaps[vid] + veh.idm.s0
                    if g < gap:
                        gap, dv = g, vk
            elif stop is not None:
                committed.pop((vid, stop.key), None)
            held = turn_hold.get(vid)
            if held is not None and held[0] == sk and held[1] == vk:
                v_here, need = held[2]
            else:
                v_here, need = _turn_braking(route, sk, vk, veh)
                turn_hold[vid] = (sk, vk, (v_here, need))
            acc = _idm_accel(vk, max(v_here, 0.1), gap, dv, veh.idm)
            m_gap, m_dv = _merge_leader(vid, veh, route, sk, vk, pos, specs, v, k, tk, red_held, merges)
            if m_gap < math.inf:  # a merging vehicle ahead: made room for at the comfortable rate
                acc = min(acc, max(_idm_accel(vk, max(v_here, 0.1), m_gap, m_dv, veh.idm), -veh.idm.b))
            if need >= veh.idm.b:  # a turn ahead: brake at the rate it needs
                acc = min(acc, -need)
            acc = max(acc, -9.0)
            vn = max(0.0, vk + acc * STEP)
            ds = 0.5 * (vk + vn) * STEP
            sn = min(sk + ds, route.path.length)
            if sn >= route.path.length:
                vn = 0.0
            s[vid][k + 1], v[vid][k + 1] = sn, vn
    return TrafficResult(t, routes, s, v, gaps, per_lane)


def first_stopped_flags(scn: Scenario, traffic: TrafficResult) -> dict[str, np.ndarray]:
    """Per vehicle and traffic step: departed, stopped, on an approach lane within the gate of
    its stop line, and no other departed vehicle on that lane between it and the stop line (a
    vehicle waiting to depart is parked off the lane)."""
    depart = {veh.id: veh.depart for veh in scn.vehicles}
    out = {}
    for vid, route in traffic.routes.items():
        flags = np.zeros(len(traffic.t), bool)
        for k in range(len(traffic.t)):
            sk = traffic.s[vid][k]
            seg = route.segment_at(sk)
            if (traffic.t[k] < depart[vid] or traffic.v[vid][k] > STOPPED_SPEED or not seg.stop_line
                    or seg.s1 - sk > FIRST_STOP_GATE + 5.0):
                continue
            ahead = False
            for oid, oroute in traffic.routes.items():
                if oid == vid or traffic.t[k] < depart[oid]:
                    continue
                oseg = oroute.segment_at(traffic.s[oid][k])
                if oseg.key == seg.key and traffic.s[oid][k] - oseg.s0 > sk - seg.s0:
                    ahead = True
                    break
            flags[k] = not ahead
        out[vid] = flags
    return out
