"""``slcp replay``: a recorded drive through the SP filter, offline or to a live agent."""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import logging
import math
from pathlib import Path

from .. import cli_types as T


def add_replay(sub) -> None:
    """The ``replay`` command's parser."""
    rp = sub.add_parser("replay", help="replay a recorded drive through the SP (GNSS/INS) filter")
    from ..datasets.formats import FORMATS

    rp.add_argument("format", choices=list(FORMATS),
                    help="recording format: " + "; ".join(f"{k}: {v[1]}" for k, v in FORMATS.items()))
    rp.add_argument("path", type=Path, help="the recording (docs/recording-formats.md)")
    rp.add_argument("--vehicle", default=None, metavar="PROFILE",
                    help="the recording vehicle's profile: a TOML file (IMU mount and noise, antenna, heights, time "
                         "offset; docs/vehicle-profiles.md) or a shipped profile's name; default: a generic vehicle")
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
    rp.add_argument("--imu-time-offset", type=T.finite_float, default=None,
                    help="prior of the IMU time offset [s] (default: the profile's)")
    rp.add_argument("--compare", type=Path, default=None, metavar="TOML",
                    help="another filter's outage figures on the same recording and protocol, reported beside "
                         "ours in report.md (a TOML file: docs/recording-formats.md#figures-to-compare-with)")
    rp.add_argument("--out", type=Path, default=Path("runs/replay"), help="output directory")
    rp.add_argument("--json", action="store_true", help="print one JSON object with the metrics")
    pg = rp.add_argument_group("publishing onto the sensor topics (a live agent runs on the drive)")
    pg.add_argument("--publish", action="store_true",
                    help="publish the drive's IMU and GNSS (outages withheld) on VEHICLE's sensor topics over Zenoh, "
                         "score the estimates the agent publishes back")
    pg.add_argument("--vehicle-id", default="V0", help="vehicle id of the topics (default V0)")
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


def _outage_arg(text: str) -> tuple[float, float]:
    try:
        length, gap = (float(x) for x in text.split(":"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected LENGTH:GNSS_ON seconds, e.g. 15:30, got {text!r}") from exc
    if length <= 0 or gap <= 0:
        raise argparse.ArgumentTypeError("outage length and GNSS-on time must be positive")
    return length, gap


#: the options of the publishing group and their defaults: given without --publish, refused
_PUBLISH_ONLY = {"vehicle_id": "V0", "speed": 1.0, "start": 0.0, "duration": None, "connect": [], "listen": [],
                 "wait_agent": 30.0}


def _check_options(args: argparse.Namespace) -> None:
    """What the command line asks that this replay would not do, refused before any work."""
    if not args.publish:
        given = [k for k, default in _PUBLISH_ONLY.items() if getattr(args, k) != default]
        if given:
            names = ", ".join("--" + k.replace("_", "-") for k in given)
            raise ValueError(f"{names}: only with --publish (the offline replay does not publish)")
        out: Path = args.out
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {out}: a file, not a folder")
        if out.is_dir() and any(out.iterdir()) and not (out / "metrics.json").is_file():
            raise ValueError(f"--out {out}: holds other files (not an earlier replay's output); choose another folder")


def json_finite(obj):
    """``obj`` with every non-finite float as None (JSON's null): strict JSON has no NaN or
    Infinity, and a metric that was not measured (no outage fits the recording) is null."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_finite(v) for v in obj]
    return obj


def _profile(args: argparse.Namespace):
    """The vehicle profile of ``--vehicle`` (or a generic one) with the command line's switches."""
    from slcp.vehicles.profile import VehicleProfile

    from ..vehicle_files import load_vehicle

    if args.vehicle is None:
        logging.getLogger(__name__).warning(
            "no --vehicle profile: a generic vehicle (IMU axes on the body's, no time offset, ellipsoidal "
            "heights, antenna at the IMU); give the recording vehicle's profile for its figures")
        prof = VehicleProfile()
    else:
        prof = load_vehicle(args.vehicle)
    c = dataclasses.replace(prof.constraints, nhc=prof.constraints.nhc and not args.no_nhc,
                            zupt=prof.constraints.zupt and not args.no_zupt)
    t = dataclasses.replace(prof.time, estimate=prof.time.estimate and not args.no_time_offset_estimation)
    if args.imu_time_offset is not None:
        t = dataclasses.replace(t, imu_offset_s=args.imu_time_offset)
    return dataclasses.replace(prof, constraints=c, time=t)


def _cmd_replay(args: argparse.Namespace) -> int:
    from ..datasets.formats import load_recording
    from ..replay import (
        REFERENCE_SHARE,
        TRAJECTORY_COLUMNS,
        OutageProtocol,
        ReplayConfig,
        phase_protocols,
        pooled_metrics,
        reference_share,
        run_replay,
    )

    _check_options(args)
    length, gap = (0.0, 1.0) if args.no_outage else args.outage
    cfg = ReplayConfig(
        profile=_profile(args),
        outage=OutageProtocol(first=args.first_outage, period=length + gap, length=length,
                              end_margin=args.end_margin),
    )
    from ..replay_report import load_comparison, replay_command, replay_report

    if args.compare is not None and args.publish:
        raise ValueError("--compare reports beside the offline replay's figures (not --publish, which scores the "
                         "live agent's)")
    other = load_comparison(args.compare) if args.compare is not None else None
    drive = load_recording(args.format, args.path)
    if args.phases > 1 and (args.no_outage or args.publish):
        raise ValueError("--phases needs outages and the offline replay (not --no-outage or --publish)")
    if args.publish:
        return _replay_publish(args, drive, cfg)
    res = run_replay(drive, cfg)
    if not args.no_outage and not res.outages:
        logging.getLogger(__name__).warning(
            "no outage fits the recording (%.1f s of GNSS; the first would start %.1f s after its first fix, and "
            "none starts later than %.1f s before its last): no outage figures; shorten --first-outage or "
            "--end-margin", float(drive.gnss.t[-1] - drive.gnss.t[0]), args.first_outage, args.end_margin)
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
    share = reference_share(drive.gnss)
    metrics.update(reference=share >= REFERENCE_SHARE, reference_share=share)
    if pooled is not None:
        metrics["phases_pooled"] = pooled
    metrics["config"] = json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
    (out / "metrics.json").write_text(json.dumps(json_finite(metrics), indent=2, allow_nan=False))
    if not metrics["reference"]:
        return _no_reference(args, metrics, out)
    try:
        from ..plots import plot_replay_error

        plot_replay_error(res, out / "error.png")
    except ImportError:  # matplotlib is a dependency; this only guards stripped installs
        logging.getLogger(__name__).warning("matplotlib not available: no error.png")
    report = replay_report(replay_command(args), metrics, other, title=f"SP replay of {args.path.name}")
    (out / "report.md").write_text(report)
    if args.json:
        print(json.dumps(json_finite({**res.metrics, **({"phases_pooled": pooled} if pooled is not None else {})}),
                         allow_nan=False))
    else:
        _print_summary(args, cfg, res.metrics, pooled, out)
    return 0


def _print_summary(args: argparse.Namespace, cfg, m: dict, pooled: dict | None, out: Path) -> None:
    """The replay's figures as text (the default output)."""
    print(f"SP replay of {args.path} ({args.format}, vehicle {cfg.profile.name}; {m['imu_span_s']:.1f} s of IMU, "
          f"{m['n_outages']} outages, {m['n_withheld_fixes']} withheld fixes)")
    if m["n_outages"]:
        print(f"  outage horizontal RMS      {m['outage_h_rms_m']:.2f} m")
        print(f"  end-of-outage mean / max   {m['outage_h_end_mean_m']:.2f} / {m['outage_h_end_max_m']:.2f} m")
        print(f"  outage max                 {m['outage_h_max_m']:.2f} m")
    print(f"  GNSS-on RMS                {m['gnss_on_h_rms_m']:.2f} m")
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
    print(f"  wrote {out}/trajectory.csv, metrics.json, report.md, error.png (the first phase)")


def _no_reference(args: argparse.Namespace, metrics: dict, out: Path) -> int:
    """A recording whose fixes are no reference: its trajectory, and no accuracy figures."""
    share = metrics["reference_share"]
    keep = ("reference", "reference_share", "imu_span_s", "wall_s", "realtime_factor", "imu_time_offset_s")
    if args.json:
        print(json.dumps(json_finite({k: metrics[k] for k in keep}), allow_nan=False))
        return 0
    print(f"SP replay of {args.path} ({args.format}): no reference, only {100 * share:.0f} % of the fixes are "
          "RTK-fixed, so outage figures would measure the receiver's own error")
    print(f"  wrote {out}/trajectory.csv and metrics.json (no figures)")
    return 0


def _replay_publish(args: argparse.Namespace, drive, cfg) -> int:
    import asyncio

    from slcp.transport.zenoh_bus import ZenohConfig

    from ..replay_publish import plan_drive, replay_publish_main

    if not args.speed > 0:
        raise ValueError(f"--speed must be > 0, got {args.speed}")
    plan = plan_drive(drive, args.vehicle_id, cfg, args.start, args.duration)
    z = ZenohConfig(connect=tuple(args.connect), listen=tuple(args.listen))
    res = asyncio.run(replay_publish_main(plan, z, args.speed, args.wait_agent,
                                          lever_arm=cfg.profile.gnss.lever_arm_m))
    if args.json:
        print(json.dumps(json_finite(res), allow_nan=False))
        return 0
    print(
        f"published {res['published']} messages ({res['imu_batches']} IMU batches of {res['imu_samples']} samples, "
        f"{res['gnss_fixes']} fixes, {res['gnss_withheld']} withheld) on {args.vehicle_id}'s topics: "
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
            f"(end mean {fmt(r['outage_h_end_mean_m'])} m, max {fmt(r['outage_h_max_m'])} m)"
        )
    return 0


HANDLERS = {"replay": _cmd_replay}
