"""The bound's recursion against an independent batch computation, and closed forms that fix the
sign and the weight of the range information.

The batch reference writes the model from its description (``deploy/bound.py``'s docstring), not
from the recursion's code: every random variable of the whole trajectory (the initial state and
each step's process noise, including the new draws of a stop's gap errors and of a lane's offset)
is stacked into one vector θ, every measurement is a row on θ with its own noise, and the bound at
step k is the posterior covariance of ``x_k = L_k θ`` given the rows up to step k, in covariance
form (the prior of θ is singular: the constants get no process noise). The recursion must agree
with it to 1e-6.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from slcp.agent.methods import STOP_LINE_MAP_SIGMA
from slcp.agent.nav.measurements.stop_line import Line2D, StopLineApproach, stop_line_fix
from slcp.deploy.bound import _NV, _run
from slcp.hw_emulation.sensors.gnss import GnssModel
from slcp.hw_emulation.sensors.imu import ImuModel
from slcp.hw_emulation.sensors.radio import RadioModel
from slcp.hw_emulation.sensors.uwb import UwbModel

# per vehicle, as the bound's docstring lays them out: p 0-1, v 2-3, multipath 4-5, stop gap
# errors 6 (d_s) and 7 (d_l), lane offset 8; then the common mode (2)


def _vehicle(white: float, mp: float, tau: tuple[float, float], vw: float, vrw: float,
             gap: tuple[float, float], lat: tuple[float, float]) -> SimpleNamespace:
    g = GnssModel(white_h=white, multipath_h=mp, multipath_tau_moving=tau[0], multipath_tau_static=tau[1],
                  velocity_white=vw)
    return SimpleNamespace(gnss=g, imu=ImuModel(vrw=vrw), stop_gap=gap, lateral=lat, l0=2.5)


def _case(with_lanes: bool):
    """Two unequal vehicles, a strong common-mode error, V0 drives north and stops first at a
    stop line across its lane (steps 6-11), V1 drives east 12-20 m away; UWB at 10 Hz against
    5 Hz steps (two ranges a step) with a distance-dependent success probability and radio loss."""
    specs = {
        "V0": _vehicle(0.4, 1.5, (20.0, 200.0), 0.05, 0.02, (1.4, 0.25), (1.7, 0.12)),
        "V1": _vehicle(0.9, 2.5, (40.0, 400.0), 0.12, 0.05, (1.6, 0.35), (1.9, 0.2)),
    }
    uwb = UwbModel(rate=10.0, sigma_los=0.1, d50=15.0, d_scale=5.0)
    radio = RadioModel(loss=0.2, ge_p_good_to_bad=0.0)
    scn = SimpleNamespace(uwb=uwb, radio=radio, common_mode_sigma=1.5, common_mode_tau=60.0)
    ts = np.arange(0.0, 3.6, 0.2)
    k = len(ts)
    v0 = np.minimum(ts, 1.2)  # V0 drives north at 1 m/s and stands from 1.2 s
    pos = {"V0": np.column_stack([v0, np.zeros(k)]),
           "V1": np.column_stack([np.full(k, 3.0), 12.0 + 2.5 * ts])}
    moving = {"V0": ts < 1.2, "V1": np.ones(k, bool)}
    first = {"V0": (ts >= 1.2) & (ts < 2.3), "V1": np.zeros(k, bool)}
    lane = {"V0": np.array(["north"] * k), "V1": np.array(["east"] * (k // 2) + ["east2"] * (k - k // 2))}
    heading = math.radians(37.0)  # neither axis-aligned nor perpendicular: every J entry non-zero
    left = Line2D.from_heading((0.0, -1.7), 0.0)
    stop = Line2D.from_heading((5.0, 0.0), heading + math.pi / 2)
    lanes = {"north": SimpleNamespace(approach=StopLineApproach(stop, left))}
    lmap = None
    if with_lanes:
        lines = {"north": left, "east": Line2D.from_heading((4.5, 0.0), math.pi / 2),
                 "east2": Line2D.from_heading((4.7, 0.0), math.pi / 2 + 0.05)}
        lmap = SimpleNamespace(marks=lines, left_line_at=lambda ln, p: lines[ln])
    return scn, specs, ["V0", "V1"], ts, pos, moving, first, lane, lanes, lmap


def _batch(scn, specs, ids, ts, pos, moving, first, lane, lanes, use_sl, use_ranges, lmap, rho):
    """The bound at every step, from the stacked trajectory (see the module docstring)."""
    nv = len(ids)
    n = _NV * nv + 2
    K = len(ts)
    Fs, Qs = _transitions(scn, specs, ids, ts, moving, first, lane, lanes, use_sl, lmap, rho,
                          _batch_prior(scn, specs, ids))
    # L_k: x_k as a linear map of θ = (x_0, w_1, ..., w_K-1)
    L = [np.zeros((n, n * K)) for _ in range(K)]
    L[0][:, :n] = np.eye(n)
    for k in range(1, K):
        L[k] = Fs[k] @ L[k - 1]
        L[k][:, n * k:n * (k + 1)] += np.eye(n)
    Sigma = np.zeros((n * K, n * K))
    for k in range(K):
        Sigma[n * k:n * (k + 1), n * k:n * (k + 1)] = Qs[k]
    rows = _rows(scn, specs, ids, ts, pos, first, lane, lanes, use_sl, use_ranges, lmap)
    out = {vid: np.zeros((K, 2, 2)) for vid in ids}
    for k in range(K):
        use = [(kk, h, var) for kk, h, var in rows if kk <= k]
        M = np.vstack([h @ L[kk] for kk, h, _ in use])
        R = np.diag([var for *_, var in use])
        SMt = Sigma @ M.T
        post = Sigma - SMt @ np.linalg.solve(M @ SMt + R, SMt.T)
        Pk = L[k] @ post @ L[k].T
        for i, vid in enumerate(ids):
            out[vid][k] = Pk[_NV * i:_NV * i + 2, _NV * i:_NV * i + 2]
    return out




def _batch_prior(scn, specs, ids) -> np.ndarray:
    """The prior of the batch's first state."""
    nv = len(ids)
    n = _NV * nv + 2
    c = slice(_NV * nv, n)
    P0 = np.zeros((n, n))
    for i, vid in enumerate(ids):
        s, b = specs[vid], _NV * i
        P0[b:b + 2, b:b + 2] = np.eye(2) * 1e4
        P0[b + 2:b + 4, b + 2:b + 4] = np.eye(2) * 100.0
        P0[b + 4:b + 6, b + 4:b + 6] = np.eye(2) * s.gnss.multipath_h**2
        P0[b + 6, b + 6], P0[b + 7, b + 7] = s.stop_gap[1] ** 2, s.lateral[1] ** 2
        P0[b + 8, b + 8] = s.lateral[1] ** 2
    P0[c, c] = np.eye(2) * scn.common_mode_sigma**2
    return P0


def _transitions(scn, specs, ids, ts, moving, first, lane, lanes, use_sl, lmap, rho, P0):
    """Each step's transition F_k and noise Q_k (the prior as the first noise)."""
    nv = len(ids)
    n = _NV * nv + 2
    K = len(ts)
    # transitions x_k = F_k x_{k-1} + w_k, w_k ~ N(0, Q_k)
    Fs, Qs = [np.eye(n)], [P0]
    in_stop = {v: False for v in ids}
    kept = {v: None for v in ids}
    for k in range(K):
        F, Q = np.eye(n), np.zeros((n, n))
        if k > 0:
            dt = ts[k] - ts[k - 1]
            for i, vid in enumerate(ids):
                s, b = specs[vid], _NV * i
                for ax in range(2):  # constant velocity per axis driven by white acceleration
                    ip, iv = b + ax, b + 2 + ax
                    F[ip, iv] = dt
                    q = s.imu.vrw**2
                    Q[ip, ip], Q[ip, iv], Q[iv, ip], Q[iv, iv] = q * dt**3 / 3, q * dt**2 / 2, q * dt**2 / 2, q * dt
                tau = s.gnss.multipath_tau_moving if moving[vid][k] else s.gnss.multipath_tau_static
                a = math.exp(-dt / tau)
                for j in (b + 4, b + 5):
                    F[j, j] = a
                    Q[j, j] = s.gnss.multipath_h**2 * (1 - a * a)
            a = math.exp(-dt / scn.common_mode_tau)
            for j in range(_NV * nv, n):
                F[j, j] = a
                Q[j, j] = scn.common_mode_sigma**2 * (1 - a * a)
        for i, vid in enumerate(ids):
            s, b = specs[vid], _NV * i
            if rho is not None and lmap is not None and str(lane[vid][k]) in lmap.marks:
                if kept[vid] is not None and kept[vid] != str(lane[vid][k]):
                    # a new lane: offset = ρ × the last one + a new draw of variance (1 - ρ²) σ²
                    F[b + 8, :] = 0.0
                    F[b + 8, b + 8] = rho[vid]
                    Q[b + 8, :] = Q[:, b + 8] = 0.0
                    Q[b + 8, b + 8] = (1.0 - rho[vid] ** 2) * s.lateral[1] ** 2
                kept[vid] = str(lane[vid][k])
            stops = use_sl and first[vid][k] and str(lane[vid][k]) in lanes
            if stops and not in_stop[vid] and k > 0:  # a new stop: new gap errors
                for j, var in ((b + 6, s.stop_gap[1] ** 2), (b + 7, s.lateral[1] ** 2)):
                    F[j, :] = 0.0
                    Q[j, :] = Q[:, j] = 0.0
                    Q[j, j] = var
            in_stop[vid] = bool(first[vid][k])
        if k > 0:
            Fs.append(F)
            Qs.append(Q)
    return Fs, Qs


def _rows(scn, specs, ids, ts, pos, first, lane, lanes, use_sl, use_ranges, lmap):
    """Every measurement row: (step, row on that step's state, noise variance)."""
    nv = len(ids)
    n = _NV * nv + 2
    K = len(ts)
    # measurement rows on the state at their step, and their noise variances
    rows: list[tuple[int, np.ndarray, float]] = []

    def row(k: int, coeffs: dict[int, float], var: float) -> None:
        h = np.zeros(n)
        for j, v in coeffs.items():
            h[j] += v
        rows.append((k, h, var))

    p_radio = 1.0 - scn.radio.expected_loss()
    for k in range(K):
        for i, vid in enumerate(ids):
            s, b = specs[vid], _NV * i
            for ax in range(2):
                row(k, {b + ax: 1.0, b + 4 + ax: 1.0, _NV * nv + ax: 1.0}, max(s.gnss.white_h, 0.05) ** 2)
                row(k, {b + 2 + ax: 1.0}, max(s.gnss.velocity_white, 0.02) ** 2)
            if use_sl and first[vid][k] and str(lane[vid][k]) in lanes:
                _, J = stop_line_fix(lanes[str(lane[vid][k])].approach, s.stop_gap[0] + s.l0, s.lateral[0])
                d_l = b + 8 if lmap is not None else b + 7
                for ax in range(2):  # p - J (δd_s, δd_l) = fix error
                    row(k, {b + ax: 1.0, b + 6: -J[ax, 0], d_l: -J[ax, 1]}, STOP_LINE_MAP_SIGMA**2)
            elif lmap is not None and str(lane[vid][k]) in lmap.marks:
                nr = lmap.left_line_at(str(lane[vid][k]), pos[vid][k]).right_normal
                row(k, {b: nr[0], b + 1: nr[1], b + 8: -1.0}, STOP_LINE_MAP_SIGMA**2)
        if use_ranges:
            per_step = scn.uwb.rate * (ts[1] - ts[0])  # ranges a pair measures in one step
            for a in range(nv):
                for bb in range(a + 1, nv):
                    d = pos[ids[a]][k] - pos[ids[bb]][k]
                    rho = float(np.hypot(*d))
                    p = float(scn.uwb.success_probability(rho)) * p_radio
                    if p <= 0.0 or rho > scn.radio.max_range or rho <= 0.5:
                        continue
                    u = d / rho  # a range is relative: +u on one vehicle, -u on the other
                    row(k, {_NV * a: u[0], _NV * a + 1: u[1], _NV * bb: -u[0], _NV * bb + 1: -u[1]},
                        scn.uwb.sigma_los**2 / (p * per_step))
    return rows


@pytest.mark.parametrize("lanes_rho", [None, 0.0, 0.6], ids=["stop-line", "lanes-redrawn", "lanes-correlated"])
@pytest.mark.parametrize("use_ranges", [False, True], ids=["own", "ranges"])
def test_the_recursion_equals_the_batch_posterior_of_the_whole_trajectory(lanes_rho: float | None,
                                                                          use_ranges: bool) -> None:
    """Without lanes, and with lane keeping whose offset V1 draws anew (ρ = 0) or correlated
    (ρ = 0.6) in its second lane."""
    case = _case(lanes_rho is not None)
    rho = None if lanes_rho is None else {"V0": 1.0, "V1": lanes_rho}
    got = _run(*case[:9], True, use_ranges, case[9], rho)
    want = _batch(*case[:9], True, use_ranges, case[9], rho)
    first = case[6]["V0"]
    for vid in ("V0", "V1"):
        assert np.allclose(got[vid], want[vid], rtol=1e-6, atol=1e-12), (vid, np.abs(got[vid] - want[vid]).max())
    # the case exercises what it claims: the stop line and the ranges move the bound
    sl = np.trace(got["V0"][first][-1])
    assert sl < 0.05 * np.trace(got["V0"][~first][0])
    if use_ranges:
        own = _run(*case[:9], True, False, case[9], rho)
        assert np.trace(got["V1"][-1]) < 0.8 * np.trace(own["V1"][-1])


def test_a_perfect_range_between_two_vehicles_leaves_their_common_mode_error() -> None:
    """Two vehicles whose GNSS error is only the common mode, with a (nearly) perfect range
    along north: a range is relative, so it cannot tell where both are together. Each one's
    north variance stays at least the common-mode variance the two GNSS share, and the
    difference of their positions becomes (nearly) exact along the range."""
    g = GnssModel(white_h=0.05, multipath_h=1e-4, velocity_white=0.02)
    specs = {v: SimpleNamespace(gnss=g, imu=ImuModel(vrw=1e-4), stop_gap=(1.5, 0.2), lateral=(1.75, 0.1), l0=2.5)
             for v in ("V0", "V1")}
    cm = 2.0
    scn = SimpleNamespace(uwb=UwbModel(sigma_los=0.001), radio=RadioModel(loss=0.0, ge_p_good_to_bad=0.0),
                          common_mode_sigma=cm, common_mode_tau=1e6)
    ts = np.arange(0.0, 4.0, 0.2)
    k = len(ts)
    pos = {"V0": np.zeros((k, 2)), "V1": np.tile([10.0, 0.0], (k, 1))}
    still = {v: np.zeros(k, bool) for v in pos}
    lanes = {v: np.array(["x"] * k) for v in pos}
    cov = _run(scn, specs, ["V0", "V1"], ts, pos, still, still, lanes, {}, False, True)
    for v in ("V0", "V1"):
        assert cov[v][-1, 0, 0] >= 0.95 * cm**2
        assert cov[v][-1, 1, 1] >= 0.95 * cm**2


def test_one_step_range_weight_in_closed_form() -> None:
    """One step, two vehicles with independent white GNSS (variance s²) and a range along
    north: UWB at 10 Hz over a 0.5 s step with success probability p gives r = 5 p ranges of
    variance σ², so the north information on (p0, p1) is ``diag(1/s² + 1/100²) + (r/σ²)
    [[1, -1], [-1, 1]]`` (the 100 m prior included), and east has no range information."""
    s = 0.5
    g = GnssModel(white_h=s, multipath_h=1e-9, velocity_white=1.0)
    specs = {v: SimpleNamespace(gnss=g, imu=ImuModel(), stop_gap=(1.5, 0.2), lateral=(1.75, 0.1), l0=2.5)
             for v in ("V0", "V1")}
    sig = 0.2
    scn = SimpleNamespace(uwb=UwbModel(rate=10.0, sigma_los=sig, d50=10.0, d_scale=3.0),
                          radio=RadioModel(loss=0.0, ge_p_good_to_bad=0.0),
                          common_mode_sigma=1e-9, common_mode_tau=600.0)
    ts = np.array([0.0, 0.5])  # the step's length sets the number of ranges in it
    pos = {"V0": np.zeros((2, 2)), "V1": np.tile([8.0, 0.0], (2, 1))}
    still = {v: np.zeros(2, bool) for v in pos}
    lanes = {v: np.array(["x"] * 2) for v in pos}
    cov = _run(scn, specs, ["V0", "V1"], ts, pos, still, still, lanes, {}, False, True)
    p = float(scn.uwb.success_probability(8.0))
    assert 0.2 < p < 0.9  # the success probability counts
    r = 10.0 * 0.5 * p
    info = np.eye(2) * (1 / s**2 + 1e-4) + (r / sig**2) * np.array([[1.0, -1.0], [-1.0, 1.0]])
    assert cov["V0"][0, 0, 0] == pytest.approx(np.linalg.inv(info)[0, 0], rel=1e-6)
    assert cov["V1"][0, 0, 0] == pytest.approx(np.linalg.inv(info)[1, 1], rel=1e-6)
    assert cov["V0"][0, 1, 1] == pytest.approx(1 / (1 / s**2 + 1e-4), rel=1e-6)  # east: no range information


def test_the_bound_at_a_time_is_the_latest_step_not_after_it() -> None:
    from slcp.deploy.bound import Bound

    cov = np.zeros((3, 2, 2))
    cov[:, 0, 0] = [9.0, 4.0, 1.0]
    cov[:, 1, 1] = [16.0, 5.0, 3.0]
    b = Bound(np.array([10.0, 10.2, 10.4]), {("SP", "V0"): cov})
    assert np.allclose(b.sigma_h("SP", "V0"), [5.0, 3.0, 2.0])
    got = b.at("SP", "V0", np.array([9.0, 10.0, 10.1, 10.2 - 1e-12, 10.2, 10.39, 10.4, 99.0]))
    assert np.allclose(got, [5.0, 5.0, 5.0, 3.0, 3.0, 3.0, 2.0, 2.0])
