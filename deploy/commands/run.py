"""``slcp run`` (a fleet on this machine, or a study of seeds) and ``slcp report``."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

from slcp.agent.methods import DEFAULT_FUSION, FUSION_RULES

from .. import cli_types as T
from ..run_dirs import folder_stem, next_free, prepare_out


def add_run(sub) -> None:
    """The ``run`` command's parser."""
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
    rn.add_argument("--agent-nice", type=T.int_range(0, 19), default=5, metavar="0-19",
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
    rn.add_argument("--view", nargs="?", type=T.port, const=8780, default=None, metavar="PORT",
                    help="show the run live on a map in the browser at http://127.0.0.1:PORT/ (default 8780; "
                         "0: any free port)")
    rn.add_argument("--foxglove", nargs="?", type=T.port, const=8765, default=None, metavar="PORT",
                    help="serve the run live to Foxglove on ws://127.0.0.1:PORT (default 8765; 0: any free port)")
    rn.add_argument("--bag-inputs", action="store_true",
                    help="the run's ROS 2 bag also holds the vehicles' inputs: IMU samples, GNSS fixes, UWB rounds and "
                         "beacons (several times the size)")
    rn.add_argument("--lanelet2", action="store_true",
                    help="configure the agents as deployed vehicles, without the scenario: their site from a Lanelet2 "
                         "map of the scenario's (config/site.osm), their sensor models written out in their files")
    rn.add_argument("--insecure", action="store_true",
                    help="a plain TCP router open to every process of the host (default: mutual TLS with the run's "
                         "own keys, and each process may publish only under its own keys); --zenoh-mode peer needs it")


def add_report(sub) -> None:
    """The ``report`` command's parser."""
    rp2 = sub.add_parser("report", help="rebuild the report of a run (from its recording) or a study (from its seeds)")
    rp2.add_argument("run_dir", type=Path)


def _refuse_bad_combinations(args: argparse.Namespace) -> None:
    """Options that cannot go together, refused before anything is written or started."""
    if args.zenoh_mode == "peer" and not args.insecure:
        raise ValueError("--zenoh-mode peer links the processes directly, past the router's access control: "
                         "it needs --insecure")
    if args.seeds and (args.view is not None or args.foxglove is not None):
        raise ValueError("--view and --foxglove show one run: leave out --seeds, or them")


def _cmd_run(args: argparse.Namespace) -> int:
    from slcp.agent.methods import METHODS, MethodSpec
    from slcp.hw_emulation.scenario import load_scenario

    from ..launcher import run_fleet
    from ..supervisor import interrupt_on_termination

    interrupt_on_termination()
    _refuse_bad_combinations(args)
    methods = tuple(args.methods) if args.methods else METHODS
    for m in methods:
        MethodSpec.of(m)  # ValueError -> clear CLI error
    scn = load_scenario(args.scenario)
    if args.faults is not None:  # read before --force removes anything
        from slcp.hw_emulation.faults import load_faults

        load_faults(args.faults, {v.id for v in scn.vehicles})
    if args.out is not None:
        prepare_out(args.out, args.force)
    stem = folder_stem(scn.name)
    if args.seeds:
        from ..study import StudyError, run_study, study_markdown

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
                              zenoh_mode=args.zenoh_mode, secure=not args.insecure, lanelet2=args.lanelet2)
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
    from ..progress import ProgressView

    try:
        with ProgressView() as view:
            m = run_fleet(args.scenario, methods, args.speed, args.seed, out, progress=view, fusion=args.fusion,
                          sign=not args.no_sign, faults=args.faults, agent_nice=args.agent_nice,
                          lane_constraint=not args.no_lane_constraint, zenoh_mode=args.zenoh_mode,
                          secure=not args.insecure, view_port=args.view,
                          foxglove_port=args.foxglove, lanelet2=args.lanelet2, bag_inputs=args.bag_inputs)
    except KeyboardInterrupt:
        print("\nslcp run: interrupted; the fleet's processes are stopped", file=sys.stderr)
        _report_partial_run(out)
        return 130
    from ..summary import terminal_summary

    print(f"done in {m['wall_s']:.1f} s; processes exited {m['processes']['exit_codes']}\n")
    missed = m["processes"].get("faults_not_applied", [])
    if missed:
        print("slcp run: scheduled faults not applied (the fleet's clock stopped short of them, or their process "
              "was not running): " + ", ".join(f"{f['kind']} at {f['start_s']:g} s" for f in missed), file=sys.stderr)
    print(terminal_summary(scn, m, out / "report.md"))
    return 1 if missed else 0


def _report_partial_run(out: Path) -> None:
    """The report of what an interrupted run recorded, or one line on why there is none."""
    from ..run_report import rebuild_report

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


def _cmd_report(args: argparse.Namespace) -> int:
    from ..run_report import rebuild_report

    if any(args.run_dir.glob("seed-*")):  # a study: re-aggregate its seeds
        from slcp.hw_emulation.scenario import load_scenario

        from ..study import rebuild_study, study_markdown

        study = rebuild_study(args.run_dir)
        (args.run_dir / "report.md").write_text(study_markdown(load_scenario(study["scenario"]), study))
    else:
        from slcp.hw_emulation.scenario import load_scenario

        from ..summary import terminal_summary

        m = rebuild_report(args.run_dir)
        print(terminal_summary(load_scenario(m["scenario_source"]), m, args.run_dir / "report.md"))
        return 0
    print((args.run_dir / "report.md").read_text())
    return 0


HANDLERS = {"run": _cmd_run, "report": _cmd_report}
