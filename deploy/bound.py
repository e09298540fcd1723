"""The physical limit: posterior Cramér-Rao bound (PCRLB) on every vehicle's horizontal position.

Tichavský, Muravchik & Nehorai (1998): for a linear-Gaussian model the PCRLB recursion is the
Kalman covariance recursion with the measurement Jacobians taken at the *true* states, so the
bound is computed as a covariance-only filter on the joint state of all vehicles, on the
scenario's true trajectories:

- per vehicle: horizontal position and velocity (constant velocity driven by the IMU's velocity
  random walk; the true acceleration is a known input and does not change the bound), GNSS
  multipath (2, Gauss-Markov with the receiver's moving/static τ following the true motion), and
  the stop gap errors (d_s, d_l) of the current stop (2, random constants drawn at each stop),
  and the driver's lateral offset in its lane (1, a random constant in each lane, correlated from
  lane to lane as the scenario's drivers draw it; with lane keeping it is also the stop-line
  fix's d_l);
- shared by all vehicles: the GNSS common-mode error (2, Gauss-Markov).

Information, at the GNSS rate: GNSS position (white noise on top of multipath + common mode) and
velocity; for a vehicle that is truly first stopped, the stop-line fix (its error is the stop
gap error state, so repeated fixes share it), from the step in whose interval it stops (the
bound at a step stands for the whole interval, :meth:`Bound.at`); for the SL methods with lane
keeping, wherever a vehicle truly drives in a lane of the map, its distance right of the left
lane line (on the
offset state, to the map's error); for every pair, UWB ranges at the UWB rate with
information ``(p/σ²) [uuᵀ, −uuᵀ; −uuᵀ, uuᵀ]``, where ``p`` is the probability that the range
is measured *and* the neighbour's beacon arrives. Everything the bound leaves out (IMU biases and
attitude, NLOS, outliers, GNSS outages) only adds error, so the bound stays a lower bound.

The four methods use subsets of the information: SP (GNSS), SL-SP (+ stop line, lanes), CP
(+ ranges), SL-CP (all). The cooperative bounds process the whole fleet's information jointly (a
bound for any distributed scheme); the others bound each vehicle on its own data. Pure numpy;
no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slcp.agent.lane_map import LaneMap
from slcp.agent.methods import METHODS, STOP_LINE_MAP_SIGMA, MethodSpec
from slcp.agent.nav.measurements.stop_line import stop_line_fix
from slcp.geo import earth
from slcp.hw_emulation.truth import ScenarioTruth

from .agent_configs import approach_lanes, lane_map

_NV = 9  # per vehicle: p (2), v (2), multipath (2), stop gap (2), lane offset (1)
#: what the driver's lateral offset in a lane is (:func:`posterior_crlb`)
LANE_OFFSET_MODELS = ("scenario", "vehicle", "lane")


@dataclass(frozen=True)
class Bound:
    """Bound per method and vehicle at times ``t``."""

    t: np.ndarray  #: (n,) [s]
    cov: dict[tuple[str, str], np.ndarray]  #: (method, vehicle) -> (n, 2, 2) horizontal covariance [m²]

    def sigma_h(self, method: str, vehicle: str) -> np.ndarray:
        """Horizontal bound ``sqrt(P_nn + P_ee)`` [m], shape (n,)."""
        c = self.cov[(method, vehicle)]
        return np.sqrt(c[:, 0, 0] + c[:, 1, 1])

    def at(self, method: str, vehicle: str, t: np.ndarray) -> np.ndarray:
        """Horizontal bound at times ``t`` (the latest bound step not after each time)."""
        k = np.clip(np.searchsorted(self.t, np.asarray(t, float) + 1e-9) - 1, 0, len(self.t) - 1)
        return self.sigma_h(method, vehicle)[k]


def map_ne(llh: np.ndarray, origin: tuple[float, float, float]) -> np.ndarray:
    """North and east [m], shape (n, 2), of geodetic points ``llh`` (rad, rad, m; shape (n, 3))
    in the scenario's map frame at ``origin``: the tangent plane scaled by the origin's radii of
    curvature (within millimetres of the exact local NED over an intersection's few hundred m)."""
    rm, rn = earth.radii(origin[0])
    return np.column_stack([(llh[:, 0] - origin[0]) * (rm + origin[2]),
                            (llh[:, 1] - origin[1]) * (rn + origin[2]) * np.cos(origin[0])])


def posterior_crlb(truth: ScenarioTruth, methods: tuple[str, ...] = METHODS, rate: float | None = None,
                   lane_constraint: bool = True, lane_offset: str = "scenario",
                   vehicles: tuple[str, ...] | None = None) -> Bound:
    """The bound for ``methods`` on the scenario's truth, stepping at ``rate`` Hz (default: GNSS).

    With ``lane_constraint`` the SL methods' bounds also hold the lane-keeping information:
    wherever a vehicle drives in a lane, its distance right of the left lane line is d_l, known
    to the map's error. ``lane_offset`` says what d_l is:

    - ``"scenario"`` (the bound proper): as the scenario's drivers draw it, a random constant in
      each lane, a first-order Gauss-Markov chain from lane to lane with the vehicle's
      ``lateral_correlation`` ρ (:func:`hw_emulation.traffic.lane_offsets`);
    - ``"vehicle"``: one random constant per vehicle over its whole route (ρ = 1 whatever the
      scenario says): the bound of a world whose drivers never change their offset;
    - ``"lane"``: a new, independent constant in each lane (ρ = 0), as the filters model it: the
      bound of an estimator with the filters' driver model (the same as ``"scenario"`` where the
      scenario's ρ is 0, the default).

    ``vehicles`` restricts the fleet to these ids (default: all): the cooperative bounds then
    process only their information, as if the others were not there, which tells how much of
    a vehicle's bound comes from which neighbours. The result holds these vehicles only.
    """
    if lane_offset not in LANE_OFFSET_MODELS:
        raise ValueError(f"lane_offset {lane_offset!r}: choose from {', '.join(LANE_OFFSET_MODELS)}")
    scn = truth.scenario
    specs = {v.id: v for v in scn.vehicles}
    ids = sorted(truth.vehicles)
    if vehicles is not None:
        unknown = sorted(set(vehicles) - set(ids))
        if unknown or not vehicles:
            raise ValueError(f"vehicles {', '.join(unknown) or '(none)'} not in scenario {scn.name!r} "
                             f"(it has {', '.join(ids)})")
        ids = sorted(set(vehicles))
    rate = rate or max(specs[v].gnss.rate for v in ids)
    t0 = float(truth.vehicles[ids[0]].truth.t[0])
    t1 = float(truth.vehicles[ids[0]].truth.t[-1])
    ts = np.arange(t0, t1 + 1e-9, 1.0 / rate)
    # truth at the bound steps: map-frame positions, stop flags, lanes
    pos, moving, first, lane, present = {}, {}, {}, {}, {}
    o = scn.origin_llh
    for vid in ids:
        tr = truth.vehicles[vid]
        k = tr.samples_over(ts)
        pos[vid] = map_ne(tr.truth.llh[k], o)
        # off the air (a vehicle of external trajectories before or after its samples): no information
        present[vid] = tr.present_over(ts)
        moving[vid] = ~tr.stopped[k]
        # first stopped at any instant of the step's interval [t_k, t_k+1): the bound at step k
        # stands for the whole interval (``Bound.at``), and a detector may claim (and fix) as
        # soon as the vehicle stops within it; more information only lowers a lower bound
        k_end = np.r_[k[1:], len(tr.truth.t)]
        first[vid] = np.array([tr.first_stopped[i:max(j, i + 1)].any() for i, j in zip(k, k_end)])
        lane[vid] = tr.segment[k]
    lanes = approach_lanes(scn)
    lmap = lane_map(scn) if lane_constraint else None
    rho = {vid: {"scenario": specs[vid].lateral_correlation, "vehicle": 1.0, "lane": 0.0}[lane_offset] for vid in ids}
    out = {}
    for m in methods:
        spec = MethodSpec.of(m)
        if spec.ranges:  # the fleet's information, processed jointly: a bound for any distributed scheme
            covs = _run(scn, specs, ids, ts, pos, moving, first, lane, lanes, spec.stop_line, True,
                        lmap if spec.stop_line else None, rho, present)
        else:  # a vehicle on its own (the common-mode error is not learned from the others)
            covs = {}
            for vid in ids:
                covs.update(_run(scn, specs, [vid], ts, pos, moving, first, lane, lanes, spec.stop_line, False,
                                 lmap if spec.stop_line else None, rho, present))
        for vid in ids:
            out[(m, vid)] = covs[vid]
    return Bound(ts, out)


I2 = np.eye(2)
#: the information of one GNSS position fix on (position, multipath, common mode), per unit weight:
#: the fix sees their sum, axis by axis
GNSS_ROWS = np.kron(np.ones((3, 3)), I2)


def _run(scn, specs, ids, ts, pos, moving, first, lane, lanes, use_sl: bool, use_ranges: bool,
         lmap: LaneMap | None = None, lane_correlation: dict[str, float] | None = None,
         present: dict | None = None) -> dict:
    """The bound's recursion over the steps ``ts`` for the vehicles ``ids`` (see the module's
    docstring); ``lane_correlation``: per vehicle, the correlation ρ of its lateral offsets in
    consecutive lanes (default: 1, one offset kept on the whole route)."""
    n_v = len(ids)
    n = _NV * n_v + 2
    P = _prior(scn, specs, ids)
    p_radio = 1.0 - scn.radio.expected_loss()
    ranges_per_step = scn.uwb.rate / (1.0 / (ts[1] - ts[0])) if len(ts) > 1 else 1.0
    out = {vid: np.zeros((len(ts), 2, 2)) for vid in ids}
    was_first = {vid: False for vid in ids}
    kept_lane: dict[str, str | None] = {vid: None for vid in ids}  # the lane whose offset the state is
    for k, _t in enumerate(ts):
        if lane_correlation is not None and lmap is not None:
            _next_lane_offsets(P, specs, ids, lane, k, lmap, kept_lane, lane_correlation)
        if k > 0:
            P = _predict(P, scn, specs, ids, moving, k, ts[k] - ts[k - 1])
        info = np.zeros((n, n))
        on = np.array([present is None or bool(present[vid][k]) for vid in ids])
        for i, vid in enumerate(ids):
            if on[i]:
                _own_information(info, P, i, vid, specs[vid], k, first, lane, pos, lanes, lmap, use_sl,
                                 was_first[vid])
            was_first[vid] = bool(first[vid][k])
        if use_ranges and n_v > 1:
            _range_information(info, scn, ids, pos, k, p_radio * ranges_per_step, on)
        P = np.linalg.inv(np.linalg.inv(P) + info)
        P = 0.5 * (P + P.T)
        for i, vid in enumerate(ids):
            out[vid][k] = P[_NV * i:_NV * i + 2, _NV * i:_NV * i + 2]
    return out


def _prior(scn, specs, ids) -> np.ndarray:
    """The joint prior: per vehicle position, velocity, multipath, stop-gap errors and lane
    offset; the common mode last."""
    n = _NV * len(ids) + 2
    P = np.zeros((n, n))
    for i, vid in enumerate(ids):
        b = _NV * i
        g = specs[vid].gnss
        P[b:b + 2, b:b + 2] = np.eye(2) * 100.0**2
        P[b + 2:b + 4, b + 2:b + 4] = np.eye(2) * 10.0**2
        P[b + 4:b + 6, b + 4:b + 6] = np.eye(2) * g.multipath_h**2
        sg = specs[vid]
        P[b + 6:b + 8, b + 6:b + 8] = np.diag([sg.stop_gap[1] ** 2, sg.lateral[1] ** 2])
        P[b + 8, b + 8] = sg.lateral[1] ** 2
    P[n - 2:, n - 2:] = np.eye(2) * scn.common_mode_sigma**2
    return P


def _next_lane_offsets(P, specs, ids, lane, k: int, lmap: LaneMap, kept_lane: dict, rho: dict[str, float]) -> None:
    """A vehicle entering a new lane draws its offset there: o ← ρ o + w, Var w = (1 − ρ²) σ²
    (the deviation from the mean; ρ = 0 a new independent draw, ρ = 1 the same offset)."""
    for i, vid in enumerate(ids):
        ln = str(lane[vid][k])
        if ln in lmap.marks and ln != kept_lane[vid]:
            r = rho[vid]
            if kept_lane[vid] is not None and r < 1.0:
                o = _NV * i + 8
                P[o, :] *= r
                P[:, o] *= r
                P[o, o] += (1.0 - r * r) * specs[vid].lateral[1] ** 2
            kept_lane[vid] = ln


def _predict(P, scn, specs, ids, moving, k: int, dt: float) -> np.ndarray:
    """Every vehicle's white-acceleration motion and Gauss-Markov multipath, and the common
    mode, over ``dt`` [s]."""
    n = len(P)
    ic = slice(n - 2, n)
    F = np.eye(n)
    Q = np.zeros((n, n))
    for i, vid in enumerate(ids):
        b = _NV * i
        g, imu = specs[vid].gnss, specs[vid].imu
        F[b:b + 2, b + 2:b + 4] = np.eye(2) * dt
        q = imu.vrw**2  # white acceleration: [[dt³/3, dt²/2], [dt²/2, dt]] q on (p, v), per axis
        Q[b:b + 2, b:b + 2] = I2 * (dt**3 / 3 * q)
        Q[b:b + 2, b + 2:b + 4] = Q[b + 2:b + 4, b:b + 2] = I2 * (dt**2 / 2 * q)
        Q[b + 2:b + 4, b + 2:b + 4] = I2 * (dt * q)
        tau = g.multipath_tau_moving if moving[vid][k] else g.multipath_tau_static
        a = np.exp(-dt / tau)
        F[b + 4:b + 6, b + 4:b + 6] = np.eye(2) * a
        Q[b + 4:b + 6, b + 4:b + 6] = np.eye(2) * g.multipath_h**2 * (1 - a * a)
    a = np.exp(-dt / scn.common_mode_tau)
    F[ic, ic] = np.eye(2) * a
    Q[ic, ic] = np.eye(2) * scn.common_mode_sigma**2 * (1 - a * a)
    return F @ P @ F.T + Q


def _own_information(info, P, i: int, vid: str, sg, k: int, first, lane, pos, lanes, lmap: LaneMap | None,
                     use_sl: bool, was_first: bool) -> None:
    """Vehicle ``i``'s own information at step ``k``: its GNSS position and velocity, and its
    stop-line fix while first stopped or else its lane keeping (a new stop redraws the gap
    errors in ``P``)."""
    n = len(P)
    b = _NV * i
    g = sg.gnss
    # GNSS position: z = p + multipath + common + white (rows on p, m, c)
    cols = np.r_[b:b + 2, b + 4:b + 6, n - 2:n]
    info[np.ix_(cols, cols)] += GNSS_ROWS / max(g.white_h, 0.05) ** 2
    info[b + 2:b + 4, b + 2:b + 4] += np.eye(2) / max(g.velocity_white, 0.02) ** 2
    ln = str(lane[vid][k])
    if use_sl and first[vid][k] and ln in lanes:
        if not was_first:  # a new stop draws new gap errors
            s = slice(b + 6, b + 8)
            P[s, :] = 0.0
            P[:, s] = 0.0
            P[s, s] = np.diag([sg.stop_gap[1] ** 2, sg.lateral[1] ** 2])
        _, J = stop_line_fix(lanes[ln].approach, sg.stop_gap[0] + sg.l0, sg.lateral[0])
        Hs = np.hstack([np.eye(2), -J])  # on (p, gap errors); the lane's offset is d_l's
        cols = np.r_[b:b + 2, b + 6, b + 8 if lmap is not None else b + 7]
        info[np.ix_(cols, cols)] += Hs.T @ Hs / STOP_LINE_MAP_SIGMA**2
    elif lmap is not None and ln in lmap.marks:
        # lane keeping (the filters skip it while the full stop-line fix holds d_l)
        line = lmap.left_line_at(ln, pos[vid][k])
        h = np.r_[line.right_normal, -1.0]
        cols = np.r_[b:b + 2, b + 8]
        info[np.ix_(cols, cols)] += np.outer(h, h) / STOP_LINE_MAP_SIGMA**2


def _range_information(info, scn, ids, pos, k: int, per_step: float, on: np.ndarray | None = None) -> None:
    """The UWB ranges of step ``k`` between every pair (of vehicles ``on`` the air), weighted by
    the chance that a range is measured and its beacon arrives (``per_step``: ranges per step
    times delivery probability)."""
    uwb, radio = scn.uwb, scn.radio
    pk = np.array([pos[v][k] for v in ids])
    ii, jj = np.triu_indices(len(ids), 1)
    d = pk[ii] - pk[jj]
    rho = np.hypot(d[:, 0], d[:, 1])
    p = uwb.success_probability(rho) * (rho <= radio.max_range) * (rho > 0.5)
    w = p * per_step / max(uwb.sigma_los, 0.01) ** 2
    if on is not None:
        w = w * (on[ii] & on[jj])
    for a, c, dd, r, wk in zip(ii, jj, d, rho, w):
        if wk <= 0.0:
            continue
        uu = wk * np.outer(dd, dd) / (r * r)
        A, C = _NV * a, _NV * c
        info[A:A + 2, A:A + 2] += uu
        info[C:C + 2, C:C + 2] += uu
        info[A:A + 2, C:C + 2] -= uu
        info[C:C + 2, A:A + 2] -= uu
