"""``slcp`` command line: the thin shell over the packages (the only place that prints)."""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import faulthandler
import json
import logging
import signal
import sys
from pathlib import Path

from agent.methods import DEFAULT_FUSION, FUSION_RULES

from . import cli_types as T
from .datasets import DatasetError
from .run_dirs import folder_stem, next_free, prepare_out


def _outage_arg(text: str) -> tuple[float, float]:
    try:
        length, gap = (float(x) for x in text.split(":"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected LENGTH:GNSS_ON seconds, e.g. 15:30, got {text!r}") from exc
    if length <= 0 or gap <= 0:
        raise argparse.ArgumentTypeError("outage length and GNSS-on time must be positive")
    return length, gap


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("slcp")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slcp", description="Stop-line-aided cooperative positioning")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}",
                   help="print the installed version and exit")
    sub = p.add_subparsers(dest="command", required=True)

    rp = sub.add_parser("replay", help="replay a recorded drive through the SP (GNSS/INS) filter")
    rp.add_argument("format", choices=["rtklib"], help="dataset format")
    rp.add_argument("path", type=Path, help="dataset folder (imu_*.csv + .tag, *.pos)")
    g = rp.add_mutually_exclusive_group()
    g.add_argument("--outage", type=_outage_arg, default=(15.0, 30.0), metavar="LEN:ON",
                   help="outage length and GNSS-on time between outages [s] (default 15:30)")
    g.add_argument("--no-outage", action="store_true", help="keep every GNSS fix")
    rp.add_argument("--first-outage", type=T.nonnegative_float, default=40.0, help="first outage start after t0 [s]")
    rp.add_argument(
        "--end-margin", type=T.nonnegative_float, default=30.0, help="no outage starts later than tN minus this [s]"
    )
    rp.add_argument("--phases", type=T.positive_int, default=1, metavar="N",
                    help="also run the protocol at N phases evenly spread over its period (first outage at "
                         "FIRST + k (LEN + ON) / N) and report each and all pooled (default 1: the protocol only)")
    rp.add_argument("--no-nhc", action="store_true", help="disable the non-holonomic constraint")
    rp.add_argument("--no-zupt", action="store_true", help="disable zero-velocity/zero-rate updates")
    rp.add_argument("--no-time-offset-estimation", action="store_true",
                    help="keep the IMU time offset fixed at --imu-time-offset")
    rp.add_argument("--imu-time-offset", type=T.finite_float, default=-0.125, help="initial IMU time offset [s]")
    rp.add_argument("--out", type=Path, default=Path("runs/replay"), help="output directory")
    rp.add_argument("--json", action="store_true", help="print one JSON object with the metrics")
    pg = rp.add_argument_group("publishing onto the sensor topics (a live agent runs on the drive)")
    pg.add_argument("--publish", action="store_true",
                    help="publish the drive's IMU and GNSS (outages withheld) on VEHICLE's sensor topics over Zenoh, "
                         "score the estimates the agent publishes back")
    pg.add_argument("--vehicle", default="V0", help="vehicle id of the topics (default V0)")
    pg.add_argument(
        "--speed", type=T.positive_float, default=1.0, help="real-time factor of the publication (default 1)"
    )
    pg.add_argument(
        "--start", type=T.nonnegative_float, default=0.0, help="start this long after the first GNSS epoch [s]"
    )
    pg.add_argument(
        "--duration", type=T.positive_float, default=None, help="publish this long [s] (default: to the end)"
    )
    pg.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    pg.add_argument("--listen", action="append", type=T.listen_endpoint, default=[], help="Zenoh endpoint to listen on")
    pg.add_argument("--wait-agent", type=T.nonnegative_float, default=30.0,
                    help="wait this long for the vehicle's agent (liveliness) before publishing [s] (default 30; "
                         "0: do not wait)")

    ag = sub.add_parser("agent", help="run one vehicle agent (Zenoh)")
    ag.add_argument("--vehicle", help="vehicle id (overrides the config file)")
    ag.add_argument("--config", type=Path, required=True, help="agent TOML (docs/cli.md, agent configuration)")
    ag.add_argument("--nice", type=int, choices=range(0, 20), default=0, metavar="0-19",
                    help="lower this process's scheduling priority by N (default 0)")
    em = sub.add_parser("emulate", help="run the emulator service (sensors, UWB, V2V radio) over Zenoh")
    em.add_argument("scenario", help="shipped scenario name or .toml")
    em.add_argument("--seed", type=T.seed, default=0, help="run seed: sensor noise and where drivers stop (default 0)")
    em.add_argument(
        "--speed", type=T.positive_float, default=None, help="real-time factor (default: as fast as agents keep up)"
    )
    em.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    em.add_argument("--listen", action="append", type=T.listen_endpoint, default=[], help="Zenoh endpoint to listen on")
    em.add_argument("--mode", choices=("peer", "client"), default="peer",
                    help="Zenoh mode (default peer; client: through the router given by --connect only)")
    em.add_argument("--faults", type=Path, default=None, help="fault schedule (TOML, docs/security.md)")
    em.add_argument(
        "--wait-agents",
        type=T.nonnegative_float,
        default=20.0,
        help="wait up to this long for every vehicle's agent before starting [s] (default 20; 0: start at once)",
    )
    em.add_argument("--start-at", type=T.nonnegative_float, default=None, metavar="T",
                    help="resume the scenario at sensor time T [s] (a restarted emulator)")
    em.add_argument("--fleet", type=Path, default=None,
                    help="fleet directory: connect with mutual TLS as identity 'emulator' (tls/ endpoints)")
    ro = sub.add_parser("router", help="run the infrastructure Zenoh router (TLS + ACL with --fleet)")
    ro.add_argument("--listen", action="append", type=T.listen_endpoint, default=[],
                    help="endpoint (repeatable; default tls/127.0.0.1:7447 with --fleet, else tcp/127.0.0.1:7447)")
    ro.add_argument(
        "--fleet",
        type=Path,
        default=None,
        help="fleet directory (slcp keys create): mutual TLS and an ACL in which a vehicle publishes only "
        "under its own keys",
    )
    ro.add_argument(
        "--print-config", action="store_true", help="print the router's Zenoh configuration (JSON5) and exit"
    )
    se = sub.add_parser(
        "sensors", help="publish a vehicle's real GNSS (NMEA/UBX) and IMU from serial ports or log files"
    )
    se.add_argument("--vehicle", required=True, help="vehicle id of the sensor topics")
    se.add_argument("--gnss", default=None, metavar="nmea|ubx:PATH[@BAUD]",
                    help="GNSS receiver: a serial device (e.g. nmea:/dev/ttyACM0@115200) or a log file")
    se.add_argument(
        "--imu", default=None, metavar="csv:PATH[@BAUD]", help="IMU text lines: a serial device or a log file"
    )
    se.add_argument("--imu-units", default="m/s2,rad/s", metavar="ACCEL,GYRO",
                    help="units of the IMU lines: m/s2|g|mg and rad/s|deg/s|mrad/s (default m/s2,rad/s)")
    se.add_argument("--imu-mount", default="0,0,0", metavar="ROLL,PITCH,YAW",
                    help="sensor-to-body rotation [deg] (default 0,0,0: the IMU axes are forward, right, down)")
    se.add_argument("--imu-time-offset", type=T.finite_float, default=0.0, help="added to the IMU time stamps [s]")
    se.add_argument(
        "--uere", type=T.positive_float, default=2.5, help="NMEA without GST: horizontal sigma = HDOP x UERE [m]"
    )
    se.add_argument(
        "--speed", type=T.positive_float, default=1.0, help="pacing of log files (real-time factor, default 1)"
    )
    se.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    se.add_argument("--listen", action="append", type=T.listen_endpoint, default=[], help="Zenoh endpoint to listen on")
    se.add_argument("--fleet", type=Path, default=None,
                    help="fleet directory: mutual TLS to the router as the vehicle (its .key/.crt)")
    rc = sub.add_parser("record", help="record every estimate and diagnostics message (JSON lines, appending)")
    rc.add_argument("--out", type=Path, required=True, help="recording file (appended to; a restart continues it)")
    rc.add_argument("--connect", action="append", type=T.endpoint, default=[], help="Zenoh endpoint to connect to")
    rc.add_argument("--fleet", type=Path, default=None, help="fleet directory: mutual TLS as identity 'recorder'")
    rn = sub.add_parser("run", help="run a fleet on this machine over Zenoh and evaluate it")
    rn.add_argument("scenario", nargs="?", default="paper-1", help="scenario (default paper-1)")
    rn.add_argument("--methods", nargs="+", default=None, help="methods (default: SP SL-SP CP SL-CP)")
    rn.add_argument(
        "--speed", type=T.positive_float, default=None, help="real-time factor (default: as fast as agents keep up)"
    )
    rn.add_argument("--seed", type=T.seed, default=0,
                    help="run seed: sensor noise and where drivers stop (default 0; with --seeds, the first)")
    rn.add_argument("--out", type=Path, default=None,
                    help="run directory (default runs/<scenario>-seed<S>, or runs/<scenario>-<N>seeds; "
                         "-2, -3, ... appended when that exists)")
    rn.add_argument(
        "--force",
        action="store_true",
        help="with --out: replace the previous run in that folder (default: refuse a folder that is not empty)",
    )
    rn.add_argument("--fusion", choices=FUSION_RULES, default=DEFAULT_FUSION,
                    help=f"how CP methods fuse ranges with beacons (default {DEFAULT_FUSION})")
    rn.add_argument("--seeds", type=T.positive_int, default=None, metavar="N",
                    help="N seeded runs (seeds S..S+N-1) spread over the cores, with mean ± sd")
    rn.add_argument("--jobs", type=T.positive_int, default=None, help="parallel runs for --seeds (default: cores)")
    rn.add_argument("--strict", action="store_true",
                    help="with --seeds: exit 1 if a seed fails twice (default: report the others and exit 0)")
    rn.add_argument("--faults", type=Path, default=None,
                    help="fault schedule (TOML): link, sensor and process faults, shown on the report")
    rn.add_argument("--agent-nice", type=int, choices=range(0, 20), default=5, metavar="0-19",
                    help="run the agents this many steps below normal priority, so that the emulated "
                         "sensors and radio and the Zenoh router are served first (default 5; 0: equal)")
    rn.add_argument("--zenoh-mode", choices=("client", "peer"), default="client",
                    help="how the agents and the emulator join the launcher's Zenoh router: client (default; "
                         "every message through the router) or peer (they also dial each other, a full mesh)")
    rn.add_argument(
        "--no-lane-constraint",
        action="store_true",
        help="SL methods use the stop line only, as the paper's (default: they also keep to the map's lanes)",
    )
    rn.add_argument("--no-sign", action="store_true",
                    help="neither sign nor verify beacons (default: a fleet CA and keys per run, every beacon signed)")
    ae = sub.add_parser(
        "attack-eval", help="misbehaviour detection against the VeReMi attacks, and false alarms on clean runs"
    )
    ae.add_argument("scenario", nargs="?", default="paper-1")
    ae.add_argument("--seeds", type=T.positive_int, default=5, help="attack runs per kind (default 5)")
    ae.add_argument("--kinds", nargs="+", default=None, help="attack kinds (default: all)")
    ae.add_argument("--clean", nargs="*", default=None, metavar="SCENARIO",
                    help="also count false alarms on whole clean runs of these scenarios (seed 0)")
    ae.add_argument("--json", action="store_true", help="print one JSON object")
    ky = sub.add_parser("keys", help="create or list a fleet's CA, vehicle keys and certificates")
    ksub = ky.add_subparsers(dest="keys_command", required=True)
    kc = ksub.add_parser(
        "create", help="create a fleet CA (if absent) and a key + certificate per vehicle and the router"
    )
    kc.add_argument("dir", type=Path, help="fleet directory (ca.crt, <vehicle>.crt/.key, router.crt/.key)")
    kc.add_argument("vehicles", nargs="+", help="vehicle ids")
    kc.add_argument("--router-host", action="append", default=None,
                    help="host name or address in the router certificate (repeatable; default 127.0.0.1, localhost)")
    kc.add_argument("--days", type=T.positive_int, default=365, help="certificate validity [days] (default 365)")
    kc.add_argument("--force", action="store_true", help="replace existing CA, keys and certificates")
    kc.add_argument("--infra", action="append", default=None,
                    help="infrastructure identity (repeatable; default: emulator, recorder)")
    kl = ksub.add_parser("list", help="check a fleet directory and list its certificates and key ids")
    kl.add_argument("dir", type=Path)
    bd = sub.add_parser("bound", help="posterior Cramér-Rao bound per vehicle and method on a scenario's truth")
    bd.add_argument("scenario", help="shipped scenario name or .toml")
    bd.add_argument("--json", action="store_true", help="print one JSON object")
    bd.add_argument("--plot", type=Path, metavar="FILE.png", help="plot the bound over time")
    bd.add_argument("--csv", type=Path, metavar="FILE.csv", help="write the bound over time")
    bd.add_argument("--no-lane-constraint", action="store_true",
                    help="SL bounds without the lane-keeping information (as for slcp run --no-lane-constraint)")
    bd.add_argument("--lane-offset", choices=("vehicle", "lane"), default="vehicle",
                    help="the driver's offset in a lane: one constant per vehicle, as the emulated drivers "
                         "keep it (the bound proper), or redrawn in each lane, as the filters model it")
    bd.add_argument("--vehicles", metavar="ID,ID,...",
                    help="a sub-fleet: the cooperative bounds process only these vehicles' information "
                         "(how much of a bound comes from which neighbours; default: all)")
    bd.add_argument("--seed", type=T.seed, default=None,
                    help="the drivers' stop draws of this run seed, as slcp run --seed draws them "
                         "(default: the scenario's draw)")
    bn = sub.add_parser("bench", help="per-step costs of an agent and the replay real-time factor")
    bn.add_argument("--drive", type=Path, default=Path("../shared/data/rtklibexplorer_drive_0708"),
                    help="rtklibexplorer drive for the replay factor (skipped if absent)")
    bn.add_argument("--quick", action="store_true", help="fewer repetitions")
    bn.add_argument("--json", action="store_true", help="print one JSON object")
    bn.add_argument("--fleet", default=None, metavar="N,N,...",
                    help="also run the fleet scaling benchmark with these agent counts (e.g. 10,25,50,75)")
    bn.add_argument(
        "--fleet-duration",
        type=T.positive_float,
        default=40.0,
        help="scenario length of each fleet point [s] (default 40)",
    )
    bn.add_argument("--fleet-method", default="SL-CP", help="the one method each agent runs (default SL-CP)")
    bn.add_argument("--fleet-fusion", choices=FUSION_RULES, default=DEFAULT_FUSION,
                    help=f"how the fleet's CP methods fuse ranges (as slcp run --fusion; default {DEFAULT_FUSION})")
    bn.add_argument("--fleet-zenoh-mode", choices=("client", "peer"), default="client",
                    help="how the fleet's processes join the router (as slcp run --zenoh-mode; default client)")
    bn.add_argument("--fleet-imu-batch", type=int, choices=range(1, 101), default=20, metavar="1-100",
                    help="IMU samples per message in the fleet's grid (default 20: 5 messages a second at 100 Hz)")
    rp2 = sub.add_parser("report", help="rebuild the report of a run (from its recording) or a study (from its seeds)")
    rp2.add_argument("run_dir", type=Path)

    sp = sub.add_parser("scenario", help="list or show emulation scenarios")
    ssub = sp.add_subparsers(dest="scenario_command", required=True)
    ssub.add_parser("list", help="list the shipped scenarios")
    ex = ssub.add_parser("export", help="write a shipped scenario's TOML, to start a scenario of your own from it")
    ex.add_argument("name", help="shipped scenario name")
    ex.add_argument("--out", type=Path, default=None, metavar="FILE.toml",
                    help="write here (default: print to the terminal); an existing file is kept unless --force")
    ex.add_argument("--force", action="store_true", help="replace an existing --out file")
    show = ssub.add_parser("show", help="summarise a scenario (name or TOML file)")
    show.add_argument("name", help="shipped scenario name or path to a .toml file")
    show.add_argument("--plot", type=Path, metavar="FILE.png", help="write a map with trajectories")
    chk = ssub.add_parser("sp-check", help="SP RMSE on emulated sensors beside the paper's SP row")
    chk.add_argument("name", help="shipped scenario name or path to a .toml file")
    chk.add_argument("--seeds", type=T.positive_int, default=20, help="sensor seeds to average (default 20)")
    chk.add_argument("--json", action="store_true", help="print one JSON object")
    gt = ssub.add_parser("gates", help="range-gate outcomes over many seeds (in process, spread over the cores)")
    gt.add_argument("name", help="shipped scenario name or path to a .toml file")
    gt.add_argument("--seeds", type=T.positive_int, default=25, help="seeds 0..N-1 (default 25)")
    gt.add_argument("--json", action="store_true", help="print one JSON object")
    ev = ssub.add_parser("evaluate", help="run all vehicles and the four methods in one process (no bus)")
    ev.add_argument("name", help="shipped scenario name or path to a .toml file")
    ev.add_argument("--seed", type=T.seed, default=0, help="sensor seed (default 0)")
    ev.add_argument("--json", action="store_true", help="print one JSON object")
    return p


def _cmd_scenario(args: argparse.Namespace) -> int:
    from hw_emulation.scenario import load_scenario, shipped_scenarios

    if args.scenario_command == "list":
        for name in shipped_scenarios():
            scn = load_scenario(name)
            print(f"{name:12s} {len(scn.vehicles):3d} vehicles {scn.duration:6.0f} s  {scn.description}")
        return 0
    if args.scenario_command == "export":
        from hw_emulation.scenario import shipped_scenario_text

        text = shipped_scenario_text(args.name)
        if args.out is None:
            print(text, end="")
            return 0
        if args.out.exists() and not args.force:
            raise FileExistsError(f"{args.out}: exists (use --force to replace it)")
        args.out.write_text(text)
        print(f"wrote {args.out} (scenario {args.name}; run it with: slcp run {args.out})")
        return 0
    from hw_emulation.events import event_times, window_bounds
    from hw_emulation.truth import build_truth

    scn = load_scenario(args.name)
    if args.scenario_command == "gates":
        return _gates(args, scn)
    # evaluate: a run's seed also redraws where the drivers stop, as in `slcp run --seed`
    truth = build_truth(scn, stop_seed=args.seed if args.scenario_command == "evaluate" else None)
    if args.scenario_command == "sp-check":
        return _sp_check(args, scn, truth)
    if args.scenario_command == "evaluate":
        return _evaluate(args, scn, truth)
    ev = event_times(truth)
    print(f"{scn.name}: {scn.description}")
    print(f"  {len(scn.lanes)} lanes, {len(scn.vehicles)} vehicles, {scn.duration:.0f} s, seed {scn.seed}")
    for vid, vt in truth.vehicles.items():
        first = vt.truth.t[vt.first_stopped]
        stopped = vt.truth.t[vt.stopped]
        print(f"  {vid:6s} route {' -> '.join(dict.fromkeys(vt.segment))}; stopped {len(stopped) / scn.imu_rate:5.1f} s"
              + (f", first stopped from {first[0]:.1f} s" if first.size else ""))
    print("  events: " + ", ".join(f"{k} = {v:.1f} s" for k, v in ev.items()))
    for w, (a, b) in window_bounds(truth, ev).items():
        print(f"  window {w}: {a:.1f} - {b:.1f} s")
    if args.plot:
        from .plots import plot_scenario

        plot_scenario(truth, args.plot, ev)
        print(f"  wrote {args.plot}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from .datasets.rtklib import load_drive
    from .replay import TRAJECTORY_COLUMNS, OutageProtocol, ReplayConfig, phase_protocols, pooled_metrics, run_replay

    drive = load_drive(args.path)
    length, gap = (0.0, 1.0) if args.no_outage else args.outage
    cfg = ReplayConfig(
        outage=OutageProtocol(first=args.first_outage, period=length + gap, length=length,
                              end_margin=args.end_margin),
        nhc=not args.no_nhc, zupt=not args.no_zupt,
        imu_time_offset=args.imu_time_offset,
        estimate_time_offset=not args.no_time_offset_estimation,
    )
    if args.phases > 1 and (args.no_outage or args.publish):
        raise ValueError("--phases needs outages and the offline replay (not --no-outage or --publish)")
    if args.publish:
        return _replay_publish(args, drive, cfg)
    res = run_replay(drive, cfg)
    pooled = None
    if args.phases > 1:  # phase 0 is the run above
        others = [run_replay(drive, dataclasses.replace(cfg, outage=p))
                  for p in phase_protocols(cfg.outage, args.phases)[1:]]
        pooled = pooled_metrics([res, *others])
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "trajectory.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRAJECTORY_COLUMNS)
        for row in res.trajectory:
            w.writerow([f"{row[0]:.3f}", f"{row[1]:.9f}", f"{row[2]:.9f}"] + [f"{x:.4f}" for x in row[3:]])
    metrics = dict(res.metrics)
    if pooled is not None:
        metrics["phases_pooled"] = pooled
    metrics["config"] = json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    try:
        from .plots import plot_replay_error

        plot_replay_error(res, out / "error.png")
    except ImportError:  # matplotlib is a dependency; this only guards stripped installs
        logging.getLogger(__name__).warning("matplotlib not available: no error.png")
    m = res.metrics
    if args.json:
        print(json.dumps({**m, **({"phases_pooled": pooled} if pooled is not None else {})}))
    else:
        print(f"SP replay of {args.path} ({m['imu_span_s']:.1f} s of IMU, {m['n_outages']} outages, "
              f"{m['n_withheld_fixes']} withheld fixes)")
        print(f"  outage horizontal RMS      {m['outage_h_rms_m']:.2f} m")
        print(f"  end-of-outage mean / max   {m['outage_h_end_mean_m']:.2f} / {m['outage_h_end_max_m']:.2f} m")
        print(f"  outage max                 {m['outage_h_max_m']:.2f} m")
        print(f"  GNSS-on prior RMS          {m['gnss_on_h_rms_m']:.2f} m")
        print(f"  estimated IMU time offset  {m['imu_time_offset_s']:+.3f} s")
        print(f"  wall {m['wall_s']:.2f} s, real-time factor {m['realtime_factor']:.0f}x")
        if pooled is not None:
            print("  outage phases (first outage after t0 [s]: outages, RMS, end mean / max, max [m])")
            for ph in pooled["phases"]:
                first = "-" if ph["first_outage_s"] is None else f"{ph['first_outage_s']:.1f}"
                print(f"    {first:>7}: {ph['n_outages']:3d}  {ph['outage_h_rms_m']:.2f}  "
                      f"{ph['outage_h_end_mean_m']:.2f} / {ph['outage_h_end_max_m']:.2f}  {ph['outage_h_max_m']:.2f}")
            print(
                f"    pooled : {pooled['n_outages']:3d}  {pooled['outage_h_rms_m']:.2f}  "
                f"{pooled['outage_h_end_mean_m']:.2f} / {pooled['outage_h_end_max_m']:.2f}  "
                f"{pooled['outage_h_max_m']:.2f}"
            )
        print(f"  wrote {out}/trajectory.csv, metrics.json, error.png (the first phase)")
    return 0


def _replay_publish(args: argparse.Namespace, drive, cfg) -> int:
    import asyncio

    from transport.zenoh_bus import ZenohConfig

    from .replay_publish import plan_drive, replay_publish_main

    if not args.speed > 0:
        raise ValueError(f"--speed must be > 0, got {args.speed}")
    plan = plan_drive(drive, args.vehicle, cfg, args.start, args.duration)
    z = ZenohConfig(connect=tuple(args.connect), listen=tuple(args.listen))
    res = asyncio.run(replay_publish_main(plan, z, args.speed, args.wait_agent))
    if args.json:
        print(json.dumps(res))
        return 0
    print(
        f"published {res['published']} messages ({res['imu_batches']} IMU batches of {res['imu_samples']} samples, "
        f"{res['gnss_fixes']} fixes, {res['gnss_withheld']} withheld) on {args.vehicle}'s topics: "
        f"{res['sensor_s']:.1f} s of sensor time in {res['wall_s']:.1f} s wall, "
        f"at most {res['max_late_s'] * 1e3:.0f} ms late"
    )
    if not res["methods"]:
        print("no estimate of the agent received (is `slcp agent` running for this vehicle?)")
    fmt = lambda x: "   -  " if x is None else f"{x:6.2f}"  # noqa: E731
    for m, r in res["methods"].items():
        print(
            f"  {m:6s} {r['n_estimates']:6d} estimates, {r['epochs']:5d} epochs: horizontal RMS {fmt(r['h_rms_m'])} m, "
            f"GNSS on {fmt(r['gnss_on_h_rms_m'])} m, outages {fmt(r['outage_h_rms_m'])} m "
            f"(max {fmt(r['outage_h_max_m'])} m)"
        )
    return 0


def _cmd_sensors(args: argparse.Namespace) -> int:
    import asyncio
    import math

    from transport.zenoh_bus import ZenohConfig

    from .sensors.driver import SourceSpec, sensors_main
    from .sensors.imu import ImuAdapter, parse_units

    try:
        mount = tuple(math.radians(float(x)) for x in args.imu_mount.split(","))
    except ValueError:
        mount = ()
    if len(mount) != 3 or not all(math.isfinite(x) for x in mount):
        raise ValueError(f"--imu-mount {args.imu_mount!r}: expected ROLL,PITCH,YAW in degrees")
    units = parse_units(args.imu_units)
    if not (args.speed > 0 and args.uere > 0):
        raise ValueError("--speed and --uere must be > 0")
    gnss = SourceSpec.parse("gnss", args.gnss) if args.gnss else None
    imu = SourceSpec.parse("imu", args.imu) if args.imu else None
    if gnss is None and imu is None:
        raise ValueError("nothing to read: give --gnss and/or --imu")
    adapter = ImuAdapter(args.vehicle, mount, args.imu_time_offset)
    z = ZenohConfig(connect=tuple(args.connect), listen=tuple(args.listen))
    if args.fleet:
        from .zenoh_security import client_config

        z = client_config(args.fleet, args.vehicle, tuple(args.connect))
    counters = asyncio.run(sensors_main(z, args.vehicle, gnss, imu, adapter, units, args.uere, args.speed))
    print(json.dumps(counters))
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from agent.methods import METHODS, MethodSpec
    from hw_emulation.scenario import load_scenario

    from .launcher import run_fleet
    from .supervisor import interrupt_on_termination

    interrupt_on_termination()
    methods = tuple(args.methods) if args.methods else METHODS
    for m in methods:
        MethodSpec.of(m)  # ValueError -> clear CLI error
    scn = load_scenario(args.scenario)
    if args.faults is not None:  # read before --force removes anything
        from hw_emulation.faults import load_faults

        load_faults(args.faults, {v.id for v in scn.vehicles})
    if args.out is not None:
        prepare_out(args.out, args.force)
    stem = folder_stem(scn.name)
    if args.seeds:
        from .study import StudyError, run_study, study_markdown

        out = args.out or next_free(Path("runs"), f"{stem}-{args.seeds}seeds")
        seeds = list(range(args.seed, args.seed + args.seeds))
        print(
            f"slcp run {args.scenario}: {args.seeds} seeds, {', '.join(methods)}, fusion {args.fusion}; writing {out}"
        )

        def bar(done: int, total: int, seed: int) -> None:
            k = int(30 * done / total)
            print(f"  [{'#' * k}{'.' * (30 - k)}] {done}/{total} (seed {seed} done)", flush=True)

        try:
            study = run_study(args.scenario, seeds, methods, out, args.fusion, args.jobs, bar, sign=not args.no_sign,
                              agent_nice=args.agent_nice, lane_constraint=not args.no_lane_constraint,
                              zenoh_mode=args.zenoh_mode)
        except StudyError as exc:
            print(f"slcp run: {exc}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            done = sorted(p.name for p in out.glob("seed-*") if (p / "metrics.json").is_file())
            print(f"\nslcp run: interrupted; the study's processes are stopped. {len(done)} of {args.seeds} seeds "
                  f"finished in {out}" + (f" ({', '.join(done)})" if done else ""), file=sys.stderr)
            return 130
        text = study_markdown(scn, study)
        (out / "report.md").write_text(text)
        print(text)
        if study["failed_seeds"]:
            print(f"slcp run: {len(study['failed_seeds'])} of {args.seeds} seeds failed and are left out "
                  f"(seeds {', '.join(study['failed_seeds'])}; see {out}/failed-seed-*/logs)", file=sys.stderr)
            return 1 if args.strict else 0
        return 0
    out = args.out or next_free(Path("runs"), f"{stem}-seed{args.seed}")
    print(f"slcp run {args.scenario}: {', '.join(methods)}, fusion {args.fusion}; writing {out}")
    from .progress import ProgressView

    try:
        with ProgressView() as view:
            m = run_fleet(args.scenario, methods, args.speed, args.seed, out, progress=view, fusion=args.fusion,
                          sign=not args.no_sign, faults=args.faults, agent_nice=args.agent_nice,
                          lane_constraint=not args.no_lane_constraint, zenoh_mode=args.zenoh_mode)
    except KeyboardInterrupt:
        print("\nslcp run: interrupted; the fleet's processes are stopped", file=sys.stderr)
        _report_partial_run(out)
        return 130
    from .summary import terminal_summary

    print(f"done in {m['wall_s']:.1f} s; processes exited {m['processes']['exit_codes']}\n")
    print(terminal_summary(scn, m, out / "report.md"))
    return 0


def _report_partial_run(out: Path) -> None:
    """The report of what an interrupted run recorded, or one line on why there is none."""
    from .run_report import rebuild_report

    rec = out / "recorded" / "messages.jsonl"
    last = None
    with contextlib.suppress(OSError), rec.open() as fh:
        for line in fh:
            try:
                t = float(json.loads(line)["t"])
            except (ValueError, KeyError, TypeError):  # a line cut by the interruption
                continue
            last = t if last is None else max(last, t)
    if last is None:
        print(f"slcp run: nothing was recorded, so no report ({out})", file=sys.stderr)
        return
    try:
        rebuild_report(out)
    except Exception as exc:  # a recording cut anywhere: one line, never a traceback after Ctrl-C
        print(f"slcp run: recorded to t={last:.1f} s, but no report of it ({type(exc).__name__}: {exc})",
              file=sys.stderr)
        return
    print(f"slcp run: recorded to t={last:.1f} s of sensor time; its report: {out / 'report.md'}", file=sys.stderr)


def _cmd_infrastructure(args: argparse.Namespace) -> int:
    import asyncio

    from transport.zenoh_bus import ZenohConfig

    from .processes import recorder_main, router_main

    if args.command == "record":
        z = ZenohConfig(mode="client" if args.fleet else "peer", connect=tuple(args.connect))
        if args.fleet:
            from .zenoh_security import client_config

            z = client_config(args.fleet, "recorder", tuple(args.connect))
        return asyncio.run(recorder_main(z, args.out))
    if args.fleet:
        from .zenoh_security import as_json5, router_config

        z = router_config(args.fleet, tuple(args.listen) or ("tls/127.0.0.1:7447",))
        if args.print_config:
            print(as_json5(z), end="")
            return 0
    else:
        z = ZenohConfig(mode="router", listen=tuple(args.listen) or ("tcp/127.0.0.1:7447",))
        if args.print_config:
            from .zenoh_security import as_json5

            print(as_json5(z), end="")
            return 0
    return asyncio.run(router_main(z))


def _cmd_attack_eval(args: argparse.Namespace) -> int:
    from hw_emulation.attacks import ATTACKS

    from .attack_eval import attack_study, evaluate_clean

    kinds = tuple(args.kinds) if args.kinds else ATTACKS
    for k in kinds:
        if k not in ATTACKS:
            raise ValueError(f"unknown attack kind {k!r}; known: {', '.join(ATTACKS)}")

    def progress(kind, seed, run):
        if not args.json:
            lat = {
                v: ("-" if r["latency_s"] is None else f"{r['latency_s']:.2f} s") for v, r in run["receivers"].items()
            }
            print(
                f"  {kind:18s} seed {seed}: {run['attacker']} from {run['start_s']:.1f} s; first flag by {lat}",
                flush=True,
            )

    study = attack_study(args.scenario, list(range(args.seeds)), kinds, progress=progress)
    study["clean"] = [evaluate_clean(s, 0) for s in (args.clean or [])]
    if args.json:
        print(json.dumps(study))
        return 0
    print(f"\nattack-eval {args.scenario}, {args.seeds} seeds per kind, detection deadline {study['deadline_s']} s")
    print(f"  {'kind':18s} {'detected':>10s} {'rate':>6s} {'median':>8s} {'max':>7s} {'honest excl.':>12s}")
    for k, d in study["kinds"].items():
        f = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
        print(
            f"  {k:18s} {d['detected']:4d}/{d['cases']:<5d} {f(d['detection_rate']):>6s} "
            f"{f(d['latency_median_s']):>8s} "
            f"{f(d['latency_max_s']):>7s} {100 * d['honest_excluded_share']:11.2f}%"
        )
    for c in study["clean"]:
        print(f"  clean {c['scenario']}: {c['excluded']} of {c['beacons']} beacons excluded "
              f"({100 * c['false_alarm_rate']:.2f} %), {c['flags']} flags")
    return 0


def _cmd_keys(args: argparse.Namespace) -> int:
    from transport.security import TrustStore, create_fleet

    if args.keys_command == "create":
        hosts = tuple(args.router_host) if args.router_host else ("127.0.0.1", "localhost")
        infra = tuple(args.infra) if args.infra else ("emulator", "recorder")
        written = create_fleet(args.dir, args.vehicles, hosts, args.days, overwrite=args.force, infrastructure=infra)
        for p in written:
            print(f"wrote {p}")
        if not written:
            print(f"{args.dir}: every certificate exists already (use --force to replace)")
    store = TrustStore.from_dir(args.dir)
    print(f"{args.dir}: fleet CA {store.ca.subject.rfc4514_string()}, valid to {store.ca.not_valid_after_utc:%Y-%m-%d}")
    kids = store.key_ids()
    for name, role in sorted(store.roles.items(), key=lambda kv: (kv[1] != "vehicle", kv[0])):
        print(f"  {name:16s} {role:15s}" + (f" beacon key id {kids[name].hex()}" if name in kids else ""))
    return 0


def _cmd_bound(args: argparse.Namespace) -> int:
    import numpy as np

    from agent.methods import METHODS
    from hw_emulation.events import window_bounds
    from hw_emulation.scenario import STANDING_WINDOW, load_scenario
    from hw_emulation.truth import build_truth

    from .bound import posterior_crlb

    scn = load_scenario(args.scenario)
    truth = build_truth(scn, stop_seed=args.seed)
    vehicles = None if args.vehicles is None else tuple(v.strip() for v in args.vehicles.split(",") if v.strip())
    b = posterior_crlb(truth, lane_constraint=not args.no_lane_constraint, lane_offset=args.lane_offset,
                       vehicles=vehicles)
    ids = sorted({vid for _, vid in b.cov})
    rows = []
    windows = {w: (lambda vid, a=a, c=c: (b.t >= a) & (b.t <= c)) for w, (a, c) in window_bounds(truth).items()}
    windows[STANDING_WINDOW] = lambda vid: truth.vehicles[vid].stopped_at(b.t)  # each vehicle's own steps
    for w, select in windows.items():
        for vid in ids:
            sel = select(vid)
            if sel.any():
                rows.append({"window": w, "vehicle": vid,
                             **{m: float(np.sqrt(np.mean(b.sigma_h(m, vid)[sel] ** 2))) for m in METHODS}})
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            wr = csv.writer(fh)
            wr.writerow(["time_s", "vehicle", *(f"{m}_sigma_h_m" for m in METHODS)])
            for vid in ids:
                cols = [b.sigma_h(m, vid) for m in METHODS]
                for k, t in enumerate(b.t):
                    wr.writerow([f"{t:.2f}", vid, *(f"{c[k]:.4f}" for c in cols)])
    if args.plot:
        from .plots import plot_bound

        plot_bound(b, ids, METHODS, args.plot, f"{scn.name}: posterior CRLB, horizontal")
    if args.json:
        print(json.dumps({"scenario": scn.name, "lane_offset": args.lane_offset, "seed": args.seed,
                          "vehicles": ids, "rows": rows}))
        return 0
    print(f"{scn.name}: posterior CRLB on horizontal position [m], RMS over each window")
    print(f"{'window':12s} {'vehicle':8s} " + " ".join(f"{m:>7s}" for m in METHODS))
    for r in rows:
        print(f"{r['window']:12s} {r['vehicle']:8s} " + " ".join(f"{r[m]:7.3f}" for m in METHODS))
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    import os
    import platform

    from agent.methods import MethodSpec

    from .bench import micro_benchmarks, replay_factor

    counts: list[int] = []
    if args.fleet:
        try:
            counts = [int(x) for x in args.fleet.split(",")]
        except ValueError:
            counts = [0]
        if not counts or min(counts) < 1:
            raise ValueError(f"--fleet {args.fleet!r}: expected positive agent counts, e.g. 10,25,50,75")
        if not args.fleet_duration > 5:
            raise ValueError("--fleet-duration must be > 5 s")
        MethodSpec.of(args.fleet_method)
    out = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
           "steps": micro_benchmarks(args.quick), "replay": replay_factor(args.drive, 1 if args.quick else 3)}
    if counts:
        from .fleet_bench import run_fleet_point

        out["fleet"] = []
        for n in counts:
            if not args.json:
                print(f"fleet benchmark: {n} agents for {args.fleet_duration:g} s at 1x ...", file=sys.stderr)
            out["fleet"].append(run_fleet_point(n, args.fleet_duration, args.fleet_method,
                                                    zenoh_mode=args.fleet_zenoh_mode,
                                                    imu_batch=args.fleet_imu_batch, fusion=args.fleet_fusion))
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"slcp bench on {out['machine']['cpus']} CPUs, Python {out['machine']['python']}")
    for k, v in out["steps"].items():
        unit = " µs" if k.endswith("_us") else ""
        print(f"  {k:28s} {v:10.2f}{unit}")
    r = out["replay"]
    if r is None:
        print(f"  replay: {args.drive} not found")
    else:
        print(f"  replay real-time factor     {r['realtime_factor']:10.1f}x  ({r['imu_span_s']:.1f} s of data in "
              f"{r['wall_s']:.2f} s, median of runs at {', '.join(f'{x:g}' for x in r['realtime_factor_runs'])}x; "
              f"outage RMS {r['outage_h_rms_m']:.2f} m)")
    for f in out.get("fleet", []):
        if "error" in f:
            print(f"  fleet {f['agents']:3d} agents: {f['error']}")
            continue
        lat = f["beacon_latency_ms"] or {"p50": float("nan"), "p99": float("nan")}
        print(
            f"  fleet {f['agents']:3d} agents ({f['method']}, {f['fusion']}, Zenoh {f['zenoh_mode']}, "
            f"IMU batch {f['imu_batch']}): "
            f"real-time factor {f['realtime_factor']:.2f}, lag p99 {f['lag_p99_s']:.2f} s, "
            f"CPU/agent {f['cpu_pct_per_agent']['mean']:.1f} % "
            f"(max {f['cpu_pct_per_agent']['max']:.1f}, {f['threads_per_agent']} threads), emulator "
            f"{f['emulator_cpu_pct']:.0f} %, launcher {f['launcher_cpu_pct']:.0f} %, "
            f"machine {f['machine_cpu_pct']:.0f} %, "
            f"RSS/agent {f['rss_mb_per_agent']['mean']:.0f} MB (max {f['rss_mb_per_agent']['max']:.0f}), "
            f"beacon latency p50 {lat['p50']:.1f} ms p99 {lat['p99']:.1f} ms, sensor drops {f['sensor_dropped']}"
        )
        if f.get("windows"):
            worst = f["beacon_p99_ms_worst_window"]
            print(
                f"    by {f['windows'][0]['wall_s']:.0f} s window: "
                f"machine CPU {f['machine_cpu_pct_peak']:.0f} % at the "
                f"busiest, beacon p99 {'–' if worst is None else f'{worst:.1f} ms'} in the worst; "
                + ", ".join(
                    f"{w['machine_cpu_pct']:.0f} %/"
                    + ("–" if w["beacon_p99_ms"] is None else f"{w['beacon_p99_ms']:.0f} ms")
                    for w in f["windows"]
                )
            )
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from .run_report import rebuild_report

    if any(args.run_dir.glob("seed-*")):  # a study: re-aggregate its seeds
        from hw_emulation.scenario import load_scenario

        from .study import rebuild_study, study_markdown

        study = rebuild_study(args.run_dir)
        (args.run_dir / "report.md").write_text(study_markdown(load_scenario(study["scenario"]), study))
    else:
        from hw_emulation.scenario import load_scenario

        from .summary import terminal_summary

        m = rebuild_report(args.run_dir)
        print(terminal_summary(load_scenario(m["scenario_source"]), m, args.run_dir / "report.md"))
        return 0
    print((args.run_dir / "report.md").read_text())
    return 0


def _evaluate(args: argparse.Namespace, scn, truth) -> int:
    import numpy as np

    from agent.methods import METHODS
    from hw_emulation.events import window_bounds

    from .gates_study import summarise
    from .inprocess import run_inprocess

    r = run_inprocess(truth, args.seed)
    rows = []
    for w, (a, b) in window_bounds(truth).items():
        m = (r.t >= a) & (r.t <= b)
        for vid in sorted(truth.vehicles):
            row = {"window": w, "vehicle": vid}
            for meth in METHODS:
                row[meth] = float(np.sqrt(np.mean(r.err[(vid, meth)][m] ** 2))) if m.any() else None
            row["paper"] = scn.paper_table.get(w, {}).get(vid, {})
            rows.append(row)
    detect = {}
    for vid, vt in truth.vehicles.items():
        true_first = vt.first_stopped[9::10][: len(r.t)]
        claims = r.first[(vid, "SL-SP")]
        detect[vid] = {"true_first_s": float(true_first.sum() / 10), "claimed_s": float(claims.sum() / 10),
                       "claimed_while_not_first_s": float((claims & ~true_first).sum() / 10)}
    ranges = summarise(r.range_outcomes)
    if args.json:
        print(json.dumps({"scenario": scn.name, "seed": args.seed, "rows": rows, "first_stopped": detect,
                          "ranges": ranges}))
        return 0
    print(f"{scn.name}, sensor seed {args.seed}: horizontal RMSE [m] (paper in brackets)")
    print(f"{'window':12s} {'vehicle':8s} " + " ".join(f"{m:>14s}" for m in METHODS))
    for row in rows:
        cells = []
        for meth in METHODS:
            p = row["paper"].get(meth)
            v = row[meth]
            cells.append(f"{v:6.2f}" + (f" [{p:5.2f}]" if p is not None else "        ") if v is not None else "     -")
        print(f"{row['window']:12s} {row['vehicle']:8s} " + " ".join(f"{c:>14s}" for c in cells))
    for m, kinds in ranges.items():
        print(
            f"{m} ranges rejected by the gates, per injected error: "
            + "; ".join(
                f"{kind} {d['rejected']}/{d['n']} ({100 * d['rejected_share']:.1f} %)"
                for kind, d in sorted(kinds.items())
                if d["n"]
            )
        )
    print(
        "first-stopped detection (SL-SP filter, seconds): "
        + "; ".join(
            f"{v}: truth {d['true_first_s']:.1f}, claimed {d['claimed_s']:.1f}, "
            f"wrongly {d['claimed_while_not_first_s']:.1f}"
            for v, d in detect.items()
        )
    )
    return 0


def _gates(args: argparse.Namespace, scn) -> int:
    from .gates_study import range_outcomes, summarise

    seeds = list(range(args.seeds))
    summary = summarise(range_outcomes(args.name, seeds))
    if args.json:
        print(json.dumps({"scenario": scn.name, "seeds": seeds, "ranges": summary}))
        return 0
    print(f"{scn.name}, seeds 0-{seeds[-1]}: ranges rejected by the gates / fused, per injected error")
    for m, kinds in summary.items():
        cells = [f"{kind} {d['rejected']}/{d['n']} ({100 * d['rejected_share']:.2f} %), fused {d['fused']}"
                 for kind, d in kinds.items() if d["n"]]
        print(f"  {m:6s} " + "; ".join(cells))
    return 0


def _sp_check(args: argparse.Namespace, scn, truth) -> int:
    import numpy as np

    from .sp_check import sp_table

    if args.seeds < 1:
        raise ValueError("--seeds must be at least 1")
    table = sp_table(truth, list(range(args.seeds)))
    rows = []
    for w, cells in table.items():
        for vid, vals in cells.items():
            paper = scn.paper_table.get(w, {}).get(vid, {}).get("SP")
            rows.append({"window": w, "vehicle": vid, "mean_rmse_m": float(np.mean(vals)),
                         "sd_rmse_m": float(np.std(vals)), "seed0_rmse_m": float(vals[0]),
                         "paper_sp_m": paper, "ratio": float(np.mean(vals)) / paper if paper else None})
    if args.json:
        print(json.dumps({"scenario": scn.name, "seeds": args.seeds, "rows": rows}))
        return 0
    print(f"SP horizontal RMSE on {scn.name}, mean over {args.seeds} sensor seeds (truth seed {scn.seed})")
    print(f"{'window':12s} {'vehicle':8s} {'mean':>6s} {'sd':>6s} {'seed 0':>7s} {'paper':>6s} {'ratio':>6s}")
    for r in rows:
        paper = f"{r['paper_sp_m']:6.2f}" if r["paper_sp_m"] else "     -"
        ratio = f"{r['ratio']:6.2f}" if r["ratio"] else "     -"
        print(f"{r['window']:12s} {r['vehicle']:8s} {r['mean_rmse_m']:6.2f} {r['sd_rmse_m']:6.2f} "
              f"{r['seed0_rmse_m']:7.2f} {paper} {ratio}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if hasattr(signal, "SIGUSR1"):  # `kill -USR1 PID`: every thread's Python stack to stderr (a hung process)
        with contextlib.suppress(OSError, ValueError):  # a stderr without a file descriptor (captured)
            faulthandler.register(signal.SIGUSR1, all_threads=True, chain=False)
    logging.basicConfig(level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "replay":
            return _cmd_replay(args)
        if args.command == "scenario":
            return _cmd_scenario(args)
        if args.command == "agent":
            import asyncio

            from .processes import agent_main

            return asyncio.run(agent_main(args.config, args.vehicle, args.nice))
        if args.command == "emulate":
            import asyncio

            from transport.zenoh_bus import ZenohConfig

            from .processes import emulator_main

            z = ZenohConfig(mode=args.mode, connect=tuple(args.connect), listen=tuple(args.listen))
            if args.fleet:
                from .zenoh_security import client_config

                z = client_config(args.fleet, "emulator", tuple(args.connect))
            return asyncio.run(emulator_main(args.scenario, args.seed, args.speed, z, faults_path=args.faults,
                                             start_at=args.start_at, wait_for_agents=args.wait_agents))
        if args.command == "sensors":
            return _cmd_sensors(args)
        if args.command in ("router", "record"):
            return _cmd_infrastructure(args)
        if args.command == "run":
            return _cmd_run(args)
        if args.command == "report":
            return _cmd_report(args)
        if args.command == "bound":
            return _cmd_bound(args)
        if args.command == "bench":
            return _cmd_bench(args)
        if args.command == "keys":
            return _cmd_keys(args)
        if args.command == "attack-eval":
            return _cmd_attack_eval(args)
    except (DatasetError, ValueError, OSError) as exc:
        print(f"slcp: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nslcp {args.command}: interrupted", file=sys.stderr)
        return 130
    return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
