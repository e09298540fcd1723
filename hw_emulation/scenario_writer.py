"""Scenario TOML for vehicles that drive given trajectories (``[trajectories]``) on a given site:
what ``slcp scenario from-sumo`` and ``from-trajectories`` write."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from slcp.geo.site import Lane

from .external import Track, write_csv_tracks
from .scenario import load_scenario
from .trajectory_truth import motion_heading, project_lanes


@dataclass(frozen=True)
class ImportOptions:
    """The scenario's span and the vehicles' common settings (lengths [m], times [s], degrees)."""

    duration: float
    seed: int = 0
    origin: tuple[float, float, float] = (39.9552, 116.3194, 50.0)  #: lat, lon [deg], h [m] of the frame's origin
    stop_gap: tuple[float, float] = (1.5, 0.2)  #: the drivers' stop-line gap, mean and σ (the agents' prior)
    lateral_sigma: float = 0.12  #: σ of the drivers' lateral offset about the lane centre
    length: float = 4.6
    l0: float = 2.5  #: front to the vehicle's reference point
    point: str = "front"  #: what the trajectories' positions are of
    #: the scenario (shipped name or file) whose sensor, UWB and radio models and common-mode
    #: GNSS error the vehicles get ("": the defaults, an urban canyon with NLOS episodes)
    sensors_like: str = "paper-1"


def toml_value(v) -> str:
    """A TOML value of numbers, strings, booleans, lists and inline tables."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(round(float(v), 4))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(x)}" for k, x in v.items()) + " }"
    return "[" + ", ".join(toml_value(x) for x in v) + "]"


def sensor_tables(like: str) -> tuple[list[str], list[str]]:
    """The ``[scenario]`` common-mode lines and the ``[sensors.*]``, ``[uwb]`` and ``[radio]``
    tables of the scenario ``like`` (shipped name or TOML file)."""
    if not like:
        return [], []
    import tomllib

    from .scenario import shipped_scenario_text

    text = Path(like).read_text() if Path(like).is_file() else shipped_scenario_text(like)
    d = tomllib.loads(text)
    head = [f"{k} = {toml_value(v)}" for k, v in d.get("scenario", {}).items() if k.startswith("common_mode_")]
    tables: list[str] = []

    def emit(name: str, table: dict) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
        if scalars:
            tables.extend(["", f"[{name}]", *(f"{k} = {toml_value(v)}" for k, v in scalars.items())])
        for k, v in table.items():
            if isinstance(v, dict):
                emit(f"{name}.{k}", v)

    for key in ("sensors", "uwb", "radio"):
        if isinstance(d.get(key), dict):
            emit(key, d[key])
    return head, tables


def route_lanes(track: Track, lanes: dict[str, Lane]) -> list[str]:
    """The site lanes a track drives on, in order: its own lanes', or, without them, the lanes
    its positions lie on."""
    lane_ids = track.lane if track.detailed else project_lanes(track, motion_heading(track), lanes)[0]
    return [str(x) for x in dict.fromkeys(lane_ids) if str(x) in lanes]


def trajectory_scenario_toml(head: list[str], name: str, description: str, lanes: dict[str, Lane],
                             tracks: dict[str, Track], opt: ImportOptions,
                             routes: dict[str, list[str]],
                             signals: tuple[float, dict[str, list[tuple[float, float]]]] | None = None) -> str:
    """The TOML text: ``head`` (comment lines), the scenario, its trajectories
    (``trajectories.csv`` beside it), a window over the whole run, the signals (cycle, green
    windows per lane), the lanes and the vehicles (``routes``: the lanes each drives on)."""
    lat, lon, h = opt.origin
    v = toml_value
    common, tables = sensor_tables(opt.sensors_like)
    out = [*head, "", "[scenario]", f"name = {v(name)}", f"description = {v(description)}", f"seed = {opt.seed}",
           f"duration = {float(opt.duration)!r}", "imu_rate = 100.0", f"origin = {v({'lat': lat, 'lon': lon, 'h': h})}",
           *common]
    if tables:
        out += ["", f"# the sensors, UWB and radio of {opt.sensors_like}", *tables[1:]]
    out += ["", "[trajectories]", 'file = "trajectories.csv"', f"point = {v(opt.point)}", "",
           "# every vehicle is scored over the whole run: the part of it that it spends on the air",
           "[[events]]", 'name = "t_0"', 'kind = "time"', "time = 0.0",
           "[[events]]", 'name = "t_e"', 'kind = "end"', "[windows]", '"t_0-t_e" = ["t_0", "t_e"]']
    if signals is not None:
        cycle, green = signals
        out += ["", "[signals]", f"cycle = {float(cycle)!r}", "offset = 0.0"]
        windows: dict[tuple[float, float], list[str]] = {}
        for lane, ws in green.items():
            for w in ws:
                windows.setdefault(w, []).append(lane)
        for (g0, g1), group in sorted(windows.items()):
            out += ["[[signals.phases]]", f"lanes = {v(sorted(group))}", f"green = {v([g0, g1])}"]
    for ln in lanes.values():
        out += ["", "[[lanes]]", f"id = {v(ln.id)}", f"centerline = {v(np.round(ln.centerline, 4).tolist())}",
                f"width = {float(ln.width)!r}", f"stop_line = {v(ln.stop_line)}"]
    for vid, tr in tracks.items():
        route = routes[vid]
        width = lanes[route[0]].width
        out += ["", "[[vehicles]]", f"id = {v(vid)}", f"route = {v(route)}", f"depart = {float(tr.t[0])!r}",
                f"length = {opt.length!r}", f"l0 = {opt.l0!r}",
                f"stop_gap = {v({'mean': opt.stop_gap[0], 'sigma': opt.stop_gap[1]})}",
                f"lateral = {v({'mean': width / 2, 'sigma': opt.lateral_sigma})}"]
    return "\n".join(out) + "\n"



def import_tracks(tracks: dict[str, Track], lanes: dict[str, Lane], out: Path, opt: ImportOptions, name: str,
                  head: list[str], description: str, shift: bool = True,
                  signals: tuple[float, dict[str, list[tuple[float, float]]]] | None = None) -> tuple[Path, float]:
    """Write the scenario folder ``out`` (``scenario.toml`` and ``trajectories.csv``) for
    vehicles driving ``tracks`` on ``lanes``; returns the scenario file and the time [s]
    subtracted from the tracks (with ``shift``, the scenario starts at their first sample, on
    the 0.1 s grid). The routes come from the tracks' lanes, or, without them, from their
    positions on ``lanes``; ``opt.duration`` 0 means up to the last sample."""
    t0 = float(np.floor(min(tr.t[0] for tr in tracks.values()) * 10.0 + 1e-6) / 10.0) if shift else 0.0
    if min(tr.t[0] for tr in tracks.values()) < t0 - 1e-9:
        raise ValueError("a track starts before 0 s")
    tracks = {vid: replace(tr, t=tr.t - t0) for vid, tr in tracks.items()}
    routes = {}
    for vid, tr in tracks.items():
        routes[vid] = route_lanes(tr, lanes)
        if not routes[vid]:
            raise ValueError(f"vehicle {vid!r} never drives on a lane of the site (a wrong frame or offset?)")
    end = max(tr.t[-1] for tr in tracks.values())
    duration = opt.duration if opt.duration > 0 else float(np.ceil(end * 10.0 - 1e-6) / 10.0)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_csv_tracks(tracks, out / "trajectories.csv")
    path = out / "scenario.toml"
    path.write_text(trajectory_scenario_toml(head, name, description, lanes, tracks, replace(opt, duration=duration),
                                             routes, signals))
    load_scenario(path)  # what was written reads back
    return path, t0
