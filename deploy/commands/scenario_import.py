"""``slcp scenario from-sumo`` and ``from-trajectories``: scenarios whose vehicles drive the
trajectories of a SUMO simulation, or of a CSV or SUMO FCD file, on a site of your choice."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from .. import cli_types as T

#: the frame's origin when nothing says where the site is (the paper's intersection, Beijing)
DEFAULT_ORIGIN = (39.9552, 116.3194, 50.0)


def _numbers(text: str, n: tuple[int, ...], what: str) -> tuple[float, ...]:
    parts = text.split(",")
    if len(parts) not in n:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return tuple(T.finite_float(x.strip()) for x in parts)


def origin(text: str) -> tuple[float, float, float]:
    """LAT,LON[,H] in degrees and metres."""
    v = _numbers(text, (2, 3), "LAT,LON[,H] (degrees, metres)")
    if not (-90 < v[0] < 90 and -180 <= v[1] <= 180):
        raise argparse.ArgumentTypeError(f"latitude/longitude out of range: {text!r}")
    return (v[0], v[1], v[2] if len(v) == 3 else 0.0)


def xy(text: str) -> tuple[float, float]:
    """X,Y in metres."""
    a, b = _numbers(text, (2,), "X,Y (metres)")
    return (a, b)


def mean_sigma(text: str) -> tuple[float, float]:
    """MEAN,SIGMA in metres (σ of 0 or more)."""
    m, s = _numbers(text, (2,), "MEAN,SIGMA (metres)")
    if s < 0:
        raise argparse.ArgumentTypeError(f"σ must be 0 or more, got {text!r}")
    return (m, s)


def _common(p) -> None:
    p.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="the scenario folder to write (scenario.toml, trajectories.csv); kept unless --force")
    p.add_argument("--force", action="store_true", help="replace an existing --out folder")
    p.add_argument("--name", default=None, help="the scenario's name (default: the folder's)")
    p.add_argument("--stop-gap", type=mean_sigma, default=(1.5, 0.2), metavar="MEAN,SIGMA",
                   help="the drivers' stop-line gap, front to line [m] (the agents' prior; default 1.5,0.2)")
    p.add_argument("--sensors-like", default="paper-1", metavar="SCENARIO",
                   help="take the sensor, UWB and radio models of this scenario (name or .toml; default paper-1, "
                        "the paper's GNSS environment); '' for the defaults (an urban canyon with NLOS episodes)")
    p.add_argument("--lateral-sigma", type=T.nonnegative_float, default=0.12, metavar="M",
                   help="σ of the drivers' lateral offset about the lane centre [m] (default 0.12)")


def add_import_commands(ssub) -> None:
    """The parsers of ``from-sumo`` and ``from-trajectories``."""
    fs = ssub.add_parser("from-sumo", help="a scenario from a SUMO network and its traffic (routes, or random trips), "
                                           "simulated by SUMO (pip install 'slcp[sumo]')")
    fs.add_argument("net", type=Path, metavar="NET.net.xml", help="the SUMO network (netgenerate, netconvert, ...)")
    fs.add_argument("--routes", type=Path, default=None, metavar="ROUTES.rou.xml",
                    help="the traffic (one <vehicle> or <trip> each); default: random trips fringe to fringe")
    fs.add_argument("--duration", type=T.positive_float, default=120.0, help="[s] of traffic (default 120)")
    fs.add_argument("--period", type=T.positive_float, default=2.5,
                    help="random trips: one departure every PERIOD seconds (default 2.5)")
    fs.add_argument("--min-time", type=T.nonnegative_float, default=20.0,
                    help="leave out vehicles on the network for less than this [s] (default 20)")
    fs.add_argument("--seed", type=T.seed, default=0, help="SUMO's and the stop gaps' seed (default 0)")
    fs.add_argument("--origin", type=origin, default=DEFAULT_ORIGIN, metavar="LAT,LON[,H]",
                    help="where the signalised junction is (degrees, metres; default the paper's intersection)")
    _common(fs)
    ft = ssub.add_parser("from-trajectories", help="a scenario whose vehicles drive the trajectories of a CSV or "
                                                   "SUMO FCD file on a site (a scenario's, a Lanelet2 map, a SUMO net)")
    ft.add_argument("file", type=Path, metavar="TRAJECTORIES", help="CSV (time_s,vehicle_id,north_m,east_m[,...]) "
                                                                    "or SUMO FCD XML (.xml)")
    site = ft.add_mutually_exclusive_group(required=True)
    site.add_argument("--site", metavar="SCENARIO", help="the lanes and origin of a scenario (name or .toml)")
    site.add_argument("--lanelet2", type=Path, metavar="MAP.osm", help="the lanes, stop lines and origin of a map")
    site.add_argument("--sumo-net", type=Path, metavar="NET.net.xml", help="the lanes and stop lines of a network")
    ft.add_argument("--point", choices=("front", "reference"), default=None,
                    help="what the positions are of (default: front for FCD, as SUMO reports; reference for CSV)")
    ft.add_argument("--offset", type=xy, default=None, metavar="X,Y",
                    help="FCD: the network point that is the frame's origin (default: --sumo-net's junction, else 0,0)")
    ft.add_argument("--origin", type=origin, default=None, metavar="LAT,LON[,H]",
                    help="where the frame's origin is (default: the site's; for --sumo-net the paper's intersection)")
    ft.add_argument("--duration", type=T.nonnegative_float, default=0.0,
                    help="[s] from the first sample (default: to the last)")
    _common(ft)


def _fresh(out: Path, force: bool) -> None:
    if out.exists():
        if not force:
            raise FileExistsError(f"{out}: exists (use --force to replace it)")
        shutil.rmtree(out) if out.is_dir() else out.unlink()


def cmd_from_sumo(args: argparse.Namespace) -> int:
    from slcp.hw_emulation.sumo_scenario import SumoOptions, build_sumo_scenario

    _fresh(args.out, args.force)
    opt = SumoOptions(duration=args.duration, seed=args.seed, origin=args.origin, stop_gap=args.stop_gap,
                      lateral_sigma=args.lateral_sigma, period=args.period, min_time=args.min_time,
                      sensors_like=args.sensors_like)
    path = build_sumo_scenario(args.net, args.out, opt, routes=args.routes, name=args.name)
    _summary(path)
    return 0


def cmd_from_trajectories(args: argparse.Namespace) -> int:
    import math

    from slcp.hw_emulation.external import read_csv_tracks, read_sumo_fcd
    from slcp.hw_emulation.scenario_writer import ImportOptions, import_tracks

    fcd = args.file.suffix.lower() == ".xml"
    if args.offset is not None and not fcd:
        raise ValueError("--offset is for SUMO FCD files (a CSV's positions are in the site's frame already)")
    origin_deg, centre = args.origin, (0.0, 0.0)
    if args.sumo_net is not None:
        from slcp.hw_emulation.sumo_network import sumo_site

        s = sumo_site(args.sumo_net)
        lanes, centre = s.lanes, s.centre
        origin_deg = origin_deg or DEFAULT_ORIGIN
    else:
        if args.lanelet2 is not None:
            from slcp.geo.lanelet2_site import read_lanelet2

            site = read_lanelet2(args.lanelet2)
        else:
            from slcp.hw_emulation.scenario import load_scenario

            site = load_scenario(args.site).site
        lanes = site.lanes
        lat, lon, h = site.origin_llh
        origin_deg = origin_deg or (math.degrees(lat), math.degrees(lon), h)
    tracks = read_sumo_fcd(args.file, args.offset or centre) if fcd else read_csv_tracks(args.file)
    point = args.point or ("front" if fcd else "reference")
    _fresh(args.out, args.force)
    opt = ImportOptions(duration=args.duration, origin=origin_deg, stop_gap=args.stop_gap,
                        lateral_sigma=args.lateral_sigma, point=point, sensors_like=args.sensors_like)
    head = [f"# Built by `slcp scenario from-trajectories` from {args.file.name} ({point} positions) on the site of "
            f"{args.site or (args.lanelet2 or args.sumo_net).name}."]
    path, shift = import_tracks(tracks, lanes, args.out, opt, args.name or args.out.name, head,
                                f"{len(tracks)} vehicles from {args.file.name}")
    if shift:
        print(f"the scenario starts at the first sample: {shift:g} s of the file is its 0 s")
    _summary(path)
    return 0


def _summary(path: Path) -> None:
    from slcp.hw_emulation.scenario import load_scenario

    scn = load_scenario(path)
    print(f"wrote {path}: {len(scn.vehicles)} vehicles, {sum(ln.stop_line for ln in scn.lanes.values())} stop lines, "
          f"{scn.duration:g} s; run it with: slcp run {path}")
