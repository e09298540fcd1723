"""``slcp scenario``: list, export, show and evaluate emulation scenarios."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .. import cli_types as T
from .scenario_import import add_import_commands, cmd_from_sumo, cmd_from_trajectories


def add_scenario(sub) -> None:
    """The ``scenario`` command's parser."""
    sp = sub.add_parser("scenario", help="list or show emulation scenarios")
    ssub = sp.add_subparsers(dest="scenario_command", required=True)
    ssub.add_parser("list", help="list the shipped scenarios")
    ex = ssub.add_parser("export", help="write a shipped scenario's TOML, to start a scenario of your own from it")
    ex.add_argument("name", help="shipped scenario name")
    ex.add_argument("--out", type=Path, default=None, metavar="FILE.toml",
                    help="write here (default: print to the terminal); an existing file is kept unless --force")
    ex.add_argument("--force", action="store_true", help="replace an existing --out file")
    l2 = ssub.add_parser("to-lanelet2", help="write a scenario's site (lanes, stop lines) as a Lanelet2 map, "
                                             "with Autoware's map_projector_info.yaml beside it")
    l2.add_argument("name", help="shipped scenario name or path to a .toml file")
    l2.add_argument("out", type=Path, metavar="MAP.osm", help="the map to write")
    l2.add_argument("--force", action="store_true", help="replace an existing map")
    show = ssub.add_parser("show", help="summarise a scenario (name or TOML file)")
    show.add_argument("name", help="shipped scenario name or path to a .toml file")
    show.add_argument("--plot", type=T.plot_file, metavar="FILE.png", help="write a map with trajectories")
    chk = ssub.add_parser("sp-check", help="SP RMSE on emulated sensors beside the paper's SP row")
    chk.add_argument("name", help="shipped scenario name or path to a .toml file")
    chk.add_argument("--seeds", type=T.positive_int, default=20, help="sensor seeds to average (default 20)")
    chk.add_argument("--json", action="store_true", help="print one JSON object")
    gt = ssub.add_parser("gates", help="range-gate outcomes over many seeds (in process, spread over the cores)")
    gt.add_argument("name", help="shipped scenario name or path to a .toml file")
    gt.add_argument("--seeds", type=T.positive_int, default=25, help="seeds 0..N-1 (default 25)")
    gt.add_argument("--json", action="store_true", help="print one JSON object")
    ch = ssub.add_parser("chaos", help="write a random fault schedule for a scenario (kills, freezes, blackouts, "
                                       "emulator and router restarts), for slcp run --faults")
    ch.add_argument("name", help="shipped scenario name or path to a .toml file")
    ch.add_argument("--seed", type=T.seed, default=0, help="random seed (default 0)")
    ch.add_argument("--per-minute", type=T.positive_float, default=4.0,
                    help="faults per minute of sensor time (default 4)")
    ch.add_argument("--max-freeze", type=T.positive_float, default=30.0,
                    help="longest agent freeze [s of wall time] (default 30)")
    ch.add_argument("--out", type=Path, default=None, metavar="FILE.toml",
                    help="write here (default: print to the terminal); an existing file is kept unless --force")
    ch.add_argument("--force", action="store_true", help="replace an existing --out file")
    add_import_commands(ssub)
    st = ssub.add_parser("study", help="a seeded study in process (every method, the vehicles' engine without the "
                                       "bus), spread over the cores: RMSE per vehicle, paired differences, detection")
    st.add_argument("name", help="shipped scenario name or path to a .toml file")
    st.add_argument("--seeds", type=T.positive_int, default=25, help="seeds 0..N-1 (default 25)")
    st.add_argument("--jobs", type=T.positive_int, default=None, help="parallel seeds (default: cores)")
    st.add_argument("--out", type=Path, required=True, metavar="DIR", help="writes study.json and report.md here")
    st.add_argument("--bound", action="store_true",
                    help="also each seed's posterior CRLB and the estimates' NEES: RMSE over the bound and ANEES, "
                         "on the air and while standing (a few seconds of CPU per seed for a large fleet)")
    ev = ssub.add_parser("evaluate", help="run all vehicles and the four methods in one process (no bus)")
    ev.add_argument("name", help="shipped scenario name or path to a .toml file")
    ev.add_argument("--seed", type=T.seed, default=0, help="sensor seed (default 0)")
    ev.add_argument("--json", action="store_true", help="print one JSON object")


def _cmd_scenario(args: argparse.Namespace) -> int:
    from slcp.hw_emulation.scenario import load_scenario, shipped_scenarios

    if args.scenario_command == "list":
        for name in shipped_scenarios():
            scn = load_scenario(name)
            print(f"{name:12s} {len(scn.vehicles):3d} vehicles {scn.duration:6.0f} s  {scn.description}")
        return 0
    if args.scenario_command == "export":
        from slcp.hw_emulation.scenario import shipped_scenario_text

        return _write_or_print(args, shipped_scenario_text(args.name),
                               f"scenario {args.name}; run it with: slcp run {args.out}")
    own = {"chaos": _chaos, "study": _study, "from-sumo": cmd_from_sumo, "from-trajectories": cmd_from_trajectories}
    if args.scenario_command in own:
        return own[args.scenario_command](args)
    if args.scenario_command == "to-lanelet2":
        from slcp.geo.lanelet2_site import write_lanelet2

        if args.out.exists() and not args.force:
            raise FileExistsError(f"{args.out}: exists (use --force to replace it)")
        write_lanelet2(load_scenario(args.name).site, args.out)
        print(f"wrote {args.out} and its map_projector_info.yaml (the site of {args.name}: lanes and stop lines)")
        return 0
    from slcp.hw_emulation.events import event_times, window_bounds
    from slcp.hw_emulation.truth import build_truth

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
        print(f"  window {w}: {a:.1f} - {b:.1f} s" + (" (empty: its end comes before its start)" if b < a else ""))
    if args.plot:
        from ..plots import plot_scenario

        plot_scenario(truth, args.plot, ev)
        print(f"  wrote {args.plot}")
    return 0


def _evaluate(args: argparse.Namespace, scn, truth) -> int:
    import numpy as np

    from slcp.agent.methods import METHODS
    from slcp.hw_emulation.events import window_bounds

    from ..gates_study import summarise
    from ..inprocess import run_inprocess

    r = run_inprocess(truth, args.seed)
    rows = []
    for w, (a, b) in window_bounds(truth).items():
        m = (r.t >= a) & (r.t <= b)
        for vid in sorted(truth.vehicles):
            row = {"window": w, "vehicle": vid}
            for meth in METHODS:
                e = r.err[(vid, meth)][m]
                e = e[np.isfinite(e)]  # a vehicle off the air has no error
                row[meth] = float(np.sqrt(np.mean(e**2))) if len(e) else None
            row["paper"] = scn.paper_table.get(w, {}).get(vid, {})
            rows.append(row)
    detect = {}
    for vid, vt in truth.vehicles.items():
        k = vt.samples_over(r.t)
        true_first, zone = vt.first_stopped[k], vt.first_stop_zone[k]
        claims = r.first[(vid, "SL-SP")]
        detect[vid] = {"true_first_s": float(true_first.sum() / 10), "claimed_s": float(claims.sum() / 10),
                       "claimed_while_not_first_s": float((claims & ~true_first & ~zone).sum() / 10)}
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


def _study(args: argparse.Namespace) -> int:
    import sys

    from slcp.hw_emulation.scenario import load_scenario

    from ..inprocess_study import run_study, write_study

    scn = load_scenario(args.name)  # a clear error before the workers start

    def progress(seed: int, done: int, total: int) -> None:
        print(f"seed {seed} done ({done}/{total})", file=sys.stderr, flush=True)

    study = run_study(args.name, list(range(args.seeds)), args.jobs, progress, bound=args.bound)
    path = write_study(study, args.out, f"{scn.name}: a {len(scn.vehicles)}-vehicle study")
    print(path.read_text(), end="")
    return 0


def _gates(args: argparse.Namespace, scn) -> int:
    from ..gates_study import range_outcomes, summarise

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

    from ..sp_check import sp_table

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


HANDLERS = {"scenario": _cmd_scenario}


def _chaos(args: argparse.Namespace) -> int:
    import numpy as np

    from slcp.hw_emulation.faults import random_schedule, schedule_toml
    from slcp.hw_emulation.scenario import load_scenario

    scn = load_scenario(args.name)
    faults = random_schedule([v.id for v in scn.vehicles], scn.duration, np.random.default_rng(args.seed),
                             args.per_minute, args.max_freeze)
    text = schedule_toml(faults, f"slcp scenario chaos {args.name} --seed {args.seed}: {len(faults)} faults "
                                 f"in {scn.duration:g} s")
    return _write_or_print(args, text, f"{len(faults)} faults; run it with: slcp run {args.name} --faults {args.out}")


def _write_or_print(args: argparse.Namespace, text: str, what: str) -> int:
    """``text`` to ``args.out`` (kept unless ``args.force``), or to the terminal without one."""
    if args.out is None:
        print(text, end="")
        return 0
    if args.out.exists() and not args.force:
        raise FileExistsError(f"{args.out}: exists (use --force to replace it)")
    args.out.write_text(text)
    print(f"wrote {args.out} ({what})")
    return 0
