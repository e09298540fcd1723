"""Sites from Lanelet2 maps (#45): maps written with the lanelet2 library itself are read back
with every lane and stop line where it was written; the shipped scenarios' sites survive a
round trip; bad maps give errors that name the file."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.geo.lanelet2_site import SiteMapError, read_lanelet2, read_projector_info, write_lanelet2
from slcp.geo.site import offset_polyline

lanelet2 = pytest.importorskip("lanelet2")
from lanelet2.core import AttributeMap, Lanelet, LaneletMap, LineString3d, Point3d, TrafficLight, getId  # noqa: E402

ORIGIN_DEG = (48.98, 8.39, 115.0)  # the origin the test's maps are written in
TOL = 0.01  # [m] acceptance: every stop line and lane within 1 cm of where it was written


def _ls(ne, **attrs) -> LineString3d:
    return LineString3d(getId(), [Point3d(getId(), float(e), float(n), 0.0) for n, e in ne], AttributeMap(attrs))


def _heading(deg: float) -> np.ndarray:
    """The unit direction (north, east) of a heading clockwise from north."""
    return np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])


class Junction:
    """A junction written with the lanelet2 library: per arm at ``headings`` (of travel towards
    the centre, degrees clockwise from north) an approach lane that ends at a stop line 12 m
    from the centre and an exit lane leaving on the other side of the road."""

    def __init__(self, headings: list[float], width: float = 3.5) -> None:
        self.map = LaneletMap()
        self.expected: dict[str, tuple[np.ndarray, float, np.ndarray | None]] = {}  # centre, width, stop ends
        for k, h in enumerate(headings):
            d = _heading(h)
            right = np.array([-d[1], d[0]])
            end = -12.0 * d + right * width / 2  # keep right
            # an approach with a bend 40 m out: a centre line of more than two points
            centre = np.array([end - 80.0 * d + 3.0 * right, end - 40.0 * d, end - 20.0 * d, end])
            stop = np.array([end - right * width / 2, end + right * width / 2])
            self._add(f"arm{k}_in", centre, width, stop)
            out = np.array([-12.0 * d - right * width / 2, -90.0 * d - right * width / 2])
            self._add(f"arm{k}_out", out, width, None)

    def _add(self, name: str, centre: np.ndarray, width: float, stop: np.ndarray | None) -> None:
        left, right = offset_polyline(centre, -width / 2), offset_polyline(centre, width / 2)
        ll = Lanelet(getId(), _ls(left, type="line_thin", subtype="solid"),
                     _ls(right, type="line_thin", subtype="dashed"),
                     AttributeMap({"type": "lanelet", "subtype": "road", "name": name}))
        if stop is not None:
            light = _ls(stop + 2.0, type="traffic_light", subtype="red_yellow_green")
            ll.addRegulatoryElement(TrafficLight(getId(), AttributeMap(
                {"type": "regulatory_element", "subtype": "traffic_light"}), [light], _ls(stop, type="stop_line")))
        self.map.add(ll)
        self.expected[name] = (centre, width, stop)

    def write(self, folder) -> object:
        from lanelet2.io import Origin
        from lanelet2.projection import LocalCartesianProjector

        path = folder / "junction.osm"
        lanelet2.io.write(str(path), self.map, LocalCartesianProjector(Origin(*ORIGIN_DEG)))
        (folder / "map_projector_info.yaml").write_text(
            "projector_type: LocalCartesian\nvertical_datum: WGS84\nmap_origin:\n"
            f"  latitude: {ORIGIN_DEG[0]}\n  longitude: {ORIGIN_DEG[1]}\n  altitude: {ORIGIN_DEG[2]}\n")
        return path


def _hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance from a point of either polyline to the other polyline [m]."""

    def one_way(p, q):
        dense = np.vstack([q[i] + np.linspace(0, 1, 200)[:, None] * (q[i + 1] - q[i]) for i in range(len(q) - 1)])
        return max(np.min(np.hypot(*(dense - x).T)) for x in p)

    return max(one_way(a, b), one_way(b, a))


@pytest.mark.parametrize("headings", [[0.0, 37.0, 180.0, 270.0], [90.0, 270.0, 0.0]], ids=["four-way", "T"])
def test_a_lanelet2_map_reads_back_with_every_lane_and_stop_line_within_a_centimetre(tmp_path, headings) -> None:
    junction = Junction(headings)
    site = read_lanelet2(junction.write(tmp_path))
    assert site.origin_llh == pytest.approx((math.radians(ORIGIN_DEG[0]), math.radians(ORIGIN_DEG[1]),
                                             ORIGIN_DEG[2]), abs=1e-12)
    assert sorted(site.lanes) == sorted(junction.expected)
    for name, (centre, width, stop) in junction.expected.items():
        lane = site.lanes[name]
        assert _hausdorff(lane.centerline, centre) < TOL, name
        assert np.abs(lane.centerline[[0, -1]] - centre[[0, -1]]).max() < TOL, name
        assert lane.width == pytest.approx(width, abs=TOL)
        assert lane.markings == ("line_thin:solid", "line_thin:dashed")
        assert lane.stop_line == (stop is not None), name
        if stop is not None:
            assert np.abs(lane.stop_line_ends() - stop).max() < TOL, name
            h = math.degrees(lane.end_heading) % 360.0  # the direction of travel at the stop line
            assert min(abs(h - headings[int(name[3])]), 360 - abs(h - headings[int(name[3])])) < 0.01


def test_a_stop_line_short_of_the_lanelets_end_or_just_past_it_cuts_or_prolongs_the_lane(tmp_path) -> None:
    m = LaneletMap()
    for name, stop_n in (("short", 40.0), ("past", 51.5), ("far", 60.0)):
        centre = np.array([[0.0, 0.0], [50.0, 0.0]]) + [0.0, 10.0 * len(m.laneletLayer)]
        e = centre[0, 1]
        stop = np.array([[stop_n, e - 1.75], [stop_n + 0.5, e + 1.75]])  # slanted by 8°
        ll = Lanelet(getId(), _ls(offset_polyline(centre, -1.75)), _ls(offset_polyline(centre, 1.75)),
                     AttributeMap({"type": "lanelet", "subtype": "road", "name": name}))
        ll.addRegulatoryElement(TrafficLight(getId(), AttributeMap({"type": "regulatory_element",
                                                                    "subtype": "traffic_light"}),
                                             [_ls(stop + 3.0)], _ls(stop, type="stop_line")))
        m.add(ll)
    crosswalk = Lanelet(getId(), _ls([[0.0, -5.0], [0.0, -9.0]]), _ls([[2.0, -5.0], [2.0, -9.0]]),
                        AttributeMap({"type": "lanelet", "subtype": "crosswalk"}))
    m.add(crosswalk)
    from lanelet2.io import Origin
    from lanelet2.projection import LocalCartesianProjector

    path = tmp_path / "m.osm"
    lanelet2.io.write(str(path), m, LocalCartesianProjector(Origin(*ORIGIN_DEG)))
    origin = (math.radians(ORIGIN_DEG[0]), math.radians(ORIGIN_DEG[1]), ORIGIN_DEG[2])
    site = read_lanelet2(path, origin)
    assert sorted(site.lanes) == ["far", "past", "short"]  # not the crosswalk
    # the lane is cut where its centre line crosses the slanted line: 40.25 m
    assert site.lanes["short"].stop_line and site.lanes["short"].centerline[-1, 0] == pytest.approx(40.25, abs=1e-3)
    # the slant (8°) kept: the line meets the lane's bounds where it was drawn, and the agent measures along it
    short = site.lanes["short"]
    assert short.stop_slant == pytest.approx(tuple(np.array([0.5, 3.5]) / math.hypot(0.5, 3.5)), abs=1e-6)
    e = short.centerline[0, 1]
    assert np.abs(short.stop_line_ends() - [[40.0, e - 1.75], [40.5, e + 1.75]]).max() < TOL
    from slcp.deploy.agent_configs import approach_lanes

    stop = approach_lanes(site)["short"].approach.stop_line
    (a, b), (c, d) = stop.direction, short.stop_slant
    assert abs(a * d - b * c) < 1e-9  # parallel
    assert site.lanes["past"].stop_slant is not None and site.lanes["far"].stop_slant is None
    assert site.lanes["past"].stop_line and site.lanes["past"].centerline[-1, 0] == pytest.approx(51.75, abs=1e-3)
    assert not site.lanes["far"].stop_line and site.lanes["far"].centerline[-1, 0] == pytest.approx(50.0, abs=1e-3)


def test_the_shipped_scenarios_sites_survive_a_round_trip_through_lanelet2(tmp_path) -> None:
    from slcp.hw_emulation.scenario import load_scenario, shipped_scenarios

    for name in shipped_scenarios():
        site = load_scenario(name).site
        write_lanelet2(site, tmp_path / name / "map.osm")
        back = read_lanelet2(tmp_path / name / "map.osm")
        assert back.origin_llh == pytest.approx(site.origin_llh, abs=1e-12)
        assert sorted(back.lanes) == sorted(site.lanes)
        for lid, lane in site.lanes.items():
            b = back.lanes[lid]
            assert _hausdorff(b.centerline, lane.centerline) < 1e-3 and b.width == pytest.approx(lane.width, abs=1e-3)
            assert b.stop_line == lane.stop_line
            if lane.stop_line:
                assert np.abs(b.stop_line_ends() - lane.stop_line_ends()).max() < 1e-3


def test_bad_maps_and_origins_are_errors_that_name_the_file(tmp_path) -> None:
    garbage = tmp_path / "garbage.osm"
    garbage.write_bytes(b"\x00\xffnot xml")
    with pytest.raises(SiteMapError, match="garbage.osm: no map_projector_info.yaml beside it"):
        read_lanelet2(garbage)
    with pytest.raises(SiteMapError, match="garbage.osm: not a Lanelet2 map"):
        read_lanelet2(garbage, (0.8, 0.1, 0.0))
    with pytest.raises(SiteMapError, match="missing.osm: no such file"):
        read_lanelet2(tmp_path / "missing.osm", (0.8, 0.1, 0.0))
    with pytest.raises(SiteMapError, match="missing.osm: no such file"):  # not "no map_projector_info.yaml"
        read_lanelet2(tmp_path / "missing.osm")
    info = tmp_path / "map_projector_info.yaml"
    info.write_text("projector_type: MGRS\nmgrs_grid: 54SUE\n")
    with pytest.raises(SiteMapError, match="projector_type 'MGRS'"):
        read_projector_info(info)
    info.write_text("projector_type: LocalCartesian\nmap_origin: {latitude: 95, longitude: 0, altitude: 0}\n")
    with pytest.raises(SiteMapError, match="not a place on Earth"):
        read_projector_info(info)
    info.write_text("projector_type: LocalCartesian\nmap_origin: {latitude: 45}\n")
    with pytest.raises(SiteMapError, match="must give latitude, longitude"):
        read_projector_info(info)
    empty = tmp_path / "empty.osm"
    empty.write_text('<?xml version="1.0"?>\n<osm version="0.6" generator="test"></osm>\n')
    with pytest.raises(SiteMapError, match="empty.osm: no road lanelets"):
        read_lanelet2(empty, (0.8, 0.1, 0.0))


def test_an_agent_takes_its_stop_lines_and_lanes_from_a_lanelet2_map(tmp_path) -> None:
    """``[agent] site``: the scenario's own site, through Lanelet2, gives the agent the same stop
    lines, lanes and origin; without a scenario too; bad sites are errors that name the file."""
    from slcp.deploy.agent_configs import agent_config
    from slcp.deploy.processes import ConfigError, load_agent_config
    from slcp.hw_emulation.scenario import load_scenario

    scn = load_scenario("paper-1")
    write_lanelet2(scn.site, tmp_path / "maps" / "paper-1.osm")
    own = agent_config(scn, "V1")
    for extra in ('scenario = "paper-1"\n', ""):
        p = tmp_path / "agent.toml"
        p.write_text(f'[agent]\nvehicle = "V1"\n{extra}site = "maps/paper-1.osm"\n')
        cfg, _ = load_agent_config(p, None)
        assert cfg.origin_llh == pytest.approx(own.origin_llh, abs=1e-12)
        assert sorted(cfg.lanes) == sorted(own.lanes) and len(cfg.lanes) == len(scn.site.stop_lanes) > 0
        for lid, lane in own.lanes.items():
            a, b = lane.approach, cfg.lanes[lid].approach
            for x, y in ((a.stop_line, b.stop_line), (a.left_lane_line, b.left_lane_line)):
                assert np.allclose(x.point, y.point, atol=1e-5) and np.allclose(x.direction, y.direction, atol=1e-9)
            assert cfg.lanes[lid].width == pytest.approx(lane.width, abs=1e-6)
        assert sorted({s.lane for s in cfg.lane_map.segments}) == sorted(scn.lanes)
    # the same map in another frame: the origin given moves every line
    p.write_text('[agent]\nvehicle = "V1"\nsite = "maps/paper-1.osm"\nsite_origin = [39.9553, 116.3194, 50.0]\n')
    cfg, _ = load_agent_config(p, None)
    lid = next(iter(own.lanes))
    a, b = own.lanes[lid].approach.stop_line.point, cfg.lanes[lid].approach.stop_line.point
    assert b[0] - a[0] == pytest.approx(-11.1, abs=0.1) and b[1] == pytest.approx(a[1], abs=0.01)
    for body, match in (('site = "nowhere.osm"\n', "nowhere.osm: no such file"),
                        ('site = 3\n', "agent.site: must be the path of a Lanelet2 map"),
                        ('site = "maps/paper-1.osm"\nsite_origin = [95, 0, 0]\n', "agent.site_origin: must be"),
                        ('site_origin = [45, 0, 0]\n', "agent.site_origin: only with agent.site")):
        p.write_text(f'[agent]\nvehicle = "V1"\n{body}')
        with pytest.raises(ConfigError, match=match) as err:
            load_agent_config(p, None)
        assert str(p) in str(err.value)


def test_the_centre_line_lies_midway_between_bounds_of_different_point_counts() -> None:
    from slcp.geo.lanelet2_site import _midline

    left = np.array([[0.0, -2.0], [100.0, -2.0]])
    right = np.array([[0.0, 1.0], [30.0, 1.0], [55.0, 1.0], [100.0, 1.0]])
    mid = _midline(left, right)
    assert np.allclose(mid[:, 1], -0.5) and mid[0, 0] == 0.0 and mid[-1, 0] == 100.0
    assert np.allclose(mid[:, 0], [0.0, 30.0, 55.0, 100.0])  # a point at every vertex of either


@pytest.mark.parametrize("name", ["paper-1", "paper-2", "rush-hour"])
def test_a_vehicle_without_its_scenario_gets_the_configuration_the_scenario_gives(tmp_path, name) -> None:
    """#45 acceptance 4, the configuration: the standalone file of every vehicle of a shipped
    scenario (its site from a Lanelet2 map, its sensors written out, no scenario) loads into the
    engine configuration that the scenario gives, field by field."""
    import dataclasses

    from slcp.deploy.agent_configs import agent_config
    from slcp.deploy.processes import load_agent_config
    from slcp.deploy.vehicle_agent_file import standalone_agent_toml
    from slcp.hw_emulation.scenario import load_scenario

    scn = load_scenario(name)
    write_lanelet2(scn.site, tmp_path / "site.osm")
    for spec in scn.vehicles:
        p = tmp_path / f"agent-{spec.id}.toml"
        p.write_text(standalone_agent_toml(scn, spec.id, "site.osm", ("SP", "SL-CP"), "split-ci", False))
        cfg, _ = load_agent_config(p, None)
        own = agent_config(scn, spec.id, ("SP", "SL-CP"), "split-ci", False)
        assert "scenario" not in p.read_text()
        for f in dataclasses.fields(own):
            a, b = getattr(own, f.name), getattr(cfg, f.name)
            if f.name == "lanes":
                assert sorted(a) == sorted(b)
                for lid in a:
                    for x, y in ((a[lid].approach.stop_line, b[lid].approach.stop_line),
                                 (a[lid].approach.left_lane_line, b[lid].approach.left_lane_line)):
                        assert np.allclose(x.point, y.point, atol=1e-5) and np.allclose(x.direction, y.direction)
            elif f.name == "lane_map":
                assert [s.lane for s in a.segments] == [s.lane for s in b.segments]
                assert [s.width for s in a.segments] == pytest.approx([s.width for s in b.segments], abs=1e-5)
            elif f.name == "origin_llh":
                assert b == pytest.approx(a, abs=1e-12)
            else:
                assert a == b, f.name


def test_slcp_scenario_to_lanelet2_writes_the_map_and_keeps_an_existing_one(tmp_path, capsys) -> None:
    from slcp.deploy.cli import main
    from slcp.hw_emulation.scenario import load_scenario

    out = tmp_path / "maps" / "paper-2.osm"
    assert main(["scenario", "to-lanelet2", "paper-2", str(out)]) == 0
    site = read_lanelet2(out)
    assert sorted(site.lanes) == sorted(load_scenario("paper-2").lanes)
    assert main(["scenario", "to-lanelet2", "paper-2", str(out)]) == 2
    assert "exists (use --force to replace it)" in capsys.readouterr().err
    assert main(["scenario", "to-lanelet2", "paper-2", str(out), "--force"]) == 0
    assert main(["scenario", "to-lanelet2", "no-such-scenario", str(tmp_path / "x.osm")]) == 2
    assert "unknown scenario 'no-such-scenario'" in capsys.readouterr().err
