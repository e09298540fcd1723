"""The posterior CRLB: closed forms on a synthetic fleet, ordering of the methods, and the CLI."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from slcp.deploy.bound import _run
from slcp.hw_emulation.sensors.gnss import GnssModel
from slcp.hw_emulation.sensors.imu import ImuModel
from slcp.hw_emulation.sensors.radio import RadioModel
from slcp.hw_emulation.sensors.uwb import UwbModel


def _fleet(n: int, gnss: GnssModel, common: float = 1e-6, uwb: UwbModel | None = None):
    specs = {f"V{i}": SimpleNamespace(gnss=gnss, imu=ImuModel(), stop_gap=(1.5, 0.2), lateral=(1.75, 0.1), l0=2.5)
             for i in range(n)}
    scn = SimpleNamespace(uwb=uwb or UwbModel(), radio=RadioModel(loss=0.0, ge_p_good_to_bad=0.0),
                          common_mode_sigma=common, common_mode_tau=600.0)
    return scn, specs


def test_gnss_only_matches_batch_least_squares() -> None:
    """One vehicle, white GNSS position and velocity noise, (almost) no process noise: the
    recursion's final bound equals the batch least-squares covariance of p(T) = p0 + v T."""
    g = GnssModel(white_h=0.5, multipath_h=1e-6, velocity_white=0.05)
    scn, specs = _fleet(1, g)
    specs["V0"].imu = ImuModel(vrw=1e-7)
    ts = np.arange(0.0, 20.0, 0.2)
    k = len(ts)
    pos = {"V0": np.zeros((k, 2))}
    still = {"V0": np.zeros(k, bool)}
    cov = _run(scn, specs, ["V0"], ts, pos, still, still, {"V0": np.array(["x"] * k)}, {}, False, False)["V0"]
    # batch, one axis: unknowns (p0, v); rows p0 + v t_k (σ 0.5) and v (σ 0.05); priors 100 m, 10 m/s
    A = np.vstack([np.column_stack([np.ones(k), ts]), np.column_stack([np.zeros(k), np.ones(k)])])
    w = np.r_[np.full(k, 1 / 0.5**2), np.full(k, 1 / 0.05**2)]
    info = A.T @ (A * w[:, None]) + np.diag([1 / 100.0**2, 1 / 10.0**2])
    end = np.array([1.0, ts[-1]])
    expected = end @ np.linalg.solve(info, end)
    assert cov[-1, 0, 0] == pytest.approx(expected, rel=0.01)
    assert cov[-1, 1, 1] == pytest.approx(expected, rel=0.01)
    assert cov[-1, 0, 1] == pytest.approx(0.0, abs=1e-9)


def test_a_range_adds_information_along_the_line_only() -> None:
    g = GnssModel(white_h=0.5, multipath_h=2.0, velocity_white=0.05)
    scn, specs = _fleet(2, g)
    ts = np.arange(0.0, 10.0, 0.2)
    k = len(ts)
    pos = {"V0": np.zeros((k, 2)), "V1": np.tile([7.0, 0.0], (k, 1))}  # V1 7 m north of V0
    still = {v: np.zeros(k, bool) for v in pos}
    lanes = {v: np.array(["x"] * k) for v in pos}
    ids = ["V0", "V1"]
    solo = _run(scn, specs, ids, ts, pos, still, still, lanes, {}, False, False)["V0"][-1]
    coop = _run(scn, specs, ids, ts, pos, still, still, lanes, {}, False, True)["V0"][-1]
    # two equal vehicles and a perfect range along north: the north variance of each halves
    assert coop[0, 0] == pytest.approx(solo[0, 0] / 2, rel=0.05)
    assert coop[1, 1] == pytest.approx(solo[1, 1], rel=1e-6)


@pytest.mark.timeout(120)
def test_methods_are_ordered_and_the_cli_prints_them(capsys) -> None:
    from slcp.deploy.cli import main

    assert main(["bound", "paper-1", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    for r in rows:
        assert r["SL-CP"] <= r["CP"] + 1e-9 <= r["SP"] + 2e-9
        assert r["SL-CP"] <= r["SL-SP"] + 1e-9 <= r["SP"] + 2e-9
    v1 = next(r for r in rows if r["vehicle"] == "V1")
    assert v1["SL-SP"] < 0.5 < v1["SP"]  # the first stopped vehicle's stop line


def test_the_stop_line_information_counts_from_the_step_in_which_the_vehicle_stops() -> None:
    """The bound at step k stands for [t_k, t_k+1) (``Bound.at``); a detector may claim, and fix,
    as soon as the vehicle stops inside it, so the stop line's information is in from that step
    (paper-2 seed 0: V0 stops at 21.46 s, between the 5 Hz steps 21.4 and 21.6 s)."""
    from slcp.deploy.bound import posterior_crlb
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth

    truth = build_truth(load_scenario("paper-2"), stop_seed=0)
    tr = truth.vehicles["V0"]
    t_on = float(tr.truth.t[np.flatnonzero(tr.first_stopped)[0]])
    b = posterior_crlb(truth, ("SL-SP",))
    k = int(np.searchsorted(b.t, t_on, side="right")) - 1
    assert b.t[k] < t_on < b.t[k + 1]  # the stop falls inside a step, not on it
    sl = b.sigma_h("SL-SP", "V0")
    assert sl[k] < 0.5 * sl[k - 1]  # the fix's information from step k on
    assert b.at("SL-SP", "V0", np.array([t_on]))[0] == sl[k]


@pytest.mark.timeout(180)
def test_an_offset_redrawn_in_each_lane_knows_less_than_one_kept_by_the_driver(capsys) -> None:
    """``--lane-offset lane`` (the filters' driver model) discards what a driver's constant
    offset (``vehicle``) tells across lanes: paper-1's SL bounds rise where a vehicle changes
    lanes and the bounds without lane information are unchanged. Paper-1's drivers draw their
    offset anew in each lane, so the default (``scenario``) is the filters' model."""
    from slcp.deploy.cli import main

    rows = {}
    for model in ("scenario", "vehicle", "lane"):
        assert main(["bound", "paper-1", "--json", "--lane-offset", model]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["lane_offset"] == model
        rows[model] = {(r["window"], r["vehicle"]): r for r in out["rows"]}
    assert rows["vehicle"].keys() == rows["lane"].keys() == rows["scenario"].keys()
    assert rows["scenario"] == rows["lane"]
    for key, v in rows["vehicle"].items():
        per_lane = rows["lane"][key]
        for m in ("SP", "CP"):
            assert per_lane[m] == pytest.approx(v[m], rel=1e-12)
        for m in ("SL-SP", "SL-CP"):
            assert per_lane[m] >= v[m] * (1 - 1e-6)
    # V0 changes lanes in its turn: its own stop-line fix no longer tells its offset in the next
    # lane (a small effect on its own sensors, about 1e-5 of the bound, but not none)
    assert rows["lane"][("t_s1-t_e", "V0")]["SL-SP"] > (1 + 1e-6) * rows["vehicle"][("t_s1-t_e", "V0")]["SL-SP"]
    # V1, the first stopped vehicle: 0.11 -> 0.13 m
    assert rows["lane"][("t_s1-t_e", "V1")]["SL-CP"] > 1.1 * rows["vehicle"][("t_s1-t_e", "V1")]["SL-CP"]


def test_an_unknown_lane_offset_model_is_refused() -> None:
    from slcp.deploy.bound import posterior_crlb

    with pytest.raises(ValueError, match="lane_offset"):
        posterior_crlb(SimpleNamespace(), lane_offset="driver")


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_sub_fleet_knows_less_and_a_vehicle_alone_is_its_own_bound(capsys) -> None:
    """``--vehicles``: the cooperative bounds of a sub-fleet process only its vehicles'
    information, so they are never below the whole fleet's; SP and SL-SP use each vehicle's own
    data and do not change; a sub-fleet of one has no ranges, so its CP and SL-CP bounds equal
    its SP and SL-SP bounds (paper-2, seed 3's stop draws). The ``standing`` rows cover the
    times a vehicle truly stands: V0 is first stopped then, and its SL-SP bound is the stop
    line's decimetres."""
    from slcp.deploy.cli import main

    rows = {}
    for sub in (None, "V0,V1", "V0"):
        assert main(["bound", "paper-2", "--json", "--seed", "3"] + ([] if sub is None else ["--vehicles", sub])) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["seed"] == 3
        rows[sub] = {(r["window"], r["vehicle"]): r for r in out["rows"]}
    assert {v for _, v in rows[None]} == {"V0", "V1", "V2"}
    assert {v for _, v in rows["V0,V1"]} == {"V0", "V1"}
    for sub in ("V0,V1", "V0"):
        for key, r in rows[sub].items():
            full = rows[None][key]
            for m in ("SP", "SL-SP"):
                assert r[m] == pytest.approx(full[m], rel=1e-9)
            for m in ("CP", "SL-CP"):
                assert r[m] >= full[m] * (1 - 1e-9)
    alone = rows["V0"]
    for r in alone.values():
        assert r["CP"] == pytest.approx(r["SP"], rel=1e-9)
        assert r["SL-CP"] == pytest.approx(r["SL-SP"], rel=1e-9)
    # the neighbours' information is worth something to V0 somewhere
    assert any(rows["V0,V1"][k]["SL-CP"] < 0.99 * r["SL-CP"] for k, r in alone.items())
    assert alone[("standing", "V0")]["SL-SP"] < 0.5 < alone[("standing", "V0")]["SP"]


def test_a_sub_fleet_with_an_unknown_vehicle_is_refused(capsys) -> None:
    from slcp.deploy.cli import main

    assert main(["bound", "paper-1", "--vehicles", "V0,V9"]) == 2
    err = capsys.readouterr().err
    assert "V9" in err and "V0, V1, V2" in err
    assert main(["bound", "paper-1", "--vehicles", " , "]) == 2


def test_the_bound_s_map_frame_is_the_local_ned_within_two_centimetres() -> None:
    """The bound places the vehicles by a tangent plane scaled at the origin; over an intersection
    (400 m each way, 60 m up) it is pymap3d's exact local NED within 2 cm."""
    import pymap3d

    from slcp.deploy.bound import map_ne

    o = (math.radians(39.9552), math.radians(116.3194), 50.0)
    rng = np.random.default_rng(11)
    ned = np.column_stack([rng.uniform(-400.0, 400.0, (60, 2)), rng.uniform(-60.0, 10.0, 60)])
    llh = np.array([pymap3d.ned2geodetic(*p, *o, deg=False) for p in ned])
    got = map_ne(llh, o)
    want = np.array([pymap3d.geodetic2ned(*p, *o, deg=False)[:2] for p in llh])
    assert np.max(np.abs(got - want)) < 0.02
    assert np.max(np.abs(got - want)) > 0.0  # an approximation, not the same computation
