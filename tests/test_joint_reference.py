"""The joint reference (`deploy/joint_filter.py`, `deploy/joint_reference.py`): row Jacobians
against numerical perturbation, a range's closed form, marginalising a state, seeded
Monte-Carlo consistency on data drawn from the filter's own model, and the in-process run."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from slcp.agent.methods import MethodFilter
from slcp.agent.nav.measurements.stop_line import Line2D, StopLineApproach
from slcp.agent.site_updates import SiteUpdates
from slcp.deploy.agent_configs import agent_config
from slcp.deploy.joint_filter import ACC_TAU, NV, JointFilter, Row
from slcp.deploy.joint_reference import Shared, main, sharing
from slcp.deploy.joint_window import relinearised, smoothed
from slcp.geo import earth
from slcp.hw_emulation.scenario import load_scenario
from slcp.transport.messages import GnssFix

SCN = load_scenario("paper-1")
ORIGIN = SCN.origin_llh
LEFT_LINE = Line2D((0.0, -1.75), (1.0, 0.0))
#: σ of the simulated INS acceleration error [m/s²] (:func:`_simulate`)
SIM_ACC_SIGMA = 0.02


def _settings(nlos: bool = False):
    s = agent_config(SCN, "V1", ("SL-CP",)).settings
    return s if nlos else dataclasses.replace(s, uwb_nlos=None)


def _llh(ne: np.ndarray) -> np.ndarray:
    """The geodetic point of map position ``ne`` (the inverse of ``bound.map_ne``)."""
    rm, rn = earth.radii(ORIGIN[0])
    return np.array([ORIGIN[0] + ne[0] / (rm + ORIGIN[2]),
                     ORIGIN[1] + ne[1] / ((rn + ORIGIN[2]) * math.cos(ORIGIN[0])), ORIGIN[2]])


def _fix(vid: str, t: float, ne: np.ndarray, v: np.ndarray, seq: int = 0) -> GnssFix:
    return GnssFix(vid, seq, t, _llh(ne), np.array([v[0], v[1], 0.0]), np.array([3.0, 3.0, 5.0]), 0.1)


def _filter(ids=("V1", "V2"), nlos: bool = False) -> JointFilter:
    jf = JointFilter(SCN, list(ids), 0.0, _settings(nlos))
    for i, vid in enumerate(ids):
        jf.start(vid, _fix(vid, 0.0, np.array([10.0 * i, 2.0]), np.array([5.0, 0.0])), ORIGIN)
    return jf


def _numeric_jacobian(row: Row, x: np.ndarray, back: float, eps: float = 1e-6) -> np.ndarray:
    h0, _ = row.fn(x, back)
    J = np.zeros((len(h0), len(x)))
    for k in range(len(x)):
        d = np.zeros(len(x))
        d[k] = eps
        J[:, k] = (row.fn(x + d, back)[0] - row.fn(x - d, back)[0]) / (2 * eps)
    return J


def test_every_row_s_jacobian_matches_numerical_perturbation() -> None:
    """GNSS position and velocity, ZUPT, the stop-line fix (full and along only, with and
    without the lane's offset), lane keeping and a range with its link's bias state: H against
    central differences at a random state, 0.07 s before the filter time."""
    jf = _filter(nlos=True)
    rng = np.random.default_rng(3)
    jf.x = jf.x + rng.normal(size=jf.n) * 0.5
    jf.x[:2] = (1.0, 3.0)  # V1
    jf.x[NV:NV + 2] = (9.0, -4.0)  # V2
    approach = StopLineApproach(Line2D((40.0, -5.0), (0.0, 1.0)), Line2D((0.0, 0.0), (1.0, 0.2)))
    rows = jf.gnss_rows(0.0, "V2", _fix("V2", 0.0, np.array([8.0, -3.0]), np.array([4.0, 1.0])), ORIGIN)
    rows += [jf.zupt_row(0.0, "V1", 0.02), jf.lane_row(0.0, "V1", Line2D((0.0, 0.0), (0.6, 0.8)))]
    rows += [jf.stop_rows(0.0, "V1", approach, along, kept) for along in (False, True) for kept in (False, True)]
    row = jf.range_row(0.0, "V1", "V2", 11.0)
    assert row is not None and len(jf.links) == 1
    rows.append(row)
    x = jf.x.copy()
    x[-1] = 0.4  # the link's bias
    for r in rows:
        _, H = r.fn(x, 0.07)
        np.testing.assert_allclose(H, _numeric_jacobian(r, x, 0.07), atol=1e-6, err_msg=r.kind)


def test_a_range_between_two_equal_vehicles_has_its_closed_form() -> None:
    """Two vehicles known to σ² per axis, uncorrelated, a range of variance σ_r² between them
    (the UWB noise and the second-order term σ⊥⁴/(2r²)): along the line of sight the relative
    variance 2σ² becomes 2σ²σ_r²/(2σ² + σ_r²), across it nothing changes, and each vehicle's
    along-line variance is σ² - σ⁴/(2σ² + σ_r²)."""
    jf = _filter()
    n = jf.n
    jf.P = np.eye(n) * 1e-6
    s2 = 0.3**2
    for b in (0, NV):
        jf.P[b:b + 2, b:b + 2] = np.eye(2) * s2
    jf.x[:2], jf.x[NV:NV + 2] = (0.0, 0.0), (30.0, 0.0)  # the line of sight along north
    row = jf.range_row(0.0, "V1", "V2", 30.0)
    assert row is not None
    r2 = float(row.R[0, 0])
    # the UWB noise and the second-order term of the 2σ² across the line of sight
    assert r2 == pytest.approx(jf.settings.sigma_uwb**2 + (2 * s2) ** 2 / (2 * 30.0**2), rel=1e-9)
    jf.update([row])
    P = jf.P
    rel_along = P[0, 0] + P[NV, NV] - 2 * P[0, NV]
    assert rel_along == pytest.approx(2 * s2 * r2 / (2 * s2 + r2), rel=1e-9)
    assert P[0, 0] == pytest.approx(s2 - s2 * s2 / (2 * s2 + r2), rel=1e-9)
    assert P[1, 1] == pytest.approx(s2, rel=1e-9)


def test_a_link_s_bias_follows_the_tracker_and_a_silent_link_is_marginalised() -> None:
    """A link's bias state takes the moments of a bias that is NLOS with the tracker's
    probability p (mean p·E[b], variance p·E[b²] - (p·E[b])², the variance never lowered);
    of three links, the one silent past LINK_IDLE is marginalised (the rest of x and P as they
    were) and the later link's index moves down."""
    jf = _filter(("V0", "V1", "V2"), nlos=True)
    nl = jf.settings.uwb_nlos
    for k, (a, c) in enumerate((("V0", "V1"), ("V0", "V2"), ("V1", "V2"))):
        jf._link_state(f"{a}|{c}", -9.0 if k == 1 else -5.0, 0.05 * (k + 1))
    li = jf.links["V0|V1"][0]
    assert jf.x[li] == pytest.approx(0.05 * nl.bias_mean)
    assert jf.P[li, li] == pytest.approx(0.05 * nl.bias_mean_square - (0.05 * nl.bias_mean) ** 2)
    rng = np.random.default_rng(1)
    A = rng.normal(size=(jf.n, jf.n))
    jf.P = A @ A.T
    before_x, before_P = jf.x.copy(), jf.P.copy()
    gone, last = jf.links["V0|V2"][0], jf.links["V1|V2"][0]
    jf._link_state("V0|V1", 1.5, 0.9)  # V0|V2 silent for 10.5 s; V0|V1 now likely NLOS
    assert "V0|V2" not in jf.links and jf.links["V1|V2"][0] == last - 1
    keep = [k for k in range(len(before_x)) if k != gone]
    li = jf.links["V0|V1"][0]
    expect_x, expect_P = before_x[keep], before_P[np.ix_(keep, keep)]
    expect_x[li] = 0.9 * nl.bias_mean
    expect_P[li, li] = max(expect_P[li, li], 0.9 * nl.bias_mean_square - (0.9 * nl.bias_mean) ** 2)
    np.testing.assert_array_equal(jf.x, expect_x)
    np.testing.assert_array_equal(jf.P, expect_P)


def test_a_link_s_bias_is_a_consider_state() -> None:
    """Ranges never move a link's bias (Schmidt): after each update it is what the link's
    tracker made it, and the bias is not averaged away: after 20 ranges on one link in 2 s
    the relative position along it keeps most of the bias's variance (0.69 of it; white noise
    of that variance would have shrunk it twenty-fold)."""
    jf = _filter(nlos=True)
    jf.x[:2], jf.x[NV:NV + 2] = (0.0, 0.0), (30.0, 0.0)
    jf.P[:2, :2] = jf.P[NV:NV + 2, NV:NV + 2] = np.eye(2) * 0.5**2
    jf.P[2:4, 2:4] = jf.P[NV + 2:NV + 4, NV + 2:NV + 4] = np.eye(2) * 1e-8  # velocities known
    for k in range(20):
        t = 0.1 * (k + 1)
        jf.predict(t, {})
        row = jf.range_row(t, "V1", "V2", 30.0)
        assert row is not None
        li = jf.links["V1|V2"][0]
        before = float(jf.x[li])
        jf.update([row])
        assert jf.x[li] == before
    var_bias = float(jf.P[li, li])
    rel = jf.P[0, 0] + jf.P[NV, NV] - 2 * jf.P[0, NV]
    assert var_bias > 0.01 and rel > 0.5 * var_bias  # (the bias decorrelates over 1/exit = 5 s)


def _simulate(seed: int, steps: int = 300, dt: float = 0.1):
    """Two vehicles driving north 30 m apart in one lane at 5 m/s, with every error the filter
    models: GNSS white noise, multipath (Gauss-Markov per vehicle) and the common mode (shared),
    INS velocity increments with a Gauss-Markov acceleration error, each driver's offset in the
    lane, UWB ranges with white noise. Yields per step the truth and the step's data."""
    rng = np.random.default_rng(seed)
    specs = {v.id: v for v in SCN.vehicles}
    ids = ("V1", "V2")
    sa = SIM_ACC_SIGMA
    p = {"V1": np.array([0.0, 0.0]), "V2": np.array([-30.0, 0.0])}
    v = {vid: np.array([5.0, 0.0]) for vid in ids}
    mp = {vid: rng.normal(size=2) * specs[vid].gnss.multipath_h for vid in ids}
    acc = {vid: rng.normal(size=2) * sa for vid in ids}
    cm = rng.normal(size=2) * SCN.common_mode_sigma
    # the lane's left line runs north along east = -1.75; each driver keeps its offset right of it
    offset = {vid: specs[vid].lateral[0] + rng.normal() * specs[vid].lateral[1] for vid in ids}
    for vid in ids:
        p[vid][1] = -1.75 + offset[vid]
    sigma_uwb = _settings().sigma_uwb
    for k in range(1, steps + 1):
        t = k * dt
        a_acc = math.exp(-dt / ACC_TAU)
        a_cm = math.exp(-dt / SCN.common_mode_tau)
        cm = cm * a_cm + rng.normal(size=2) * SCN.common_mode_sigma * math.sqrt(1 - a_cm**2)
        data = {}
        for vid in ids:
            g = specs[vid].gnss
            a_mp = math.exp(-dt / g.multipath_tau_moving)
            mp[vid] = mp[vid] * a_mp + rng.normal(size=2) * g.multipath_h * math.sqrt(1 - a_mp**2)
            true_dv = np.array([0.2 * math.sin(0.3 * t), 0.0]) * dt  # gentle speed changes
            p[vid] = p[vid] + v[vid] * dt + true_dv * dt / 2
            v[vid] = v[vid] + true_dv
            acc[vid] = acc[vid] * a_acc + rng.normal(size=2) * sa * math.sqrt(1 - a_acc**2)
            ins_dv = true_dv - acc[vid] * dt  # the INS's increment = truth + its error
            fix = None
            if k % 2 == 0:
                z = p[vid] + mp[vid] + cm + rng.normal(size=2) * g.white_h
                vz = v[vid] + rng.normal(size=2) * g.velocity_white
                fix = _fix(vid, t, z, vz, k)
            data[vid] = (ins_dv, fix, k % 10 == 5)  # a lane-keeping row once a second
        r = float(np.hypot(*(p["V1"] - p["V2"]))) + rng.normal() * sigma_uwb
        yield t, {vid: p[vid].copy() for vid in ids}, data, r, sa


def _synthetic_step(f: JointFilter, t: float, data: dict, r: float | None, x0: np.ndarray | None) -> None:
    """One step of :func:`_simulate`'s data through ``f``: the INS (the simulation's
    acceleration error σ), the fixes (the first one starts a vehicle), the lane rows and the
    range (``r`` None: none) once its line of sight is known; rows linearised at ``x0``."""
    f.predict(t, {vid: (dv, dv * 0.05, np.eye(2) * SIM_ACC_SIGMA**2) for vid, (dv, _, _) in data.items()})
    rows: list[Row] = []
    for vid, (_, fix, lane) in data.items():
        if fix is not None:
            if vid not in f.started:
                f.start(vid, fix, ORIGIN)
            rows += f.gnss_rows(t, vid, fix, ORIGIN)
        if lane and vid in f.started:
            rows.append(f.lane_row(t, vid, LEFT_LINE))
    if r is not None and len(f.started) == 2 and f.relative_sigma("V1", "V2") < 0.2 * r:
        row = f.range_row(t, "V1", "V2", r)
        assert row is not None
        rows.append(row)
    f.update(rows, iterations=3 if x0 is None else 1, x0=x0)


@pytest.mark.slow
def test_the_filter_is_consistent_on_data_drawn_from_its_model() -> None:
    """Seeded Monte-Carlo, 16 runs of 30 s in one lane. The normalised NEES of both vehicles'
    positions averages 1 (0.84 measured: their errors, the slow multipath and common mode, give
    few independent draws, so the band is wide), and along the line of sight, where the range
    holds the relative position to centimetres (the GNSS alone: metres), the error's RMS
    matches the σ the filter reports (1.02 measured; with the INS acceleration error's σ a tenth
    of the truth's, 3.9)."""
    nees, rel_err, rel_sig = [], [], []
    for seed in range(16):
        jf = JointFilter(SCN, ["V1", "V2"], 0.0, _settings())
        for t, truth, data, r, _sa in _simulate(seed):
            _synthetic_step(jf, t, data, r, None)
            if t > 5.0:
                for vid, b in (("V1", 0), ("V2", NV)):
                    e = jf.x[b:b + 2] - truth[vid]
                    nees.append(float(e @ np.linalg.solve(jf.P[b:b + 2, b:b + 2], e)) / 2)
                d = (jf.x[:2] - jf.x[NV:NV + 2]) - (truth["V1"] - truth["V2"])
                rel_err.append(float(d[0]))  # along the line of sight
                rel_sig.append(math.sqrt(jf.P[0, 0] + jf.P[NV, NV] - 2 * jf.P[0, NV]))
    assert 0.6 < float(np.mean(nees)) < 1.4
    rel_rms, sig = float(np.sqrt(np.mean(np.square(rel_err)))), float(np.mean(rel_sig))
    assert rel_rms < 0.05
    assert 0.8 < rel_rms / sig < 1.25


def test_sharing_restores_the_engine_even_after_an_error() -> None:
    before = (MethodFilter.propagate, MethodFilter.zupt, SiteUpdates.stop_line, SiteUpdates.lane_line)
    with pytest.raises(RuntimeError):
        with sharing(Shared()):
            assert MethodFilter.propagate is not before[0]
            raise RuntimeError("boom")
    assert (MethodFilter.propagate, MethodFilter.zupt, SiteUpdates.stop_line, SiteUpdates.lane_line) == before


def test_bad_arguments_are_refused(capsys) -> None:
    assert main(["paper-1", "--seeds", "0,x"]) == 2
    assert "joint_reference: error" in capsys.readouterr().err
    assert main(["nope"]) == 2
    assert "unknown scenario" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_the_reference_on_paper_1_in_process(capsys) -> None:
    """One seed of paper-1: the shared data hold every vehicle's INS, fixes, the first stopped
    vehicle's stop-line rows and the ranges; the table prints the joint reference beside SL-SP
    and SL-CP for every vehicle; its ranges bring V0 (on its own 0.55 m off in the window)
    under half a metre."""
    assert main(["paper-1", "--seeds", "0"]) == 0
    out = capsys.readouterr().out
    for v in ("V0", "V1", "V2"):
        line = next(ln for ln in out.splitlines() if ln.strip().startswith(v))
        assert "joint" in line and "SL-SP" in line and "SL-CP" in line
    v0 = next(ln for ln in out.splitlines() if ln.strip().startswith("V0"))
    joint, own = float(v0.split("joint")[1].split("/")[0]), float(v0.split("SL-SP")[1].split("/")[0])
    assert joint < 0.5 < own


def test_rts_smoothing_equals_the_batch_solution_of_a_linear_problem() -> None:
    """A 1-D constant-velocity track with noisy position fixes, filtered by a Kalman filter and
    smoothed by :func:`smoothed`: every smoothed state equals the weighted least-squares
    solution over the whole track (the information matrix of the prior, the motion and the
    fixes, solved at once)."""
    rng = np.random.default_rng(5)
    dt, q, r, n = 0.5, 0.3, 0.8, 12
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    H = np.array([[1.0, 0.0]])
    x0, P0 = np.array([0.0, 1.0]), np.diag([4.0, 1.0])
    z = np.cumsum(np.full(n, dt)) + rng.normal(size=n) * r
    hist = {}
    x, P = x0.copy(), P0.copy()
    for k in range(n):
        xp, Pp = (F @ x, F @ P @ F.T + Q) if k else (x.copy(), P.copy())
        K = Pp @ H.T / (H @ Pp @ H.T + r * r)
        x = xp + (K * (z[k] - H @ xp)).ravel()
        P = (np.eye(2) - K @ H) @ Pp
        hist[k] = (xp, Pp, F if k else None, x, P)
    got = smoothed(hist, 0, n - 1)
    # batch: minimise the prior, motion and fix residuals over all 2n states
    A = np.zeros((2 * n, 2 * n))
    b = np.zeros(2 * n)
    A[:2, :2] += np.linalg.inv(P0)
    b[:2] += np.linalg.inv(P0) @ x0
    Qi = np.linalg.inv(Q)
    for k in range(1, n):
        J = np.zeros((2, 2 * n))
        J[:, 2 * k - 2:2 * k] = -F
        J[:, 2 * k:2 * k + 2] = np.eye(2)
        A += J.T @ Qi @ J
    for k in range(n):
        A[2 * k, 2 * k] += 1 / r**2
        b[2 * k] += z[k] / r**2
    batch = np.linalg.solve(A, b).reshape(n, 2)
    for k in range(n):
        np.testing.assert_allclose(got[k], batch[k], atol=1e-9)


def _synthetic_steps(seed: int, with_ranges: bool):
    steps = []
    for k, (t, truth, data, r, _sa) in enumerate(_simulate(seed, steps=150)):
        steps.append((t, data, r if with_ranges else None, truth, k))
    return steps


def _run_synthetic(steps, window: float):
    jf = JointFilter(SCN, ["V1", "V2"], 0.0, _settings(), keep_links=True)
    est = {}

    def do(f: JointFilter, st, x0) -> None:
        t, data, r, _, _ = st
        _synthetic_step(f, t, data, r, x0)

    def output(f: JointFilter, k: int) -> None:
        est[k] = f.x.copy()

    if window > 0.0:
        relinearised(jf, steps, do, output, window)
    else:
        for st in steps:
            do(jf, st, None)
            output(jf, st[-1])
    return est


def test_relinearising_a_linear_problem_changes_nothing(monkeypatch) -> None:
    """Without ranges (and without the robust weights, which depend on where the rows are
    evaluated) every row is linear: re-running the window at smoothed states gives the plain
    filter's outputs; with the ranges it does not."""
    monkeypatch.setattr("slcp.deploy.joint_filter.HUBER_K", {})
    steps = _synthetic_steps(2, with_ranges=False)
    plain, relin = _run_synthetic(steps, 0.0), _run_synthetic(steps, 3.0)
    for k in plain:
        np.testing.assert_allclose(relin[k], plain[k], atol=1e-7)
    steps = _synthetic_steps(2, with_ranges=True)
    plain, relin = _run_synthetic(steps, 0.0), _run_synthetic(steps, 3.0)
    assert max(float(np.max(np.abs(relin[k] - plain[k]))) for k in plain) > 1e-6


def test_a_window_needs_a_filter_of_fixed_size() -> None:
    jf = JointFilter(SCN, ["V1", "V2"], 0.0, _settings())
    with pytest.raises(ValueError, match="keep_links"):
        relinearised(jf, [], lambda f, st, x0: None, lambda f, k: None, 3.0)


def test_a_link_in_an_nlos_episode_waits_for_its_end() -> None:
    """Two standing vehicles 30 m apart, ranged at 10 Hz: when the link's ranges step up by
    2.5 m and stay there (an NLOS episode), the link's tracker holds it to be NLOS and its
    ranges are held back (counted); when they step down again, they are fused again."""
    jf = _filter(nlos=True)
    jf.x[:2], jf.x[NV:NV + 2] = (0.0, 0.0), (30.0, 0.0)
    jf.x[2:4] = jf.x[NV + 2:NV + 4] = 0.0
    jf.P[:2, :2] = jf.P[NV:NV + 2, NV:NV + 2] = np.eye(2) * 0.1**2
    jf.P[2:4, 2:4] = jf.P[NV + 2:NV + 4, NV + 2:NV + 4] = np.eye(2) * 1e-8  # standing
    rng = np.random.default_rng(4)
    used = []
    for k in range(60):
        t = 0.1 * (k + 1)
        r = 30.0 + (2.5 if 20 <= k < 40 else 0.0) + rng.normal() * 0.05
        jf.predict(t, {})
        row = jf.range_row(t, "V1", "V2", r)
        used.append(row is not None)
        if row is not None:
            jf.update([row])
    assert all(used[:20]) and not any(used[25:40]) and all(used[45:])
    assert jf.counters["range_nlos"] >= 15
    assert abs(jf.x[NV] - jf.x[0] - 30.0) < 0.1  # the episode moved nobody
