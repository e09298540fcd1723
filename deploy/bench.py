"""``slcp bench``: what a vehicle costs, measured on this machine (benchmarks print figures; they
are not timed tests).

Per-step costs in microseconds (median of repeated timings of a batch): the strapdown step alone,
the filter's IMU step (mechanisation plus its share of the 10 Hz covariance propagation), one
covariance propagation, a GNSS update (position and velocity), a UWB range update with split
CI, a stop-line fix, a first-stopped decision (driving and standing), beacon encode/decode and
sign/verify (ECDSA P-256). Then the real-time factor of the SP replay of
the shared real drive, if it is there.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from pathlib import Path

import numpy as np


def _time_us(fn, n: int, repeats: int = 5) -> float:
    """Median over ``repeats`` of the mean time of ``n`` calls [µs]."""
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        out.append((time.perf_counter() - t0) / n * 1e6)
    return statistics.median(out)


def micro_benchmarks(quick: bool = False) -> dict[str, float]:
    """Step costs [µs] of the pieces of an agent, on paper-1's V1 at its stop."""
    from slcp.agent.methods import MethodFilter, MethodSpec, initial_state
    from slcp.agent.nav.mechanization import mechanize_fast
    from slcp.agent.neighbours import NeighbourState
    from slcp.geo import earth
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth
    from slcp.transport.messages import Beacon

    from .agent_configs import agent_config

    scale = 0.2 if quick else 1.0
    n = lambda k: max(10, int(k * scale))  # noqa: E731 - a local shorthand
    scn = load_scenario("paper-1")
    truth = build_truth(scn)
    cfg = agent_config(scn, "V1")
    tr = truth.vehicles["V1"].truth
    k = int(np.searchsorted(tr.t, 30.0))  # standing at the stop line
    st0 = initial_state(tr.llh[k], np.zeros(3), np.array([0.0, 0.0, -9.8]))
    dth, dv, dt = tr.dtheta[k], tr.dvel[k], float(tr.t[k + 1] - tr.t[k])

    def fresh(method: str) -> MethodFilter:
        return MethodFilter(MethodSpec.of(method), st0.copy(), np.array([3.0, 3.0, 5.0]), cfg.settings,
                            float(tr.t[k]), cfg.gap, cfg.origin_llh)

    out: dict[str, float] = {}
    th_t, dv_t = tuple(dth), tuple(dv)
    out["mechanisation_us"] = _time_us(lambda: mechanize_fast(st0, th_t, dv_t, dt, None, None), n(5000))
    f = fresh("SL-CP")
    out["imu_step_us"] = _time_us(lambda: f.propagate(th_t, dv_t, dt), n(5000))
    f = fresh("SL-CP")

    def cov_step():
        f.filter._acc_dt = 0.1  # one 0.1 s covariance step on the current state
        f.filter.flush_covariance()
    out["covariance_step_us"] = _time_us(cov_step, n(500))
    llh, v = tr.llh[k].copy(), np.zeros(3)
    sig = np.array([3.0, 3.0, 5.0])
    out["gnss_update_us"] = _time_us(lambda: f.gnss(llh, v, sig, 0.05), n(500))
    rm, _ = earth.radii(float(tr.llh[k][0]))
    # 25 m south, σ 1 m: far enough for the linearisation (``range_min_sigmas``), and a range
    # that agrees, so that every rule makes the whole update
    nb = NeighbourState("V2", tr.llh[k] + np.array([-_RANGE_M / rm, 0.0, 0.0]), np.eye(3), 0.05)
    f.settings = dataclasses.replace(cfg.settings, min_gain=0.0)  # always fuse: time the whole update
    ff = f.filter
    saved = (ff.state.copy(), ff.P.copy(), None if ff.P_ind is None else ff.P_ind.copy())

    def range_step():
        # from the same prior each time: repeated fusion would walk the estimate onto the neighbour
        ff.state, ff.P = saved[0].copy(), saved[1].copy()
        ff.P_ind = None if saved[2] is None else saved[2].copy()
        return f.range(nb, _RANGE_M + 0.2)
    _require_fused(range_step())
    out["range_update_split_ci_us"] = _time_us(range_step, n(500))
    out["range_update_source_ci_us"] = _source_ci_cost(cfg, st0, float(tr.t[k]), nb, n(500))
    lane = cfg.lanes["NB_in"].approach

    def sl():
        f.last_stop_line = -math.inf
        f.stop_line(lane, stop_id=1.0)
    out["stop_line_update_us"] = _time_us(sl, n(500))
    out.update(_decision_costs(fresh, tr.llh[k], float(tr.t[k]), cfg, rm, n(500)))
    out.update(_beacon_costs(Beacon("V1", 1, "SL-CP", 30.0, tr.llh[k], v, np.eye(3)), n))
    # one vehicle running the four methods: 100 Hz IMU steps, 5 Hz GNSS, 10 Hz ranges to 2
    # neighbours for the two CP methods (the default rule), 1 Hz stop-line fix for the SL methods
    per_s = (4 * 100 * out["imu_step_us"] + 4 * 5 * out["gnss_update_us"]
             + 2 * 2 * 10 * out["range_update_source_ci_us"] + 2 * out["stop_line_update_us"])
    out["four_methods_cpu_share"] = per_s / 1e6
    return out


def _beacon_costs(b, n) -> dict[str, float]:
    """A beacon's encoding, decoding, signing and verification [µs] and its sizes [bytes]."""
    import tempfile

    from slcp.transport.codec import decode, encode
    from slcp.transport.security import BeaconSigner, TrustStore, create_fleet

    out: dict[str, float] = {}
    payload = encode(b)
    out["beacon_encode_us"] = _time_us(lambda: encode(b), n(5000))
    out["beacon_decode_us"] = _time_us(lambda: decode(payload), n(5000))
    out["beacon_bytes"] = float(len(payload))
    # with source CI's breakdown: the own part, the common-mode error, two vehicles, two links
    labels = (("V1",), ("~common",), ("V0",), ("V2",), ("V0|V1",), ("V1|V2",))
    out["beacon_bytes_source_ci"] = float(len(encode(dataclasses.replace(
        b, sources=tuple((lab, np.eye(3) / 6.0) for lab in labels)))))
    # signing (ECDSA P-256 / SHA-256 over the canonical encoding) and verifying
    with tempfile.TemporaryDirectory() as d:
        create_fleet(d, ["V1"])
        signer, store = BeaconSigner.from_file("V1", Path(d) / "V1.key"), TrustStore.from_dir(d)
    signed = signer.sign(b)
    out["beacon_sign_us"] = _time_us(lambda: signer.sign(b), n(1000))
    out["beacon_verify_us"] = _time_us(lambda: store.verify(signed), n(1000))
    out["signed_beacon_bytes"] = float(len(encode(signed)))
    return out


#: the benchmarks' neighbour distance [m]
_RANGE_M = 25.0


def _require_fused(outcome: str | None) -> None:
    """A range benchmark times the whole update: refuse to report one that gated or skipped."""
    if outcome != "fused":
        raise RuntimeError(f"the benchmark's range was not fused ({outcome}): it would time a shortcut")


def _source_ci_cost(cfg, st0, t: float, nb, n: int) -> float:
    """One source-CI range update [µs] of SL-CP, from the same prior each time, with as many
    components as the fleet's agents hold (the grid of ``--fleet``: 10-12 stored, beacons of
    12-15): eleven stored (the common-mode GNSS error, seven vehicles, three links) against a
    beacon of thirteen, most of whose sources the vehicle also holds; and exactly tracked
    constants: the vehicle's own three (stop gap, lane offset) and five of others, the beacon
    eight (the same five, three others)."""
    from slcp.agent.methods import MethodFilter, MethodSpec
    from slcp.agent.nav.source_fusion import COMMON_MODE
    from slcp.agent.neighbours import NeighbourState

    settings = dataclasses.replace(cfg.settings, fusion="source-ci", min_gain=0.0)
    f = MethodFilter(MethodSpec.of("SL-CP"), st0.copy(), np.array([3.0, 3.0, 5.0]), settings, t, cfg.gap,
                     cfg.origin_llh, vehicle="V1")
    ff = f.filter
    ff.flush_covariance()
    mine = (COMMON_MODE, "V0", "V3", "V4", "V5", "V6", "V7", "V8", "V0|V1", "V1|V3", "V1|V4")
    for lab in mine:
        ff.sources.add(frozenset({lab}), 0.02 * ff.P)
    theirs = (("V2",), (COMMON_MODE,), ("V0",), ("V1",), ("V3",), ("V4",), ("V5",), ("V6",), ("V9",),
              ("V1|V2",), ("V0|V2",), ("V2|V3",), ("V2|V9",))
    rng = np.random.default_rng(0)
    shared = [f"V{k}~1.0.000" for k in (0, 3, 4, 5, 6)]
    ff.sources.new_constants(shared, [ff.extra_offset + f._sl.start] * len(shared), 0.05)
    ff.P[ff.extra_offset + f._sl.start, ff.extra_offset + f._sl.start] += 5 * 0.05**2
    consts = tuple((lab, 0.05 * rng.normal(size=3)) for lab in shared + ["V2~1.0.000", "V2~2.0.000", "V9~1.0.000"])
    g = sum(np.outer(c, c) for _, c in consts)
    cov = (nb.cov_ned - g) / len(theirs)
    nb = NeighbourState(nb.vehicle, nb.llh, nb.cov_ned, nb.age, nb.v_ned,
                        tuple(frozenset(lab) for lab in theirs), np.array([cov] * len(theirs)), consts)
    saved = (ff.state.copy(), ff.P.copy(), ff.sources.copy())

    def step():
        ff.state, ff.P, ff.sources = saved[0].copy(), saved[1].copy(), saved[2].copy()
        return f.range(nb, _RANGE_M + 0.2)
    _require_fused(step())
    return _time_us(step, n)


def _decision_costs(fresh, llh: np.ndarray, t: float, cfg, rm: float, n: int) -> dict[str, float]:
    """One first-stopped decision [µs] with seven neighbours in the table (stopped, 20–50 m
    behind): driving at 10 m/s (no geometry needed) and standing for 1 s at the stop line (the
    map and neighbour geometry; the stop-line fix it triggers applies once, then waits for its
    interval)."""
    from slcp.agent.decision_step import first_stopped_step
    from slcp.agent.first_stopped import FirstStoppedDetector, StopTracker
    from slcp.agent.neighbours import NeighbourTable

    out = {}
    for name, speed in (("decision_moving_us", 10.0), ("decision_standing_us", 0.0)):
        f = fresh("SL-CP")
        f.filter.state.v = np.array([speed, 0.0, 0.0])
        table = NeighbourTable()
        for i in range(7):
            nb_llh = llh + np.array([-(20.0 + 5.0 * i) / rm, 0.0, 0.0])
            table.update(f"N{i}", 1, t, nb_llh, np.zeros(3), np.eye(3) * 4.0, "SL-CP", t)
        tracker = StopTracker(FirstStoppedDetector(cfg.lanes, cfg.gap))
        for nb in table.vehicles():
            tracker.observe_neighbour(nb, t - 5.0, 0.0, False)
        first_stopped_step(tracker, f, table, cfg.lanes, cfg.origin_llh, t - 1.0)  # at rest since then
        out[name] = _time_us(
            lambda tr=tracker, f=f, tab=table: first_stopped_step(tr, f, tab, cfg.lanes, cfg.origin_llh, t), n
        )
    return out


def replay_factor(path: Path, repeats: int = 3) -> dict | None:
    """Real-time factor (median of ``repeats`` runs) and accuracy of the SP replay of the
    rtklibexplorer drive (None if absent)."""
    from .datasets.rtklib import load_drive
    from .replay import ReplayConfig, run_replay
    from .vehicle_files import load_vehicle

    if not Path(path).is_dir():
        return None
    drive = load_drive(path)
    cfg = ReplayConfig(profile=load_vehicle("rtklibexplorer-drive"))
    runs = [run_replay(drive, cfg).metrics for _ in range(repeats)]
    # this VM's speed varies by ±25 % from run to run: report the median run, and all of them
    m = sorted(runs, key=lambda r: r["wall_s"])[len(runs) // 2]
    out = {k: m[k] for k in ("realtime_factor", "imu_span_s", "wall_s", "outage_h_rms_m", "outage_h_end_mean_m",
                             "outage_h_max_m")}
    out["realtime_factor_runs"] = [round(r["realtime_factor"], 1) for r in runs]
    return out
