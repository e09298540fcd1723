"""All vehicles and methods of a scenario in one process, in lockstep on sensor time.

This is the reference evaluation of the methods before the distributed fleet: the same emulated
sensors, beacons through the V2V radio model (loss, latency, range) into per-method neighbour
tables, UWB ranges fused by both ends, and first-stopped decisions from each filter's own
estimate and its neighbours' beacons (no truth).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from agent.first_stopped import FirstStoppedDetector, StopTracker
from agent.integrity import OWN_TWIN, check_separation
from agent.methods import DEFAULT_FUSION, METHODS, MethodFilter, MethodSpec, first_stopped_step, initial_state
from agent.nav import earth
from agent.nav.motion import StationarityMonitor, ZuptGate, speed_sigma
from agent.neighbours import NeighbourTable
from hw_emulation.emulate import emulate_uwb, emulate_vehicle_sensors
from hw_emulation.sensors.radio import simulate_link
from hw_emulation.truth import ScenarioTruth

from .agent_configs import agent_config, approach_lanes, lane_map


BEACON_RATE = 5.0
DECISION_RATE = 10.0
RECORD_STEP = 10


@dataclass
class RunResult:
    t: np.ndarray
    err: dict[tuple[str, str], np.ndarray]  #: (vehicle, method) -> horizontal error [m]
    sigma: dict[tuple[str, str], np.ndarray]
    first: dict[tuple[str, str], np.ndarray]  #: detector decisions at the record times
    counters: dict[tuple[str, str], dict[str, int]] = field(default_factory=dict)
    decisions: list[tuple[float, str, str, str]] = field(default_factory=list)  #: (t, vehicle, method, reason)
    #: (vehicle, method) -> signed along-track error [m] (truth heading)
    along: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    #: method -> injected error kind ("clean", "nlos", "outlier") -> range outcome -> count
    range_outcomes: dict[str, dict[str, dict[str, int]]] = field(default_factory=dict)
    #: (vehicle, method) -> horizontal NEES at the record times (n = 2)
    nees: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    #: (vehicle, method) -> horizontal error (north, east) [m], shape (n, 2), and the reported
    #: horizontal covariance [m²], shape (n, 2, 2), at the record times
    err_ne: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    cov_ne: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)


def run_inprocess(truth: ScenarioTruth, seed: int, methods: tuple[str, ...] = METHODS,
                  fusion: str = DEFAULT_FUSION) -> RunResult:
    scn = truth.scenario
    rng = np.random.default_rng(seed)
    sensors = emulate_vehicle_sensors(truth, rng)
    ranges = emulate_uwb(truth, rng)
    lanes = approach_lanes(scn)
    lmap = lane_map(scn)
    ids = sorted(truth.vehicles)
    t = truth.vehicles[ids[0]].truth.t
    dt = np.diff(t)

    filters: dict[tuple[str, str], MethodFilter] = {}
    detectors = {}
    sigma_uwb: dict[str, float] = {}
    for vid in ids:
        g = sensors[vid].gnss
        f_b = sensors[vid].imu.dvel[:10].mean(axis=0) / dt[0]
        st0 = initial_state(g.llh[0], g.v_ned[0], f_b)
        cfg = agent_config(scn, vid, methods, fusion)
        gap, settings = cfg.gap, cfg.settings
        detectors[vid] = FirstStoppedDetector(lanes, gap)
        sigma_uwb[vid] = settings.sigma_uwb
        for m in methods:
            filters[(vid, m)] = MethodFilter(MethodSpec.of(m), st0.copy(), g.sigma_ned[0], settings, float(t[0]),
                                             gap, scn.origin_llh, heading_known=np.hypot(*g.v_ned[0, :2]) > 1.0,
                                             vehicle=vid)
    tables = {(vid, m): NeighbourTable() for vid in ids for m in methods}
    trackers = {(vid, m): StopTracker(detectors[vid]) for vid in ids for m in methods if MethodSpec.of(m).stop_line}

    rest = {vid: StationarityMonitor() for vid in ids}
    zupt_gate = {vid: ZuptGate() for vid in ids}
    decisions: list[tuple[float, str, str, str]] = []
    range_outcomes: dict[str, dict[str, dict[str, int]]] = {}

    def claim_of(vid: str, m: str) -> bool:
        tr = trackers.get((vid, m))
        return tr is not None and tr.claim

    # beacon schedule and radio fates per directed pair
    step = int(round(scn.imu_rate / BEACON_RATE))
    b_idx = np.arange(step, len(t), step)
    fates = {}
    for a in ids:
        for b in ids:
            if a != b:
                la, lb = truth.vehicles[a].truth.llh[b_idx], truth.vehicles[b].truth.llh[b_idx]
                rm, rn = earth.radii(float(la[0, 0]))
                dist = np.hypot((la[:, 0] - lb[:, 0]) * rm, (la[:, 1] - lb[:, 1]) * rn * np.cos(la[:, 0]))
                fates[(a, b)] = simulate_link(scn.radio, t[b_idx], dist, rng)
    pending: list[tuple[float, str, str, str, tuple]] = []  # (arrive, sender, receiver, method, beacon)
    uwb_step = int(round(scn.imu_rate / scn.uwb.rate))
    dec_step = int(round(scn.imu_rate / DECISION_RATE))
    gnss_i = {vid: 0 for vid in ids}
    lane_i = {vid: 0 for vid in ids}
    imu = {vid: (sensors[vid].imu.dtheta.tolist(), sensors[vid].imu.dvel.tolist()) for vid in ids}
    dts = dt.tolist()
    rec_t, err, sig, first = [], {k: [] for k in filters}, {k: [] for k in filters}, {k: [] for k in filters}
    along: dict[tuple[str, str], list[float]] = {k: [] for k in filters}
    nees: dict[tuple[str, str], list[float]] = {k: [] for k in filters}
    err_ne: dict[tuple[str, str], list[np.ndarray]] = {k: [] for k in filters}
    cov_ne: dict[tuple[str, str], list[np.ndarray]] = {k: [] for k in filters}

    for k in range(len(dts)):
        tk = float(t[k + 1])
        for vid in ids:
            th, dv = imu[vid][0][k], imu[vid][1][k]
            for m in methods:
                filters[(vid, m)].propagate(th, dv, dts[k])
            g = sensors[vid].gnss
            while gnss_i[vid] < len(g.t) and g.t[gnss_i[vid]] <= tk + 1e-6:
                i = gnss_i[vid]
                if g.t[i] > t[0] + 1e-6:
                    zupt_gate[vid].gnss(float(g.t[i]))
                    for m in methods:
                        filters[(vid, m)].gnss(g.llh[i], g.v_ned[i], g.sigma_ned[i], float(g.sigma_v[i]))
                gnss_i[vid] += 1
            cam = sensors[vid].lane
            while cam is not None and lane_i[vid] < len(cam.t) and cam.t[lane_i[vid]] <= tk + 1e-6:
                i = lane_i[vid]
                for m in methods:
                    if (vid, m) in trackers:
                        trackers[(vid, m)].observe_markings(float(cam.t[i]), int(cam.classes[i, 0]),
                                                            int(cam.classes[i, 1]))
                lane_i[vid] += 1
            rest[vid].push(th, dv, dts[k], filters[(vid, methods[0])].filter.state.dcm)
            ref = filters[(vid, methods[0])].filter
            v = ref.state.v
            if zupt_gate[vid].due(tk, rest[vid], math.hypot(v[0], v[1]),
                                  lambda: speed_sigma(ref.state.v, ref.velocity_cov)):
                for m in methods:
                    filters[(vid, m)].zupt()
        # beacons: send at the schedule, deliver after the radio latency
        if (k + 1) % step == 0:
            j = (k + 1) // step - 1
            for a in ids:
                for m in methods:
                    spec = MethodSpec.of(m)
                    if not (spec.ranges or spec.stop_line):  # SL methods need beacons to detect "first"
                        continue
                    llh, v, cov = filters[(a, m)].beacon()
                    src = (filters[(a, m)].beacon_sources(), filters[(a, m)].beacon_constants())
                    for b in ids:
                        if b != a and fates[(a, b)].delivered[j]:
                            pending.append((float(fates[(a, b)].t_arrive[j]), a, b, m,
                                            (j, tk, llh, v, cov, claim_of(a, m), src)))
        if pending:
            still = []
            for item in pending:
                arrive, a, b, m, (seq, tb, llh, v, cov, claim_at_send, src) = item
                if arrive <= tk:
                    if tables[(b, m)].update(a, seq, tb, llh, v, cov, m, tk, *src) and (b, m) in trackers:
                        trackers[(b, m)].observe_neighbour(a, tb, float(np.hypot(v[0], v[1])), claim_at_send)
                else:
                    still.append(item)
            pending = still
        # UWB: one value per pair, fused by both ends
        if (k + 1) % uwb_step == 0:
            r_i = (k + 1) // uwb_step
            for (a, b), rr in ranges.items():
                if r_i >= len(rr.t) or not np.isfinite(rr.range[r_i]):
                    continue
                for me, other in ((a, b), (b, a)):
                    for m in methods:
                        if (me, m) in trackers:
                            trackers[(me, m)].observe_range(other, tk, float(rr.range[r_i]), sigma_uwb[me])
                        if MethodSpec.of(m).ranges:
                            nb = tables[(me, m)].at(other, tk)
                            if nb is not None:
                                outcome = filters[(me, m)].range(nb, float(rr.range[r_i]))
                                kind = "outlier" if rr.outlier[r_i] else "nlos" if rr.nlos[r_i] else "clean"
                                tally = range_outcomes.setdefault(m, {}).setdefault(kind, {})
                                tally[outcome] = tally.get(outcome, 0) + 1
        # first-stopped decisions and stop-line fixes
        if (k + 1) % dec_step == 0:
            for key, tr in trackers.items():
                dec, changed = first_stopped_step(tr, filters[key], tables[key], lanes, scn.origin_llh, tk,
                                                  lane_map=lmap)
                if changed:
                    decisions.append((tk, key[0], key[1], dec.reason))
            for (vid, m), f in filters.items():  # cooperative integrity against the own-sensor twin
                own = filters.get((vid, OWN_TWIN.get(m, "")))
                if own is not None:
                    check_separation(f, own)
        if (k + 1) % RECORD_STEP == 0:
            rec_t.append(tk)
            for (vid, m), f in filters.items():
                s = f.filter.state
                e = earth.ned_offset(s.lat, s.lon, s.h, *truth.vehicles[vid].truth.llh[k + 1])
                p = f.filter.position_cov
                err[(vid, m)].append(math.hypot(e[0], e[1]))
                yaw = truth.vehicles[vid].truth.euler[k + 1, 2]
                along[(vid, m)].append(e[0] * math.cos(yaw) + e[1] * math.sin(yaw))
                sig[(vid, m)].append(math.sqrt(p[0, 0] + p[1, 1]))
                eh = np.array([e[0], e[1]])
                nees[(vid, m)].append(float(eh @ np.linalg.solve(p[:2, :2], eh)))
                err_ne[(vid, m)].append(eh)
                cov_ne[(vid, m)].append(np.array(p[:2, :2]))
                first[(vid, m)].append(claim_of(vid, m))
    return RunResult(np.array(rec_t), {k: np.array(v) for k, v in err.items()},
                     {k: np.array(v) for k, v in sig.items()}, {k: np.array(v) for k, v in first.items()},
                     {k: dict(f.counters) for k, f in filters.items()}, decisions=decisions,
                     range_outcomes=range_outcomes, along={k: np.array(v) for k, v in along.items()},
                     nees={k: np.array(v) for k, v in nees.items()},
                     err_ne={k: np.array(v).reshape(-1, 2) for k, v in err_ne.items()},
                     cov_ne={k: np.array(v).reshape(-1, 2, 2) for k, v in cov_ne.items()})
