"""Scenario files (TOML): map, signals, vehicles, sensors, radio, events and evaluation windows.

The format is documented in docs/scenario-format.md. Units: metres, seconds, m/s;
the geodetic origin in degrees (converted here). Sensor sections use the field names of
:class:`~hw_emulation.sensors.imu.ImuModel`, :class:`~hw_emulation.sensors.gnss.GnssModel`,
:class:`~hw_emulation.sensors.uwb.UwbModel` and :class:`~hw_emulation.sensors.radio.RadioModel`
(SI units). Every error names the file, the field path and the reason.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from slcp.geo.site import Lane, Site

from .geometry import polyline_length
from .sensors.camera import LaneCameraModel
from .sensors.gnss import GnssModel
from .sensors.imu import ImuModel, imu_model_of
from .sensors.radio import RadioModel
from .sensors.uwb import UwbModel
from .toml_checks import Ctx, ScenarioError, array_of, check_keys
from .toml_checks import model_from_table as model_from_table  # the agent file's reader takes it from here
from .trajectory_source import TrajectorySource, parse_trajectories

EVENT_KINDS = ("first_stopped", "stopped", "moving", "passes_stop_line", "near", "green", "time", "end")

#: the evaluation window each run adds per vehicle: the times it truly stands still (a scenario
#: may not define a window of that name)
STANDING_WINDOW = "standing"
MAX_IMU_RATE = 2000.0  #: [Hz] the highest IMU rate of a scenario (vehicle IMUs output at most 1-2 kHz)
#: Physical bounds on a scenario's numbers: beyond them a value is a typo, and the emulation would
#: allocate its truth for it (a day at 100 Hz is 8.6 M samples a vehicle)
MAX_DURATION = 86400.0  #: [s] a day
MAX_EXTENT = 50e3  #: [m] a site's lanes within this of its origin (one local frame)
MAX_LANE_WIDTH = 10.0  #: [m]
MAX_SPEED = 70.0  #: [m/s] 250 km/h
MAX_VEHICLE_LENGTH = 30.0  #: [m] a road train's
#: IDM's a and b [m/s²] (a car's limits), s0 [m], T [s] and δ at most
IDM_BOUNDS = {"a": 10.0, "b": 10.0, "s0": 20.0, "T": 10.0, "delta": 10.0}


@dataclass(frozen=True)
class SignalPhase:
    lanes: tuple[str, ...]
    green_start: float
    green_end: float


@dataclass(frozen=True)
class Signals:
    cycle: float
    offset: float
    phases: tuple[SignalPhase, ...]

    def is_green(self, lane: str, t: float) -> bool:
        """True if ``lane`` may cross its stop line at time ``t`` (lanes without a phase: always)."""
        ph = [p for p in self.phases if lane in p.lanes]
        if not ph:
            return True
        c = (t - self.offset) % self.cycle
        return any(p.green_start <= c < p.green_end for p in ph)


@dataclass(frozen=True)
class Idm:
    """Intelligent Driver Model parameters: max accel a, comfortable decel b [m/s²], jam gap
    s0 [m], time headway T [s], exponent delta."""

    a: float = 1.5
    b: float = 2.0
    s0: float = 2.0
    T: float = 1.2
    delta: float = 4.0


@dataclass(frozen=True)
class VehicleSpec:
    id: str
    route: tuple[str, ...]
    depart: float
    depart_pos: float
    desired_speed: float
    idm: Idm
    length: float
    l0: float  #: reference point O_b (IMU) behind the front [m]
    stop_gap: tuple[float, float]  #: d_s ~ N(m_xb, σ_xb²), front to stop line [m]
    lateral: tuple[float, float]  #: d_l ~ N(m_yb, σ_yb²), O_b right of the left lane line [m]
    imu: ImuModel
    gnss: GnssModel
    initial_speed: float = 0.0
    #: correlation of the driver's d_l in one lane of its route with its d_l in the lane before:
    #: 0, a new draw in every lane (the filters' model); 1, one offset kept on the whole route
    lateral_correlation: float = 0.0


@dataclass(frozen=True)
class EventSpec:
    """A named instant defined from the truth (see docs/scenario-format.md)."""

    name: str
    kind: str
    vehicle: str | None = None
    time: float | None = None
    other: str | None = None
    distance: float | None = None
    lane: str | None = None


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    seed: int
    duration: float
    imu_rate: float
    origin_llh: tuple[float, float, float]  #: radians, radians, metres
    lanes: dict[str, Lane]
    signals: Signals
    vehicles: tuple[VehicleSpec, ...]
    uwb: UwbModel
    radio: RadioModel
    common_mode_sigma: float
    common_mode_tau: float
    events: tuple[EventSpec, ...]
    windows: dict[str, tuple[str, str]]
    paper_table: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    #: the vehicles' IMU batches start at evenly spread phases instead of all at once (clocks of
    #: different vehicles are not synchronised; spreads a large fleet's load over time)
    imu_stagger: bool = False
    #: IMU samples per message (an IMU driver's batch): 10 at 100 Hz is a message every 0.1 s
    imu_batch: int = 10
    camera: LaneCameraModel = field(default_factory=LaneCameraModel)  #: every vehicle's lane camera
    #: the vehicles' paths from a file instead of the traffic model (:mod:`hw_emulation.trajectory_truth`)
    trajectories: TrajectorySource | None = None

    @property
    def site(self) -> Site:
        """The scenario's lanes and stop lines, the site an agent deployed there would carry."""
        return Site(self.origin_llh, self.lanes)


def _correlation(ctx: Ctx, d: dict, path: str) -> float:
    """``d``'s ``correlation`` (default 0), a correlation coefficient in [0, 1]."""
    rho = ctx.number(d, "correlation", path, 0.0, non_negative=True)
    if rho > 1.0:
        raise ctx.fail(f"{path}.correlation", f"must be within [0, 1], got {rho!r}")
    return rho


def parse_scenario(data: dict, source: str = "<scenario>") -> Scenario:
    """Validate a parsed TOML document and build a :class:`Scenario`."""
    ctx = Ctx(source)
    check_keys(ctx, data, {"scenario", "lanes", "signals", "vehicles", "sensors", "radio", "uwb",
                           "events", "windows", "paper", "trajectories"}, "")
    sc = ctx.table(data, "scenario", "", required=True)
    head = _parse_header(ctx, sc)
    lanes = _parse_lanes(ctx, data)
    signals = _parse_signals(ctx, data, lanes)
    sensors = ctx.table(data, "sensors", "")
    check_keys(ctx, sensors, {"imu", "gnss", "camera"}, "sensors")
    imu_base = ctx.model(ImuModel, ctx.table(sensors, "imu", "sensors"), "sensors.imu")
    gnss_base = ctx.model(GnssModel, ctx.table(sensors, "gnss", "sensors"), "sensors.gnss")
    camera = ctx.model(LaneCameraModel, ctx.table(sensors, "camera", "sensors"), "sensors.camera")
    uwb = ctx.model(UwbModel, ctx.table(data, "uwb", ""), "uwb")
    radio = ctx.model(RadioModel, ctx.table(data, "radio", ""), "radio")
    vehicles = _parse_vehicles(ctx, data, lanes, imu_base, gnss_base)
    events = _parse_events(ctx, data, lanes, {v.id for v in vehicles})
    windows = _parse_windows(ctx, data, events)
    return Scenario(
        **head, description=str(sc.get("description", "")), lanes=lanes, signals=signals,
        vehicles=tuple(vehicles), uwb=uwb, radio=radio,
        common_mode_sigma=ctx.number(sc, "common_mode_sigma", "scenario", 1.5, non_negative=True),
        common_mode_tau=ctx.number(sc, "common_mode_tau", "scenario", 600.0, positive=True),
        events=tuple(events), windows=windows, paper_table=ctx.table(data, "paper", ""), source=source,
        camera=camera, trajectories=parse_trajectories(ctx, ctx.table(data, "trajectories", "")),
    )


def _parse_header(ctx: Ctx, sc: dict) -> dict:
    """The ``[scenario]`` table's name, seed, duration, IMU rate and batching, and origin."""
    check_keys(ctx, sc, {"name", "description", "seed", "duration", "imu_rate", "origin",
                         "common_mode_sigma", "common_mode_tau", "imu_stagger", "imu_batch"}, "scenario")
    imu_stagger = sc.get("imu_stagger", False)
    if not isinstance(imu_stagger, bool):
        raise ctx.fail("scenario.imu_stagger", f"must be true or false, got {imu_stagger!r}")
    name = ctx.string(sc, "name", "scenario")
    seed = sc.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ctx.fail("scenario.seed", f"must be a non-negative integer, got {seed!r}")
    duration = ctx.number(sc, "duration", "scenario", positive=True, maximum=MAX_DURATION)
    imu_rate = ctx.number(sc, "imu_rate", "scenario", 100.0, positive=True)
    if imu_rate > MAX_IMU_RATE:
        raise ctx.fail("scenario.imu_rate", f"must be at most {MAX_IMU_RATE:g} Hz, got {imu_rate:g}")
    if abs(round(imu_rate / 10.0) * 10.0 - imu_rate) > 1e-9:
        raise ctx.fail("scenario.imu_rate", "must be a multiple of 10 Hz (the traffic step is 0.1 s)")
    imu_batch = sc.get("imu_batch", 10)
    if isinstance(imu_batch, bool) or not isinstance(imu_batch, int) or not 1 <= imu_batch <= imu_rate:
        raise ctx.fail("scenario.imu_batch", f"must be an integer from 1 to imu_rate (at most 1 s of samples), "
                                             f"got {imu_batch!r}")
    org = ctx.table(sc, "origin", "scenario", required=True)
    lat = ctx.number(org, "lat", "scenario.origin")
    lon = ctx.number(org, "lon", "scenario.origin")
    if not -90 < lat < 90 or not -180 <= lon <= 180:
        raise ctx.fail("scenario.origin", f"latitude/longitude out of range: {lat}, {lon}")
    origin = (math.radians(lat), math.radians(lon), ctx.number(org, "h", "scenario.origin", 0.0))

    return {"name": name, "seed": seed, "duration": duration, "imu_rate": imu_rate, "origin_llh": origin,
            "imu_stagger": imu_stagger, "imu_batch": imu_batch}


def _parse_lanes(ctx: Ctx, data: dict) -> dict[str, Lane]:
    lanes: dict[str, Lane] = {}
    raw_lanes = data.get("lanes")
    if not isinstance(raw_lanes, list) or not raw_lanes:
        raise ctx.fail("lanes", "must be a non-empty array of tables")
    for i, ln in enumerate(raw_lanes):
        p = f"lanes[{i}]"
        if not isinstance(ln, dict):
            raise ctx.fail(p, "must be a table")
        check_keys(ctx, ln, {"id", "centerline", "width", "stop_line"}, p)
        lid = ctx.string(ln, "id", p)
        if lid in lanes:
            raise ctx.fail(f"{p}.id", f"duplicate lane id {lid!r}")
        try:
            cl = np.asarray(ln.get("centerline"), float)
        except (TypeError, ValueError):
            raise ctx.fail(f"{p}.centerline", "must be a list of [north, east] pairs") from None
        if cl.ndim != 2 or cl.shape[1] != 2 or len(cl) < 2 or not np.all(np.isfinite(cl)):
            raise ctx.fail(f"{p}.centerline", "must be at least two finite [north, east] points")
        if np.max(np.abs(cl)) > MAX_EXTENT:
            raise ctx.fail(f"{p}.centerline", f"must lie within {MAX_EXTENT / 1e3:g} km of the origin")
        if np.any(np.linalg.norm(np.diff(cl, axis=0), axis=1) < 1e-6):
            raise ctx.fail(f"{p}.centerline", "has repeated consecutive points")
        stop = ln.get("stop_line", False)
        if not isinstance(stop, bool):
            raise ctx.fail(f"{p}.stop_line", "must be true or false")
        lanes[lid] = Lane(lid, cl, ctx.number(ln, "width", p, 3.5, positive=True, maximum=MAX_LANE_WIDTH), stop)

    return lanes


def _parse_signals(ctx: Ctx, data: dict, lanes: dict[str, Lane]) -> Signals:
    sg = ctx.table(data, "signals", "")
    check_keys(ctx, sg, {"cycle", "offset", "phases"}, "signals")
    cycle = ctx.number(sg, "cycle", "signals", 60.0, positive=True)
    phases = []
    for i, ph in enumerate(array_of(ctx, sg, "phases", "signals")):
        p = f"signals.phases[{i}]"
        check_keys(ctx, ph, {"lanes", "green"}, p)
        ls = ph.get("lanes")
        if not isinstance(ls, list) or not all(isinstance(x, str) for x in ls):
            raise ctx.fail(f"{p}.lanes", "must be a list of lane ids")
        for x in ls:
            if x not in lanes:
                raise ctx.fail(f"{p}.lanes", f"unknown lane {x!r}")
            if not lanes[x].stop_line:
                raise ctx.fail(f"{p}.lanes", f"lane {x!r} has no stop line")
        g = ph.get("green")
        if not (isinstance(g, list) and len(g) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in g)
                and 0.0 <= g[0] < g[1] <= cycle):
            raise ctx.fail(f"{p}.green", f"must be [start, end] seconds into the cycle, 0 <= start < end <= cycle "
                                         f"({cycle:g} s), got {g!r}")
        phases.append(SignalPhase(tuple(ls), float(g[0]), float(g[1])))
    return Signals(cycle, ctx.number(sg, "offset", "signals", 0.0), tuple(phases))



def _profile_imu(ctx: Ctx, v: dict, path: str, imu_base: ImuModel) -> ImuModel:
    """The emulated IMU of a vehicle with a ``profile`` (a vehicle profile file, relative to the
    scenario's folder): the profile's datasheet noise and biases; else ``imu_base``."""
    if "profile" not in v:
        return imu_base
    from slcp.vehicles.profile import ProfileError, load_profile

    name = ctx.string(v, "profile", path)
    try:
        spec = load_profile(Path(ctx.source).parent / name).imu
    except ProfileError as exc:
        raise ctx.fail(f"{path}.profile", str(exc)) from None
    return imu_model_of(spec)


def _parse_vehicles(ctx: Ctx, data: dict, lanes: dict[str, Lane], imu_base: ImuModel,
                    gnss_base: GnssModel) -> list[VehicleSpec]:
    vehicles = []
    raw_v = data.get("vehicles")
    if not isinstance(raw_v, list) or not raw_v:
        raise ctx.fail("vehicles", "must be a non-empty array of tables")
    ids = set()
    for i, v in enumerate(raw_v):
        p = f"vehicles[{i}]"
        check_keys(ctx, v, {"id", "route", "depart", "depart_pos", "desired_speed", "initial_speed", "idm",
                            "length", "l0", "stop_gap", "lateral", "imu", "gnss", "profile"}, p)
        vid = ctx.string(v, "id", p)
        if vid in ids:
            raise ctx.fail(f"{p}.id", f"duplicate vehicle id {vid!r}")
        ids.add(vid)
        route = v.get("route")
        if not isinstance(route, list) or not route or not all(isinstance(x, str) for x in route):
            raise ctx.fail(f"{p}.route", "must be a non-empty list of lane ids")
        for x in route:
            if x not in lanes:
                raise ctx.fail(f"{p}.route", f"unknown lane {x!r}")
        idm_d = ctx.table(v, "idm", p)
        idm = ctx.model(Idm, idm_d, f"{p}.idm")
        for k, most in IDM_BOUNDS.items():
            x = getattr(idm, k)
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not 0 < x <= most:
                raise ctx.fail(f"{p}.idm.{k}", f"must be a number above 0 and at most {most:g}, got {x!r}")
        sgap = ctx.table(v, "stop_gap", p)
        check_keys(ctx, sgap, {"mean", "sigma"}, f"{p}.stop_gap")
        lat_d = ctx.table(v, "lateral", p)
        check_keys(ctx, lat_d, {"mean", "sigma", "correlation"}, f"{p}.lateral")
        first = lanes[route[0]]
        depart_pos = ctx.number(v, "depart_pos", p, 0.0, non_negative=True)
        if depart_pos >= polyline_length(first.centerline):
            raise ctx.fail(f"{p}.depart_pos", f"beyond the end of lane {first.id!r}")
        vehicles.append(VehicleSpec(
            id=vid, route=tuple(route),
            depart=ctx.number(v, "depart", p, 0.0, non_negative=True),
            depart_pos=depart_pos,
            desired_speed=ctx.number(v, "desired_speed", p, 12.0, positive=True, maximum=MAX_SPEED),
            initial_speed=ctx.number(v, "initial_speed", p, 0.0, non_negative=True, maximum=MAX_SPEED),
            idm=idm,
            length=ctx.number(v, "length", p, 4.6, positive=True, maximum=MAX_VEHICLE_LENGTH),
            l0=ctx.number(v, "l0", p, 2.5, non_negative=True, maximum=MAX_VEHICLE_LENGTH),
            stop_gap=(ctx.number(sgap, "mean", f"{p}.stop_gap", 1.5),
                      ctx.number(sgap, "sigma", f"{p}.stop_gap", 0.3, non_negative=True)),
            lateral=(ctx.number(lat_d, "mean", f"{p}.lateral", first.width / 2),
                     ctx.number(lat_d, "sigma", f"{p}.lateral", 0.15, non_negative=True)),
            lateral_correlation=_correlation(ctx, lat_d, f"{p}.lateral"),
            imu=ctx.model(ImuModel, ctx.table(v, "imu", p), f"{p}.imu", _profile_imu(ctx, v, p, imu_base)),
            gnss=ctx.model(GnssModel, ctx.table(v, "gnss", p), f"{p}.gnss", gnss_base),
        ))

    return vehicles


def _parse_events(ctx: Ctx, data: dict, lanes: dict[str, Lane], ids: set[str]) -> list[EventSpec]:
    events = []
    names: set[str] = set()
    for i, e in enumerate(array_of(ctx, data, "events")):
        p = f"events[{i}]"
        check_keys(ctx, e, {"name", "kind", "vehicle", "time", "other", "distance", "lane"}, p)
        en = ctx.string(e, "name", p)
        if en in names:
            raise ctx.fail(f"{p}.name", f"duplicate event {en!r}")
        names.add(en)
        kind = ctx.string(e, "kind", p)
        if kind not in EVENT_KINDS:
            raise ctx.fail(f"{p}.kind", f"must be one of {', '.join(EVENT_KINDS)}, got {kind!r}")
        veh = e.get("vehicle")
        if kind in ("first_stopped", "stopped", "moving", "passes_stop_line", "near") and not (
                isinstance(veh, str) and veh in ids):
            raise ctx.fail(f"{p}.vehicle", f"unknown or missing vehicle {veh!r}")
        tm = ctx.number(e, "time", p, non_negative=True) if kind == "time" else None
        other = dist = lane = None
        if kind == "near":
            other = e.get("other")
            if not isinstance(other, str) or other not in ids or other == veh:
                raise ctx.fail(f"{p}.other", f"must be another vehicle id, got {other!r}")
            dist = ctx.number(e, "distance", p, positive=True)
        if kind == "green":
            lane = e.get("lane")
            if not isinstance(lane, str) or lane not in lanes or not lanes[lane].stop_line:
                raise ctx.fail(f"{p}.lane", f"must be a lane with a stop line, got {lane!r}")
        events.append(EventSpec(en, kind, veh, tm, other, dist, lane))
    return events


def _parse_windows(ctx: Ctx, data: dict, events: list[EventSpec]) -> dict[str, tuple[str, str]]:
    """The evaluation windows; one between two fixed times must not end before it starts."""
    names = {e.name: e for e in events}
    windows = {}
    for wn, w in ctx.table(data, "windows", "").items():
        if wn == STANDING_WINDOW:
            raise ctx.fail(f"windows.{wn}", "is reserved: the evaluation adds it per vehicle (its times at rest)")
        if not (isinstance(w, list) and len(w) == 2 and all(isinstance(x, str) and x in names for x in w)):
            raise ctx.fail(f"windows.{wn}", f"must be [start_event, end_event] of defined events, got {w!r}")
        a, b = names[w[0]], names[w[1]]
        if a.kind == "time" and b.kind == "time" and b.time < a.time:
            raise ctx.fail(f"windows.{wn}", f"ends ({w[1]} at {b.time:g} s) before it starts ({w[0]} at {a.time:g} s)")
        windows[wn] = (w[0], w[1])
    return windows


def load_scenario(path_or_name: str | Path) -> Scenario:
    """Load a scenario from a TOML file, or a shipped one by name (``paper-1``, ...)."""
    p = Path(path_or_name)
    if p.suffix == ".toml" or p.exists():
        try:
            text = p.read_text()
        except OSError as exc:
            raise ScenarioError(f"{p}: cannot read ({exc.strerror})") from exc
        except UnicodeDecodeError:
            raise ScenarioError(f"{p}: not a scenario file (not UTF-8 text)") from None
        source = str(p)
    else:
        text = shipped_scenario_text(str(path_or_name))
        source = f"{path_or_name}.toml"
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: not valid TOML ({exc})") from exc
    return parse_scenario(data, source)


def shipped_scenario_text(name: str) -> str:
    """The TOML text of the shipped scenario ``name`` (:class:`ScenarioError` if there is none)."""
    if name not in shipped_scenarios():
        raise ScenarioError(f"unknown scenario {name!r}; shipped: {', '.join(shipped_scenarios())}")
    return resources.files("slcp.hw_emulation.scenarios").joinpath(f"{name}.toml").read_text()


def scenario_lasting(scenario: str, duration: float, folder: Path) -> Path:
    """A copy of ``scenario`` (shipped name or file) that lasts ``duration`` seconds of sensor
    time, written to ``folder`` as ``<name>-<duration>s.toml`` (a long soak, or a short test of a
    mechanism that needs the fleet running, not the whole drive)."""
    text = Path(scenario).read_text() if Path(scenario).is_file() else shipped_scenario_text(scenario)
    new, n = re.subn(r"(?m)^duration\s*=.*$", f"duration = {float(duration)!r}", text, count=1)
    if n != 1:
        raise ScenarioError(f"scenario {scenario!r} has no 'duration' line to change")
    path = Path(folder) / f"{Path(scenario).stem}-{duration:g}s.toml"
    path.write_text(new)
    if abs(load_scenario(str(path)).duration - duration) > 1e-9:
        raise ScenarioError(f"the copy of {scenario!r} in {path} does not last {duration:g} s")
    return path


def shipped_scenarios() -> list[str]:
    """Names of the scenarios shipped with the package."""
    root = resources.files("slcp.hw_emulation.scenarios")
    return sorted(f.name[:-5] for f in root.iterdir() if f.name.endswith(".toml"))
