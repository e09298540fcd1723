"""Scenarios from SUMO: a network and its traffic (routes, or random trips), simulated by SUMO,
become a scenario folder (``scenario.toml`` and ``trajectories.csv``) that ``slcp run`` plays.

SUMO (the ``eclipse-sumo`` package, ``pip install 'slcp[sumo]'``) simulates the traffic at
0.1 s steps with no teleports; each vehicle's floating-car data (front position, heading, speed,
lane and lane position) become its trajectory, the network's lanes and the signalised junction's
stop lines the site (:mod:`hw_emulation.sumo_network`), and the traffic light's plan the
scenario's signals. The drivers' stance comes from SUMO's models, set per vehicle: each gets a
vehicle type of its own (SUMO's Krauss driver, deterministic, :data:`DRIVER`) whose stop-line
gap (``jmStoplineGap``, front to stop line at a red light) is drawn from the scenario's stop-gap
distribution, which is then the agents' prior; SUMO drives on the lane centre, where the
lateral prior is centred (its σ is the real drivers').
"""

from __future__ import annotations

import logging
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .external import Track, read_sumo_fcd
from .scenario_writer import ImportOptions, import_tracks, route_lanes
from .sumo_network import SumoNetworkError, sumo_site

log = logging.getLogger(__name__)

#: SUMO's step [s]: the scenario's traffic grid, so that every sample is a truth knot
SUMO_STEP = 0.1


@dataclass(frozen=True)
class SumoOptions(ImportOptions):
    """How ``from-sumo`` builds a scenario: the import's settings, and for random trips one
    departure every ``period`` [s] until ``duration - min_time``; a vehicle on the air for less
    than ``min_time`` [s] is left out (its agent would learn nothing)."""

    period: float = 2.5
    min_time: float = 20.0


class SumoError(OSError):
    """SUMO is missing, or one of its tools failed (the message says which and where its log is)."""


def sumo_home() -> Path:
    """Where SUMO's binaries and tools are: the ``eclipse-sumo`` package's, else ``$SUMO_HOME``."""
    try:
        import sumo  # the eclipse-sumo wheel

        return Path(sumo.SUMO_HOME)
    except ImportError:
        pass
    import os

    home = os.environ.get("SUMO_HOME")
    if home and (Path(home) / "bin").is_dir():
        return Path(home)
    raise SumoError("SUMO is not installed: pip install 'slcp[sumo]' (or set SUMO_HOME)")


def _run(cmd: list[str], log_path: Path, what: str) -> None:
    with open(log_path, "w") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, timeout=600, check=False)
    if proc.returncode != 0:
        tail = log_path.read_text().strip().splitlines()[-3:]
        raise SumoError(f"{what} failed (exit {proc.returncode}): {' / '.join(tail)}; log: {log_path}")


def netgenerate(out: Path, arm_length: float = 200.0, lanes: int = 2) -> Path:
    """A four-way signalised junction (``netgenerate --grid``, one node with four arms), a green
    phase for each approach in turn (no left turn waits inside the junction for oncoming traffic)."""
    net = Path(out)
    _run([str(sumo_home() / "bin" / "netgenerate"), "--grid", "--grid.number=1",
          f"--grid.attach-length={arm_length}", "--tls.guess=true", "--tls.layout=incoming",
          f"--default.lanenumber={lanes}", "--no-turnarounds=true", "-o", str(net)], net.with_suffix(".log"),
         "netgenerate")
    return net


def random_trips(net: Path, folder: Path, opt: SumoOptions) -> Path:
    """Routes of random trips from fringe to fringe (SUMO's ``randomTrips.py``)."""
    routes = folder / "routes.rou.xml"
    end = opt.duration - opt.min_time
    if end <= 0:
        raise SumoError(f"duration {opt.duration:g} s leaves no time for departures (min_time {opt.min_time:g} s)")
    _run([sys.executable, str(sumo_home() / "tools" / "randomTrips.py"), "-n", str(net),
          "-o", str(folder / "trips.xml"), "-r", str(routes), "--seed", str(opt.seed), "-b", "0", "-e", f"{end:g}",
          "-p", f"{opt.period:g}", "--fringe-factor", "max", "--validate"], folder / "randomTrips.log", "randomTrips")
    return routes


#: SUMO's Krauss model, deterministic (σ 0): it brakes to a clean stop at a red light. (SUMO's
#: IDM creeps its last centimetres at speeds alternating between 0 and 0.15 m/s for seconds,
#: which no car does and a stationarity detector rightly calls moving.)
DRIVER = {"carFollowModel": "Krauss", "sigma": "0", "accel": "1.5", "decel": "3", "tau": "1", "minGap": "2"}


def typed_routes(routes: Path, out: Path, opt: SumoOptions) -> dict[str, float]:
    """``routes`` with a vehicle type of its own per vehicle (:data:`DRIVER`, the drawn stop-line
    gap), written to ``out``; returns the gaps drawn by SUMO vehicle id."""
    try:
        tree = ET.parse(routes)
    except (ET.ParseError, OSError) as exc:
        raise SumoError(f"{routes}: not a SUMO routes file ({exc})") from exc
    root = tree.getroot()
    rng = np.random.default_rng([opt.seed, 7])
    gaps: dict[str, float] = {}
    for i, veh in enumerate([v for v in root if v.tag in ("vehicle", "trip", "flow")]):
        if veh.tag == "flow":
            raise SumoError(f"{routes}: flows are not supported (one <vehicle> or <trip> per vehicle)")
        gap = float(max(rng.normal(*opt.stop_gap), 0.2))
        vid = veh.get("id")
        gaps[vid] = gap
        vt = ET.Element("vType", {"id": f"slcp_{vid}", "length": f"{opt.length:g}", "speedDev": "0",
                                  "jmStoplineGap": f"{gap:.4f}", **DRIVER})
        root.insert(i + len(gaps) - 1, vt)
        veh.set("type", vt.get("id"))
    tree.write(out)
    return gaps


def simulate(net: Path, routes: Path, folder: Path, opt: SumoOptions) -> Path:
    """SUMO's floating-car data of the run (``fcd.xml``)."""
    fcd = folder / "fcd.xml"
    _run([str(sumo_home() / "bin" / "sumo"), "-n", str(net), "-r", str(routes), "--step-length", f"{SUMO_STEP:g}",
          "--begin", "0", "--end", f"{opt.duration:g}", "--precision", "4", "--fcd-output", str(fcd),
          "--seed", str(opt.seed), "--time-to-teleport", "-1", "--no-step-log", "true",
          # a lane change takes its time (SUMO's default moves a vehicle across in one step)
          "--lanechange.duration", "3"],
         folder / "sumo.log", "sumo")
    return fcd


def _slcp_id(sumo_id: str) -> str:
    return f"V{sumo_id}" if re.fullmatch(r"\d+", sumo_id) else re.sub(r"[^A-Za-z0-9_-]", "_", sumo_id)


def check_no_jumps(tracks: dict[str, Track], source: Path) -> None:
    """SUMO ran without teleports: no vehicle moves further in a step than its speeds allow."""
    for vid, tr in tracks.items():
        step = np.linalg.norm(np.diff(tr.ne, axis=0), axis=1)
        allowed = 0.5 * (tr.speed[1:] + tr.speed[:-1]) * np.diff(tr.t) + 0.5
        if np.any(step > allowed):
            k = int(np.argmax(step - allowed))
            raise SumoError(f"{source}: vehicle {vid!r} jumps {step[k]:.1f} m at t={tr.t[k + 1]:.1f} s (a teleport?)")


def build_sumo_scenario(net: Path, out: Path, opt: SumoOptions, routes: Path | None = None,
                        name: str | None = None) -> Path:
    """Simulate ``net`` with ``routes`` (else random trips) and write the scenario folder ``out``;
    returns its ``scenario.toml``. SUMO's own files stay in ``out/sumo``."""
    out = Path(out)
    work = out / "sumo"
    work.mkdir(parents=True, exist_ok=True)
    net = Path(net)
    try:
        site = sumo_site(net)
    except SumoNetworkError as exc:
        raise SumoError(str(exc)) from exc
    if net.resolve() != (work / "net.net.xml").resolve():
        shutil.copy(net, work / "net.net.xml")
    raw = Path(routes) if routes is not None else random_trips(net, work, opt)
    typed_routes(raw, work / "typed.rou.xml", opt)
    fcd = simulate(net, work / "typed.rou.xml", work, opt)
    tracks = {_slcp_id(k): tr for k, tr in read_sumo_fcd(fcd, offset=site.centre).items()
              if tr.t[-1] - tr.t[0] >= opt.min_time - 1e-6 and route_lanes(tr, site.lanes)}
    if not tracks:
        raise SumoError(f"{fcd}: no vehicle stays {opt.min_time:g} s on the network")
    check_no_jumps(tracks, fcd)
    source = f"{net.name}" + (f" and {Path(routes).name}" if routes else " with random trips")
    head = [f"# Built by `slcp scenario from-sumo` from {source} (seed {opt.seed}); the vehicles drive SUMO's",
            "# trajectories (trajectories.csv, positions of the front), the site is the network's; the frame's",
            f"# origin is the network's point x = {site.centre[0]:g}, y = {site.centre[1]:g} (junction {site.tls})."]
    path, _ = import_tracks(tracks, site.lanes, out, opt, name or out.name, head,
                            f"SUMO junction {site.tls}: {len(tracks)} vehicles over {opt.duration:g} s", shift=False,
                            signals=(site.cycle, site.green))
    log.info("SUMO scenario %s: %d vehicles, %d stop lanes, %.0f s", path, len(tracks),
             sum(ln.stop_line for ln in site.lanes.values()), opt.duration)
    return path
