"""The drivers' lateral offset in each lane of their route: the emulation's draws, the truth it
drives, and the bound that follows the same model."""

from __future__ import annotations

import dataclasses
import re
from types import SimpleNamespace

import numpy as np
import pytest

from slcp.deploy.agent_configs import lane_map
from slcp.deploy.bound import map_ne, posterior_crlb
from slcp.hw_emulation.scenario import ScenarioError, load_scenario, parse_scenario, shipped_scenario_text
from slcp.hw_emulation.traffic import driver_draws, lane_offsets
from slcp.hw_emulation.truth import build_truth, stance_draws


def _drivers(rho: float, lanes: int = 3, mean: float = 1.6, sigma: float = 0.2):
    veh = SimpleNamespace(id="V0", route=tuple(f"L{i}" for i in range(lanes)), lateral=(mean, sigma),
                          lateral_correlation=rho, stop_gap=(1.5, 0.3))
    return SimpleNamespace(vehicles=[veh])


@pytest.mark.parametrize("rho", [0.0, 0.6, 1.0])
def test_each_lane_draws_its_offset_with_the_scenarios_mean_sigma_and_correlation(rho: float) -> None:
    """A first-order Gauss-Markov chain over the lanes: every lane's d_l ~ N(m, σ²), consecutive
    lanes correlated by ρ, lanes two apart by ρ² (4,000 seeded routes; bounds of 4 standard
    errors)."""
    scn = _drivers(rho)
    rng = np.random.default_rng(11)
    n = 4000
    d = np.array([lane_offsets(scn, driver_draws(scn, rng), rng)["V0"] for _ in range(n)])
    assert d.shape == (n, 3)
    assert np.all(np.abs(d.mean(axis=0) - 1.6) < 4 * 0.2 / np.sqrt(n))
    assert np.all(np.abs(d.std(axis=0) / 0.2 - 1.0) < 4 / np.sqrt(2 * n))
    if rho == 1.0:
        assert np.allclose(d[:, 1], d[:, 0]) and np.allclose(d[:, 2], d[:, 0])
        return
    se = (1 - rho**2) / np.sqrt(n) + 1e-3
    assert abs(np.corrcoef(d[:, 0], d[:, 1])[0, 1] - rho) < 4 * se
    assert abs(np.corrcoef(d[:, 1], d[:, 2])[0, 1] - rho) < 4 * se
    assert abs(np.corrcoef(d[:, 0], d[:, 2])[0, 1] - rho**2) < 4 * ((1 - rho**4) / np.sqrt(n) + 1e-3)


def test_the_first_lane_and_the_stop_gaps_are_the_stance_draws() -> None:
    """The later lanes are drawn after the stances: the stop gaps and the first lanes' offsets
    are those of ``stance_draws`` (which the studies check without simulating the traffic)."""
    scn = load_scenario("paper-1")
    for seed in (0, 3):
        truth = build_truth(scn, stop_seed=seed)
        draws = stance_draws(scn, seed)
        for v in scn.vehicles:
            d_s, d_l = draws[v.id]
            assert truth.traffic.stop_gap[v.id] == max(d_s, 0.2)
            assert truth.traffic.lateral[v.id] == d_l == truth.traffic.lane_lateral[v.id][0]
            assert len(truth.traffic.lane_lateral[v.id]) == len(v.route)


def test_the_truth_drives_each_lane_at_its_own_offset() -> None:
    """Paper-1's V0 turns from WB_in_R into NB_out: in each lane its true position stands at that
    lane's d_l right of the lane's left line (median over the lane's samples, within 2 cm: the
    route's smoothing), and the two lanes' offsets differ as drawn."""
    scn = load_scenario("paper-1")
    truth = build_truth(scn, stop_seed=0)
    lm = lane_map(scn)
    checked = []
    for v in scn.vehicles:
        vt = truth.vehicles[v.id]
        ne = map_ne(vt.truth.llh, scn.origin_llh)
        for lane_id, d_l in zip(v.route, truth.traffic.lane_lateral[v.id]):
            idx = np.flatnonzero(vt.segment == lane_id)
            if len(idx) < 100:  # a lane the vehicle does not reach before the scenario ends
                continue
            checked.append((v.id, lane_id))
            dist = []
            for i in idx[::10]:
                line = lm.left_line_at(lane_id, ne[i])
                dist.append(float(np.dot(line.right_normal, ne[i] - np.asarray(line.point, float))))
            assert abs(np.median(dist) - d_l) < 0.02, (v.id, lane_id, np.median(dist), d_l)
    assert {("V0", "WB_in_R"), ("V0", "NB_out")} <= set(checked)
    a, b = truth.traffic.lane_lateral["V0"]
    assert abs(a - b) > 0.05  # the check above tells the lanes apart only if their draws differ


def _with_correlation(truth, rho: float):
    scn = truth.scenario
    vehicles = [dataclasses.replace(v, lateral_correlation=rho) for v in scn.vehicles]
    return dataclasses.replace(truth, scenario=dataclasses.replace(scn, vehicles=vehicles))


@pytest.mark.timeout(120)
def test_the_bound_follows_the_scenarios_lane_to_lane_correlation() -> None:
    """The bound's default driver model is the scenario's: with ρ = 0 it is the filters' model
    (``lane``), with ρ = 1 one offset per vehicle (``vehicle``), and in between it lies between
    them, lower for the first-stopped vehicle V1 the more the offsets carry across the turn."""
    methods = ("SL-SP", "SL-CP")
    paper1 = build_truth(load_scenario("paper-1"))
    lane = posterior_crlb(paper1, methods, lane_offset="lane")
    vehicle = posterior_crlb(paper1, methods, lane_offset="vehicle")
    for rho, want in ((0.0, lane), (1.0, vehicle)):
        got = posterior_crlb(_with_correlation(paper1, rho), methods)
        for k, c in got.cov.items():
            assert np.allclose(c, want.cov[k], rtol=1e-9, atol=1e-15), (rho, k)
    half = posterior_crlb(_with_correlation(paper1, 0.5), methods)
    for k, c in half.cov.items():
        tr = np.trace(c, axis1=1, axis2=2)
        assert np.all(tr <= np.trace(lane.cov[k], axis1=1, axis2=2) * (1 + 1e-9))
        assert np.all(tr >= np.trace(vehicle.cov[k], axis1=1, axis2=2) * (1 - 1e-9))
    v1 = [float(np.mean(b.sigma_h("SL-CP", "V1"))) for b in (vehicle, half, lane)]
    assert v1[0] < v1[1] < v1[2], v1


def test_a_correlation_outside_zero_to_one_or_an_unknown_field_is_refused() -> None:
    import tomllib

    data = tomllib.loads(shipped_scenario_text("paper-1"))
    for lateral, why in (({"mean": 1.75, "sigma": 0.12, "correlation": 1.5}, "within [0, 1]"),
                         ({"mean": 1.75, "sigma": 0.12, "correlation": -0.1}, ">= 0"),
                         ({"mean": 1.75, "sigam": 0.12}, "unknown field")):
        bad = dict(data, vehicles=[dict(data["vehicles"][0], lateral=lateral), *data["vehicles"][1:]])
        with pytest.raises(ScenarioError, match=re.escape(why)):
            parse_scenario(bad, "bad.toml")
