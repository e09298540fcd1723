"""The lab's commands: ``slcp attack-eval``, ``bound``, ``bench`` and ``soak``."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from slcp.agent.methods import DEFAULT_FUSION, FUSION_RULES

from .. import cli_types as T
from ..fleet_capacity import FLEET_ENGINES


def add_attack_eval(sub) -> None:
    """The ``attack-eval`` command's parser."""
    ae = sub.add_parser(
        "attack-eval", help="misbehaviour detection against the VeReMi attacks, and false alarms on clean runs"
    )
    ae.add_argument("scenario", nargs="?", default="paper-1")
    ae.add_argument("--seeds", type=T.positive_int, default=5, help="attack runs per kind (default 5)")
    ae.add_argument("--kinds", nargs="+", default=None, help="attack kinds (default: all)")
    ae.add_argument("--clean", nargs="*", default=None, metavar="SCENARIO",
                    help="also count false alarms on whole clean runs of these scenarios (seed 0)")
    ae.add_argument("--json", action="store_true", help="print one JSON object")


def add_bound(sub) -> None:
    """The ``bound`` command's parser."""
    bd = sub.add_parser("bound", help="posterior Cramér-Rao bound per vehicle and method on a scenario's truth")
    bd.add_argument("scenario", help="shipped scenario name or .toml")
    bd.add_argument("--json", action="store_true", help="print one JSON object")
    bd.add_argument("--plot", type=T.plot_file, metavar="FILE.png", help="plot the bound over time")
    bd.add_argument("--csv", type=Path, metavar="FILE.csv", help="write the bound over time")
    bd.add_argument("--no-lane-constraint", action="store_true",
                    help="SL bounds without the lane-keeping information (as for slcp run --no-lane-constraint)")
    bd.add_argument("--lane-offset", choices=("scenario", "vehicle", "lane"), default="scenario",
                    help="the driver's offset in a lane: as the scenario's drivers draw it, correlated from "
                         "lane to lane by their lateral.correlation (the bound proper; default), one constant "
                         "per vehicle on its whole route, or drawn anew in each lane, as the filters model it")
    bd.add_argument("--vehicles", metavar="ID,ID,...",
                    help="a sub-fleet: the cooperative bounds process only these vehicles' information "
                         "(how much of a bound comes from which neighbours; default: all)")
    bd.add_argument("--seed", type=T.seed, default=None,
                    help="the drivers' stop draws of this run seed, as slcp run --seed draws them "
                         "(default: the scenario's draw)")


def add_bench(sub) -> None:
    """The ``bench`` command's parser."""
    bn = sub.add_parser("bench", help="per-step costs of an agent and the replay real-time factor")
    bn.add_argument("--drive", type=Path, default=Path("../shared/data/rtklibexplorer_drive_0708"),
                    help="rtklibexplorer drive for the replay factor (skipped if absent)")
    bn.add_argument("--quick", action="store_true", help="fewer repetitions")
    bn.add_argument("--json", action="store_true", help="print one JSON object")
    fg = bn.add_mutually_exclusive_group()
    fg.add_argument("--fleet", default=None, metavar="N,N,...",
                    help="also run the fleet scaling benchmark with these agent counts (e.g. 10,25,50,75)")
    fg.add_argument("--fleet-capacity", nargs="?", const="10:100", default=None, metavar="START:MOST",
                    help="also find the largest fleet this machine holds within the performance targets: "
                         "counts from START doubled, then bisected to 5 agents, at most MOST (default 10:100)")
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
    bn.add_argument("--fleet-imu-batch", type=T.int_range(1, 100), default=20, metavar="1-100",
                    help="IMU samples per message in the fleet's grid (default 20: 5 messages a second at 100 Hz)")
    bn.add_argument("--fleet-engine", choices=FLEET_ENGINES, default="full",
                    help="the agents' engine: full (default), or stand-in: once started it estimates nothing "
                         "and sends copies of its beacons and estimates at their rates, so the point "
                         "measures what the fleet costs without its estimation")
    bn.add_argument("--fleet-view", action="store_true",
                    help="serve the live map during each fleet point, watched by a client that takes every frame")


def add_soak(sub) -> None:
    """The ``soak`` command's parser."""
    sk = sub.add_parser("soak", help="a long fleet run on an open bus beside a hostile station: bounded memory, "
                                     "decodable diagnostics, every genuine beacon delivered")
    sk.add_argument("scenario", nargs="?", default="paper-1", help="shipped scenario name or .toml (default paper-1)")
    sk.add_argument("--duration", type=T.positive_float, default=600.0,
                    help="sensor time [s]: the scenario is played this long (default 600)")
    sk.add_argument("--rate", type=T.nonnegative_float, default=10_000.0,
                    help="bad beacons per second from the hostile station (default 10000)")
    sk.add_argument("--big-rate", type=T.nonnegative_float, default=1.0,
                    help="10 MB payloads per second, each to an agent, the radio and the recorder (default 1)")
    sk.add_argument("--identities", type=T.positive_int, default=5000,
                    help="stranger identities churning through liveliness (default 5000)")
    sk.add_argument("--token-life", type=T.positive_float, default=5.0,
                    help="how long a stranger's liveliness token lives [s] (default 5)")
    sk.add_argument("--speed", type=T.positive_float, default=1.0, help="real-time factor of the fleet (default 1)")
    sk.add_argument("--seed", type=T.seed, default=0, help="seed of the run and of the hostile station (default 0)")
    sk.add_argument("--out", type=Path, default=None, help="run directory (default runs/soak-<scenario>)")
    sk.add_argument("--json", action="store_true", help="print the verdict as one JSON object")


def _cmd_soak(args: argparse.Namespace) -> int:
    from ..soak import run_soak

    out = args.out or Path("runs") / f"soak-{Path(args.scenario).stem}"
    if args.identities < 2:
        raise ValueError("--identities must be at least 2")
    v = run_soak(args.scenario, args.duration, args.seed, out, args.rate, args.big_rate, args.identities,
                 args.token_life, args.speed)
    if args.json:
        print(json.dumps(v, default=str))
        return 0 if v["passed"] else 1
    a = v["attacker"]
    print(f"soak of {args.scenario} for {args.duration:g} s: {'passed' if v['passed'] else 'FAILED'} ({out})")
    print(f"  hostile station: {a.get('bad_beacons', 0):,} bad beacons ({a.get('bad_per_s', 0):,.0f}/s), "
          f"{a.get('oversized_payloads', 0)} payloads of {a.get('oversized_bytes', 0) / 2**20:g} MB, "
          f"{a.get('tokens_declared', 0):,} liveliness tokens over {a.get('identities', 0):,} identities")
    for name, ok in v["checks"].items():
        print(f"  {'ok  ' if ok else 'FAIL'} {name.replace('_', ' ')}")
    print("  resident set [MB], peak of the middle third -> of the last third:")
    for name, m in v["memory"].items():
        print(f"    {name:12s} {m['peak_mid_mb']:8.1f} -> {m['peak_end_mb']:8.1f}")
    lost = sum(b.get("lost", 0) for b in v["beacons"].values() if isinstance(b.get("lost"), int))
    got = sum(b.get("verified", 0) for b in v["beacons"].values())
    print(f"  genuine beacons: {got:,} verified, {lost} lost; the curve: {out / 'soak-rss.csv'}")
    return 0 if v["passed"] else 1


def _cmd_attack_eval(args: argparse.Namespace) -> int:
    from slcp.hw_emulation.attacks import ATTACKS

    from ..attack_eval import attack_study, evaluate_clean

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


def _cmd_bound(args: argparse.Namespace) -> int:
    import numpy as np

    from slcp.agent.methods import METHODS
    from slcp.hw_emulation.events import window_bounds
    from slcp.hw_emulation.scenario import STANDING_WINDOW, load_scenario
    from slcp.hw_emulation.truth import build_truth

    from ..bound import posterior_crlb

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
        from ..plots import plot_bound

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

    from slcp.agent.methods import MethodSpec

    from ..bench import micro_benchmarks, replay_factor

    counts, search = _fleet_counts(args)
    if counts or search:
        if not args.fleet_duration > 5:
            raise ValueError("--fleet-duration must be > 5 s")
        MethodSpec.of(args.fleet_method)
    out = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
           "steps": micro_benchmarks(args.quick), "replay": replay_factor(args.drive, 1 if args.quick else 3)}
    if counts:
        out["fleet"] = [_fleet_point(args, n) for n in counts]
    if search:
        from ..fleet_capacity import capacity_search

        found = capacity_search(lambda n: _fleet_point(args, n), start=search[0], most=search[1])
        out["fleet"] = found.pop("points")
        out["capacity"] = found
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
        _print_fleet_point(f)
    if "capacity" in out:
        from ..fleet_capacity import BEACON_P99_MAX_MS, REALTIME_MIN, RSS_MAX_MB

        c = out["capacity"]
        print(f"  capacity: {c['capacity']} agents meet the targets (real-time factor >= {REALTIME_MIN:g}, beacon p99 "
              f"< {BEACON_P99_MAX_MS:g} ms, no sensor sample dropped, RSS <= {RSS_MAX_MB:g} MB)"
              + ("" if c["first_missed"] is None else f"; {c['first_missed']} did not")
              + " (one run each: near the boundary, a run again may differ)")
    return 0


def _fleet_counts(args: argparse.Namespace) -> tuple[list[int], tuple[int, int] | None]:
    """The agent counts of ``--fleet``, and ``--fleet-capacity``'s START and MOST."""
    counts: list[int] = []
    if args.fleet:
        try:
            counts = [int(x) for x in args.fleet.split(",")]
        except ValueError:
            counts = [0]
        if not counts or min(counts) < 1:
            raise ValueError(f"--fleet {args.fleet!r}: expected positive agent counts, e.g. 10,25,50,75")
    search = None
    if args.fleet_capacity is not None:
        try:
            start, most = (int(x) for x in args.fleet_capacity.split(":"))
        except ValueError:
            start = most = 0
        if not 1 <= start <= most:
            raise ValueError(f"--fleet-capacity {args.fleet_capacity!r}: expected START:MOST agent counts with "
                             "1 <= START <= MOST, e.g. 10:100")
        search = (start, most)
    return counts, search


def _fleet_point(args: argparse.Namespace, n: int) -> dict:
    """One fleet point of ``slcp bench``, with the step costs measured right after it and what it
    misses of the performance targets."""
    from ..bench import micro_benchmarks
    from ..fleet_bench import run_fleet_point
    from ..fleet_capacity import missed_targets

    if not args.json:
        print(f"fleet benchmark: {n} agents for {args.fleet_duration:g} s at 1x ...", file=sys.stderr)
    point = run_fleet_point(n, args.fleet_duration, args.fleet_method, zenoh_mode=args.fleet_zenoh_mode,
                            imu_batch=args.fleet_imu_batch, fusion=args.fleet_fusion, view=args.fleet_view,
                            engine=args.fleet_engine)
    # the machine's speed drifts within a run too: the costs of the agents' main steps,
    # measured again right after the point, tell a slow moment from a regression
    steps = micro_benchmarks(quick=True)
    point["steps"] = {k: steps[k] for k in FLEET_POINT_STEPS}
    point["missed"] = missed_targets(point)
    return point


#: the step costs ``slcp bench`` measures again beside each fleet point
FLEET_POINT_STEPS = ("mechanisation_us", "covariance_step_us", "gnss_update_us", "range_update_source_ci_us",
                     "beacon_verify_us")


def _print_fleet_point(f: dict) -> None:
    if "error" in f:
        print(f"  fleet {f['agents']:3d} agents: {f['error']}")
    else:
        _print_fleet_figures(f)
    if f.get("steps"):
        print("    step costs right after it: " + ", ".join(
            f"{k.removesuffix('_us').replace('_', ' ')} {v:.1f} µs" for k, v in f["steps"].items()))
    if "missed" in f:
        print("    performance targets: " + ("met" if not f["missed"] else "missed: " + "; ".join(f["missed"])))


def _print_fleet_figures(f: dict) -> None:
    """One fleet point's figures (``slcp bench`` without ``--json``)."""
    lat = f["beacon_latency_ms"] or {"p50": float("nan"), "p99": float("nan")}
    print(
        f"  fleet {f['agents']:3d} agents ({f['method']}, {f['fusion']}, Zenoh {f['zenoh_mode']}, "
        f"IMU batch {f['imu_batch']}{', stand-in engine' if f.get('engine') == 'stand-in' else ''}): "
        f"real-time factor {f['realtime_factor']:.2f}, lag p99 {f['lag_p99_s']:.2f} s, "
        f"CPU/agent {f['cpu_pct_per_agent']['mean']:.1f} % "
        f"(max {f['cpu_pct_per_agent']['max']:.1f}, {f['threads_per_agent']} threads), emulator "
        f"{f['emulator_cpu_pct']:.0f} %, launcher {f['launcher_cpu_pct']:.0f} %, "
        f"machine {f['machine_cpu_pct']:.0f} %, "
        f"RSS/agent {f['rss_mb_per_agent']['mean']:.0f} MB (max {f['rss_mb_per_agent']['max']:.0f}), "
        f"beacon latency p50 {lat['p50']:.1f} ms p99 {lat['p99']:.1f} ms, sensor drops {f['sensor_dropped']}"
        + (f", live map {f['view_frames']} frames of up to {f['view_vehicles']} vehicles" if "view_frames" in f
           else "")
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


HANDLERS = {"attack-eval": _cmd_attack_eval, "bound": _cmd_bound, "bench": _cmd_bench, "soak": _cmd_soak}
