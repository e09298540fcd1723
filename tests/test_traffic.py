"""The emulated drivers: how they take turns, slow from above their desired speed, and wait to
depart (closed forms and the shipped scenarios' traffic)."""

from __future__ import annotations

import numpy as np
import pytest

from slcp.hw_emulation.scenario import Idm, load_scenario
from slcp.hw_emulation.traffic import LAT_ACCEL_MAX, STEP, _idm_accel, simulate_traffic


@pytest.fixture(scope="module")
def traffic():
    return {name: (load_scenario(name), simulate_traffic(load_scenario(name), np.random.default_rng(0)))
            for name in ("paper-1", "paper-2", "rush-hour")}


def test_a_driver_above_its_desired_speed_slows_at_the_comfortable_rate() -> None:
    """On a free road IDM's a (1 − (v/v0)^δ) asks for 9 m/s² at 1.7 v0; bounded at −b, as in
    the improved IDM. Below v0, and behind a leader, IDM is unchanged."""
    p = Idm()
    free = float("inf")
    assert _idm_accel(17.0, 10.0, free, 0.0, p) == pytest.approx(-p.b)
    assert _idm_accel(10.5, 10.0, free, 0.0, p) == pytest.approx(p.a * (1 - 1.05**4))  # above -b: IDM's
    assert _idm_accel(5.0, 10.0, free, 0.0, p) == pytest.approx(p.a * (1 - 0.5**4))
    s_star = p.s0 + 10.0 * p.T + 10.0 * 4.0 / (2 * np.sqrt(p.a * p.b))
    assert _idm_accel(10.0, 10.0, 20.0, 4.0, p) == pytest.approx(-p.a * (s_star / 20.0) ** 2)


@pytest.mark.parametrize("name", ["paper-1", "paper-2", "rush-hour"])
def test_turns_are_taken_near_the_lateral_cap_after_comfortable_braking(traffic, name) -> None:
    """Every vehicle takes its turns at about the 2 m/s² lateral cap (3 at most: the 0.1 s steps),
    braking for them at IDM's comfortable rate: in paper-1 and paper-2 nobody brakes harder than
    a red light asks (3.5 m/s²), in rush-hour too, where turns from opposite approaches merge into
    one exit lane. The cap on the next 30 m alone made paper-1's V0 brake at 9 m/s² and still
    take a 3 m radius at 6 m/s (12 m/s² lateral)."""
    scn, tr = traffic[name]
    turned = 0
    for vid, route in tr.routes.items():
        v = tr.v[vid]
        kappa = np.abs(route.path.curvature(tr.s[vid]))
        lateral = kappa * v * v
        assert lateral.max() < LAT_ACCEL_MAX + 1.0, (vid, lateral.max())
        turned += int(kappa.max() > 0.05)
        assert np.min(np.diff(v) / STEP) > -3.6, (vid, np.min(np.diff(v) / STEP))
    assert turned >= 1


def test_a_vehicle_waiting_to_depart_holds_nobody_up(traffic) -> None:
    """Rush-hour's N5-N7 depart after a minute from where N1-N3 start: until then they are parked
    off the lane, and N2-N4 drive up to the queue at the stop line (they stood 140 m before it,
    behind the parked cars, for a minute)."""
    scn, tr = traffic["rush-hour"]
    spec = {v.id: v for v in scn.vehicles}
    k25 = int(round(25.0 / STEP))
    line = tr.routes["N1"].segments[0].s1
    for vid in ("N2", "N3", "N4"):
        assert tr.s[vid][k25] > line - 40.0, (vid, tr.s[vid][k25], line)
    for vid in ("N5", "N6", "N7"):
        k = int(round(spec[vid].depart / STEP))
        assert np.all(tr.s[vid][:k] == spec[vid].depart_pos) and tr.s[vid][-1] > spec[vid].depart_pos + 50.0


def test_a_vehicle_parked_by_the_stop_line_is_not_the_queue_head() -> None:
    """Paper-1 with V2 parked 3 m short of NB_in's stop line until after the scenario: V1 drives
    past it to the line and is the first stopped vehicle; V2, parked off the lane, never is."""
    import tomllib

    from slcp.hw_emulation.geometry import polyline_length
    from slcp.hw_emulation.scenario import parse_scenario, shipped_scenario_text
    from slcp.hw_emulation.traffic import first_stopped_flags

    data = tomllib.loads(shipped_scenario_text("paper-1"))
    scn = parse_scenario(data, "paper-1.toml")
    line = polyline_length(scn.lanes["NB_in"].centerline)
    vehicles = [dict(v) for v in data["vehicles"]]
    v2 = next(v for v in vehicles if v["id"] == "V2")
    v2.update(depart=1000.0, depart_pos=line - 3.0, initial_speed=0.0)
    scn = parse_scenario(dict(data, vehicles=vehicles, events=[], windows={}, paper={}), "parked.toml")
    tr = simulate_traffic(scn, np.random.default_rng(0))
    flags = first_stopped_flags(scn, tr)
    assert flags["V1"].any() and not flags["V2"].any()
    assert tr.s["V1"][-1] > line - 10.0 and np.all(tr.s["V2"] == line - 3.0)


def _min_gap_in_lanes(scn, tr) -> tuple[float, tuple]:
    """The smallest bumper-to-bumper gap [m] between two departed vehicles on one segment, over
    the run, and where: (follower, leader, segment, time)."""
    spec = {v.id: v for v in scn.vehicles}
    best, where = np.inf, ()
    for k, tk in enumerate(tr.t):
        on: dict[str, list] = {}
        for vid, route in tr.routes.items():
            if tk >= spec[vid].depart:
                seg = route.segment_at(tr.s[vid][k])
                on.setdefault(seg.key, []).append((tr.s[vid][k] - seg.s0, vid))
        for key, lst in on.items():
            lst.sort()
            for (a, va), (b, vb) in zip(lst, lst[1:]):
                g = (b + spec[vb].l0 - spec[vb].length) - (a + spec[va].l0)
                if g < best:
                    best, where = g, (va, vb, key, round(float(tk), 1))
    return best, where


def _rush_hour_with(vehicles):
    import tomllib

    from slcp.hw_emulation.scenario import parse_scenario, shipped_scenario_text

    data = tomllib.loads(shipped_scenario_text("rush-hour"))
    return parse_scenario(dict(data, vehicles=vehicles, events=[], windows={}, paper={}), "merge.toml")


def _rush_hour_vehicles(*ids):
    import tomllib

    from slcp.hw_emulation.scenario import shipped_scenario_text

    data = tomllib.loads(shipped_scenario_text("rush-hour"))
    return [dict(v) for v in data["vehicles"] if v["id"] in ids]


def test_turns_into_one_exit_lane_enter_it_one_after_the_other(traffic, monkeypatch) -> None:
    """Rush-hour's E1 (a left turn into NB_out) and W3 (the opposite right turn into it) reach
    the exit lane together on the same green. The one nearer to the merge point goes first; the
    other makes room before the merge at no more than the comfortable deceleration, and enters
    a safe gap behind. Without the rule (a zero horizon) they met in the lane: E1 braked at
    9 m/s² and still ran 4 m into W3. Over the whole of rush-hour, no two vehicles in one lane
    come closer than IDM's standstill gap."""
    from slcp.hw_emulation import traffic as traffic_mod

    scn = _rush_hour_with(_rush_hour_vehicles("E1", "W3"))
    tr = simulate_traffic(scn, np.random.default_rng(0))
    gap, where = _min_gap_in_lanes(scn, tr)
    assert gap > 1.5, where
    for vid in ("E1", "W3"):
        assert np.min(np.diff(tr.v[vid]) / STEP) > -(Idm().b + 0.9), vid
    first = {vid: tr.t[int(np.argmax(tr.s[vid] >= tr.routes[vid].segments[-1].s0))] for vid in ("E1", "W3")}
    assert first["W3"] + 1.0 < first["E1"], first  # W3 turns right from nearer; E1 follows

    monkeypatch.setattr(traffic_mod, "MERGE_HORIZON", 0.0)
    off = simulate_traffic(scn, np.random.default_rng(0))
    assert _min_gap_in_lanes(scn, off)[0] < 0.0
    assert np.min(np.diff(off.v["E1"]) / STEP) < -8.0
    monkeypatch.undo()

    scn, full = traffic["rush-hour"]
    gap, where = _min_gap_in_lanes(scn, full)
    assert gap > 1.5, where


def test_a_vehicle_held_by_a_red_light_does_not_merge_ahead() -> None:
    """A vehicle standing at its red light, 20 m from where its left turn joins NB_out, is nearer
    to that merge point than N1 driving through on green: it is no leader for N1, whose drive is
    the same to the bit as beside the same vehicle parked off the road for the whole run (as a
    leader it would have had N1 slow down for it). It turns on its next green, after N1."""
    n1 = _rush_hour_vehicles("N1")
    waiting = dict(n1[0], id="E9", route=["EB_in_L", "NB_out"], depart=32.0, depart_pos=385.0,
                   initial_speed=0.0)
    a = simulate_traffic(_rush_hour_with(n1 + [dict(waiting, depart=1000.0)]), np.random.default_rng(0))
    b = simulate_traffic(_rush_hour_with(n1 + [waiting]), np.random.default_rng(0))
    np.testing.assert_array_equal(a.s["N1"], b.s["N1"])
    k_red = int(round(40.0 / STEP))
    e9 = b.routes["E9"]
    assert b.v["E9"][k_red] == 0.0 and e9.segments[-1].s0 - b.s["E9"][k_red] < 30.0
    k = int(np.argmax(b.s["N1"] >= b.routes["N1"].segments[-1].s0))  # N1 joins NB_out
    assert b.t[k] < 58.0 and b.s["E9"][k] == b.s["E9"][k_red]
    assert b.s["E9"][-1] > e9.segments[-1].s0
