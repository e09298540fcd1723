"""``slcp run``: a fleet on one machine over Zenoh on loopback.

The launcher opens a Zenoh session in router mode on ``tls/127.0.0.1:<free port>`` and records
every estimate and diagnostics message (append-only JSON lines, flushed per batch). It starts the
emulator service and one agent process per vehicle (each a ``slcp`` subprocess in its own
session, logging to ``logs/``), waits for the emulator to finish, stops the agents with SIGTERM
(SIGKILL after a grace period), and never leaves a child behind (also on Ctrl-C). Then it
evaluates the recording against the truth and writes the run directory.

Run directory::

    config/agent-<vehicle>.toml      the agents' configurations
    keys/                            the run's fleet CA, keys and certificates (the router's mutual
                                     TLS and access control; beacon signing)
    logs/<process>.log               each process's log
    recorded/messages.jsonl          every recorded message, one JSON object per line
    recorded/bag/                    the same as a ROS 2 bag in MCAP storage (deploy.mcap_recording)
    estimates/<vehicle>.csv          time, method, lat, lon, h, velocity, attitude, sigma, errors
    metrics.json                     RMSE per window, vehicle and method; detection; counters
    report.md                        paper-style tables beside the paper's figures
    errors.png, map.png              error over time per vehicle and method; the map
"""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
import socket
import time
from pathlib import Path

from slcp.agent.methods import DEFAULT_FUSION, METHODS
from slcp.geo.lanelet2_site import write_lanelet2
from slcp.hw_emulation.faults import load_faults
from slcp.hw_emulation.scenario import Scenario, load_scenario
from slcp.hw_emulation.truth import build_truth
from slcp.transport.security import create_fleet

from .mcap_recording import McapSink
from .progress import FleetProgress
from .run_report import evaluate_recording, report_markdown
from .supervisor import supervise as _supervise
from .vehicle_agent_file import standalone_agent_toml
from .viewers import viewer_sinks

log = logging.getLogger(__name__)

#: How the agents and the emulator join the launcher's Zenoh router (see :func:`run_fleet`).
ZENOH_MODES = ("client", "peer")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _write_agent_configs(out: Path, vehicles: list[str], scenario: str, methods: tuple[str, ...], fusion: str,
                         lane_constraint: bool, endpoint: str, zenoh_mode: str, sign: bool,
                         secure: bool, standalone: Scenario | None = None) -> dict[str, Path]:
    """The agents' files under ``out/config`` (and, for ``sign`` or ``secure``, the run's keys).
    Given ``standalone`` (the scenario), they name no scenario, as a deployed vehicle's: the site
    is a Lanelet2 map of the scenario's (``config/site.osm``), the sensors' models are written
    out (:mod:`deploy.vehicle_agent_file`)."""
    security = ""
    if sign or secure:
        # a new CA for every run: the certificates of an earlier run in this directory, or of
        # another run on the host, must not admit anyone to this one
        create_fleet(out / "keys", vehicles, new_ca=True)
        security = '[security]\ntrust_dir = "../keys"\n' + ('' if sign else 'sign_beacons = false\n') + '\n'
    scn = standalone
    if scn is not None:
        write_lanelet2(scn.site, out / "config" / "site.osm")
    configs = {}
    for vid in vehicles:
        p = out / "config" / f"agent-{vid}.toml"
        agent = (standalone_agent_toml(scn, vid, "site.osm", methods, fusion, lane_constraint) if scn is not None else
                 f'[agent]\nvehicle = "{vid}"\nscenario = "{scenario}"\nmethods = {json.dumps(list(methods))}\n'
                 f'fusion = "{fusion}"\nlane_constraint = {str(lane_constraint).lower()}\n')
        p.write_text(f'{agent}\n{security}[zenoh]\nmode = "{zenoh_mode}"\nconnect = ["{endpoint}"]\n'
                     + ('tls = true\n' if secure else ''))
        configs[vid] = p
    return configs


def _prepare_run_dir(out: Path, scenario: str, faults: Path | None, started: dict) -> str:
    """The run directory's folders, its copy of the fault schedule, and ``config/run.json``: what
    ``slcp report`` needs to evaluate the recording of a run that never got to its evaluation.
    Returns the scenario's source (its file's absolute path, or the shipped name)."""
    for sub in ("config", "logs", "recorded", "estimates"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    if faults is not None:  # the run keeps its own copy of the schedule
        (out / "config" / "faults.toml").write_text(Path(faults).read_text())
    source = str(Path(scenario).resolve()) if Path(scenario).is_file() else str(scenario)
    (out / "config" / "run.json").write_text(json.dumps({"scenario": source, **started}, indent=2))
    return source


def _bag(out: Path, scn, truth, inputs: bool = False) -> McapSink:
    """The run's ROS 2 bag (``recorded/bag``), new, with the site and, given, the truth (and with
    ``inputs``, the vehicles' inputs)."""
    bag = out / "recorded" / "bag"
    shutil.rmtree(bag, ignore_errors=True)
    sink = McapSink(bag, scn.origin_llh, inputs=inputs)
    sink.write_site(list(scn.lanes.values()))
    for vid, vt in (truth.vehicles.items() if truth is not None else ()):
        tr = vt.truth
        sink.write_truth(vid, tr.t, tr.llh, tr.v_ned, tr.euler, vt.first_stopped)
    return sink


def run_fleet(scenario: str = "paper-1", methods: tuple[str, ...] = METHODS, speed: float | None = None,
              seed: int = 0, out: Path = Path("runs/fleet"), progress=None, fusion: str = DEFAULT_FUSION,
              sign: bool = True, faults: Path | None = None, monitor=None, evaluate: bool = True,
              wait_agents: float = 20.0, agent_nice: int = 5, agent_args: tuple[str, ...] = (),
              lane_constraint: bool = True, zenoh_mode: str = "client", secure: bool = True,
              view_port: int | None = None, foxglove_port: int | None = None, lanelet2: bool = False,
              bag_inputs: bool = False) -> dict:
    """Run the fleet and return the metrics (also written to ``out``).

    ``progress`` (optional) is called about twice a second with a
    :class:`deploy.progress.FleetProgress` (and once more before the evaluation). With ``sign``
    a fleet CA and per-vehicle keys are created in ``out/keys`` and every beacon is signed and
    verified. ``monitor`` (optional, see :class:`deploy.fleet_bench.FleetMonitor`) gets
    ``attach(bus, procs, endpoint)`` (the router's bus, the processes by name, the router's
    endpoint) once every process is started and ``sample(recorder)`` every 0.2 s.
    Without ``evaluate`` only the process statistics are returned (no truth, no metrics files).
    The emulator waits up to ``wait_agents`` s for every agent's liveliness. The agents (``slcp
    agent`` with ``agent_args``) run ``agent_nice`` steps below the normal priority (``nice``): on
    one machine the emulated sensors and radio, and the Zenoh router, stand for hardware that does
    not wait for the vehicles' computers, so they are served first when the CPUs are busy. Without
    ``lane_constraint`` the SL methods use the stop line only (the paper's), and so does the bound.

    ``zenoh_mode`` says how the agents and the emulator join the launcher's router: ``"client"``
    (default) sends every message through the router, one link per process; ``"peer"`` lets them
    dial each other as well (a full mesh of N²/2 links whose keep-alives alone cost a 50-agent
    fleet about a third of a core on one machine). Agents get Zenoh's light runtime
    (:data:`transport.zenoh_bus.LIGHT_CLIENT_RUNTIME`) unless ``ZENOH_RUNTIME`` is set.

    With ``secure`` (default) the run is locked down as a deployed fleet is
    (:mod:`deploy.zenoh_security`): the router listens on TLS only, admits only certificates of
    the run's own CA (``out/keys``, new for every run) and lets each process publish only under
    its own keys; the recorder then takes a message only on the key of the sender it names
    (:class:`deploy.recorder.Recorder`). Another user of the host can neither join nor forge the
    run's results. Without it the router is plain TCP on loopback, open to any local process;
    peer mode needs it off (peers link directly, past the router's access control).

    With ``view_port`` the launcher shows the run live on a map in the browser at
    ``http://127.0.0.1:<port>/`` (:mod:`deploy.live_map`), with ``foxglove_port`` it serves it to
    Foxglove on ``ws://127.0.0.1:<port>`` (:mod:`deploy.foxglove_view`); 0: any free port, logged.
    With ``lanelet2`` the agents are configured as deployed vehicles, without the scenario: their
    site is a Lanelet2 map of the scenario's, their sensor models written out in their files.
    With ``bag_inputs`` the run's bag also holds the vehicles' inputs (:mod:`deploy.mcap_inputs`)."""
    if zenoh_mode not in ZENOH_MODES:
        raise ValueError(f"zenoh_mode must be one of {', '.join(ZENOH_MODES)}, got {zenoh_mode!r}")
    if secure and zenoh_mode == "peer":
        raise ValueError("zenoh_mode 'peer' links the processes directly, past the router's access control: "
                         "it needs secure=False (slcp run --insecure)")
    scn = load_scenario(scenario)
    schedule = load_faults(faults, {v.id for v in scn.vehicles}) if faults is not None else []
    out = Path(out)
    source = _prepare_run_dir(out, scenario, faults, {"seed": seed, "methods": list(methods), "fusion": fusion,
                                                      "lane_constraint": lane_constraint, "lanelet2": lanelet2})
    endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{free_port()}"
    vehicles = [v.id for v in scn.vehicles]
    fleet_dir = out / "keys"
    configs = _write_agent_configs(out, vehicles, scenario, methods, fusion, lane_constraint, endpoint, zenoh_mode,
                                   sign, secure, scn if lanelet2 else None)
    # the truth first (the evaluation needs it anyway): the bag and the map show it beside the estimates
    truth = build_truth(scn, stop_seed=seed) if evaluate else None
    # then the viewers: a port that is taken stops the run before it starts
    sinks: list = [*viewer_sinks(view_port, foxglove_port, scn, truth), _bag(out, scn, truth, bag_inputs)]
    wall0 = time.monotonic()
    stats = asyncio.run(_supervise(scenario, vehicles, configs, endpoint, speed, seed, out, progress,
                                   faults=schedule, monitor=monitor, wait_agents=wait_agents,
                                   agent_nice=agent_nice, zenoh_mode=zenoh_mode, end_t=scn.duration,
                                   title=scn.name, fleet_dir=fleet_dir if secure else None,
                                   sinks=sinks, agent_args=agent_args))
    wall = time.monotonic() - wall0
    if not evaluate:
        return {"wall_s": wall, "processes": stats}
    if progress:
        progress(FleetProgress(scn.name, "evaluating", scn.duration, scn.duration, 0, len(vehicles),
                               stats["recorded"], wall))
    metrics = evaluate_recording(truth if truth is not None else build_truth(scn, stop_seed=seed),
                                 out / "recorded" / "messages.jsonl", out, methods, schedule, lane_constraint)
    metrics.update({"wall_s": wall, "seed": seed, "scenario_source": source, "fusion": fusion,
                    "lane_constraint": lane_constraint, "processes": stats})
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "report.md").write_text(report_markdown(scn, metrics))
    return metrics
