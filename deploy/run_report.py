"""A fleet run's evaluation: the recorded estimates against the truth.

:func:`evaluate_recording` reads a run's recording (``recorded/messages.jsonl``) and writes the
per-vehicle estimate files, the metrics and the pictures; :func:`report_markdown` is the run's
report; :func:`rebuild_report` evaluates a run directory again (``slcp report``), also one whose
launcher never got to it.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path

import numpy as np

from slcp.agent.methods import METHODS, MethodSpec
from slcp.geo import earth
from slcp.hw_emulation.events import event_times, window_bounds
from slcp.hw_emulation.faults import load_faults
from slcp.hw_emulation.scenario import STANDING_WINDOW, load_scenario
from slcp.hw_emulation.truth import build_truth

from .bound import posterior_crlb
from .detection import score_first_stopped

log = logging.getLogger(__name__)


def lane_keeping_label(lane_constraint: bool | None) -> str:
    """", lane-keeping on|off" for a report's title ("" when a run does not say)."""
    return {True: ", lane-keeping on", False: ", lane-keeping off"}.get(lane_constraint, "")


def evaluate_recording(truth, path: Path, out: Path, methods: tuple[str, ...], faults: list | None = None,
                       lane_constraint: bool = True) -> dict:
    """RMSE per window, vehicle and method from the recorded estimates; writes estimate CSVs.
    ``lane_constraint`` says whether the SL methods kept to the lanes (for the bound).
    With a fault schedule, each fault's window is shaded on the plot and its recovery measured
    (:func:`fault_recovery`)."""
    est, diags, bad_lines = _read_recording(path)
    windows = window_bounds(truth)
    bound = posterior_crlb(truth, tuple(methods), lane_constraint=lane_constraint)
    scored: dict[tuple[str, str], _Scored] = {}
    for vid, vt in truth.vehicles.items():
        with open(out / "estimates" / f"{vid}.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(ESTIMATE_COLUMNS)
            for m in methods:
                scored[(vid, m)] = _score_method(vt, m, sorted(est.get((vid, m), []), key=lambda r: r["t"]), w)
    series = {k: (sc.t, sc.err) for k, sc in scored.items()}
    try:
        from .plots import plot_run_errors, plot_scenario

        plot_run_errors(series, windows, methods, out / "errors.png",
                        f"{truth.scenario.name}: horizontal error per vehicle and method",
                        {k: sc.sigma_h for k, sc in scored.items()}, bound, faults=faults)
        shown = next((m for m in ("SL-CP", "CP", "SL-SP", "SP") if m in methods), None)
        plot_scenario(truth, out / "map.png", event_times(truth), map_estimates(est, truth, shown), shown)
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        log.warning("matplotlib unavailable: no plots")
    detection: dict = {}
    for (vid, m), sc in scored.items():
        if MethodSpec.of(m).stop_line and (sc.claim.any() or sc.truth_first.any()):
            detection.setdefault(vid, {})[m] = score_first_stopped(sc.t, sc.truth_first, sc.claim, sc.err[:, 0],
                                                                   zone=sc.zone)
    return {
        "scenario": truth.scenario.name,
        "events": event_times(truth),
        "windows": {k: list(v) for k, v in windows.items()},
        "faults": [fault_recovery(f, series, sorted(truth.vehicles)) for f in faults or []],
        "rmse": _window_rows(scored, windows, bound),
        "first_stopped": detection,
        "unreadable_lines": bad_lines,
        "estimates": {f"{v}/{m}": len(sc.t) for (v, m), sc in scored.items()},
        "diagnostics": diags,
    }


ESTIMATE_COLUMNS = ["time_s", "method", "lat_deg", "lon_deg", "h_m", "vn_mps", "ve_mps", "vd_mps",
                    "roll_deg", "pitch_deg", "yaw_deg", "sigma_n_m", "sigma_e_m", "cov_ne_m2", "first_stopped",
                    "err_n_m", "err_e_m", "err_h_m", "err_along_m", "err_cross_m", "nees_h"]


def _read_recording(path: Path) -> tuple[dict[tuple[str, str], list[dict]], dict[str, dict], int]:
    """The recording's estimates per (vehicle, method), the last diagnostics per source, and the
    number of lines that could not be read (e.g. a line cut short when a recorder was killed).
    ``path`` is the JSON lines file, or a ROS 2 bag directory (:mod:`deploy.mcap_recording`)."""
    if Path(path).is_dir():
        from .mcap_recording import read_recording

        est_bag, diags_bag, _ = read_recording(Path(path))
        return est_bag, diags_bag, 0
    est: dict[tuple[str, str], list[dict]] = {}
    diags: dict[str, dict] = {}
    bad_lines = 0
    with open(path) as fh:
        for line in fh:
            try:
                r = json.loads(line)
            except json.JSONDecodeError:
                bad_lines += 1
                continue
            if r["type"] == "Estimate":
                est.setdefault((r["vehicle"], r["method"]), []).append(r)
            elif r["type"] == "Diagnostics":
                diags[r["source"]] = r["counters"]
    return est, diags, bad_lines


class _Scored:
    """One vehicle and method's estimates against the truth, at the estimates' times."""

    def __init__(self, t, err, nees, claim, truth_first, standing, sigma_h, zone=None) -> None:
        self.t = np.array(t)
        self.err = np.array(err).reshape(-1, 3)  #: horizontal, along-track, cross-track [m]
        self.nees = np.array(nees)
        self.claim = np.array(claim, bool)
        self.truth_first = np.array(truth_first, bool)
        self.standing = np.array(standing, bool)
        self.sigma_h = np.asarray(sigma_h, float)
        self.zone = np.array(zone if zone is not None else truth_first, bool)


def _score_method(vt, m: str, recs: list[dict], w) -> _Scored:
    """Score one method's estimates of vehicle ``vt``, writing a CSV row for each to ``w``."""
    tr = vt.truth
    ts, eh, nees, claim, truth_first, stands, zone = [], [], [], [], [], [], []
    for r in recs:
        e, k = vt.error_of(r["t"], r["llh"])
        yaw = tr.euler[k, 2]
        along = e[0] * math.cos(yaw) + e[1] * math.sin(yaw)
        cross = -e[0] * math.sin(yaw) + e[1] * math.cos(yaw)
        cov = np.array(r["cov_pos"])
        try:
            q = float(e[:2] @ np.linalg.solve(cov[:2, :2], e[:2]))
        except np.linalg.LinAlgError:
            q = math.inf
        w.writerow([f"{r['t']:.3f}", m, f"{math.degrees(r['llh'][0]):.9f}", f"{math.degrees(r['llh'][1]):.9f}",
                    f"{r['llh'][2]:.3f}", *(f"{x:.3f}" for x in r["v_ned"]),
                    *(f"{math.degrees(x):.3f}" for x in r["rpy"]), f"{math.sqrt(cov[0][0]):.3f}",
                    f"{math.sqrt(cov[1][1]):.3f}", f"{cov[0][1]:.4f}", int(r["first_stopped"]), f"{e[0]:.3f}",
                    f"{e[1]:.3f}", f"{math.hypot(e[0], e[1]):.3f}", f"{along:.3f}", f"{cross:.3f}", f"{q:.4f}"])
        ts.append(r["t"])
        eh.append((math.hypot(e[0], e[1]), along, cross))
        nees.append(q)
        claim.append(bool(r["first_stopped"]))
        truth_first.append(bool(vt.first_stopped[k]))
        zone.append(bool(vt.first_stop_zone[k]))
        stands.append(bool(vt.stopped[k]))
    sigma_h = np.sqrt([r["cov_pos"][0][0] + r["cov_pos"][1][1] for r in recs])
    return _Scored(ts, eh, nees, claim, truth_first, stands, sigma_h, zone)


def _window_rows(scored: dict[tuple[str, str], _Scored], windows: dict, bound) -> dict:
    """Window -> vehicle -> method -> RMSE (horizontal, along, cross), NEES and the bound: the
    scenario's windows, then each vehicle's own, the times it truly stands still."""
    rows: dict = {w: {} for w in windows}
    for (vid, m), sc in scored.items():
        masks = [(wname, (sc.t >= a) & (sc.t <= b)) for wname, (a, b) in windows.items()]
        for wname, sel in masks + [(STANDING_WINDOW, sc.standing)]:
            if sel.any():
                rms = np.sqrt(np.mean(sc.err[sel] ** 2, axis=0))
                lim = bound.at(m, vid, sc.t[sel])
                rows.setdefault(wname, {}).setdefault(vid, {})[m] = {
                    "rmse_m": float(rms[0]), "along_rmse_m": float(rms[1]), "cross_rmse_m": float(rms[2]),
                    "n": int(sel.sum()), "nees_h": float(np.mean(sc.nees[sel])),
                    "bound_rms_m": float(np.sqrt(np.mean(lim**2))),
                    "sigma_below_bound": float(np.mean(sc.sigma_h[sel] < lim * 0.99))}
    return rows


def fault_recovery(fault, series: dict, vehicles: list[str], before: float = 5.0) -> dict:
    """A fault's effect on the affected vehicles' horizontal error, per method: the mean over
    ``before`` seconds before it, the maximum from its start to 10 s after its end, and the
    recovery time: from its end until the error, past that maximum, is back within
    max(1.2 × before, before + 0.3 m) (None if it never is)."""
    hit = list(fault.vehicles) or vehicles
    out = {"kind": fault.kind, "start_s": fault.start, "end_s": fault.end, "vehicles": list(fault.vehicles),
           "effect": {}}
    for (vid, m), (ts, eh) in series.items():
        if vid not in hit or not len(ts):
            continue
        pre = eh[(ts >= fault.start - before) & (ts < fault.start), 0]
        during = (ts >= fault.start) & (ts <= fault.end + 10.0)
        if not pre.size or not during.any():
            continue
        base = float(np.mean(pre))
        ok = max(1.2 * base, base + 0.3)
        idx = np.flatnonzero(during)
        peak = idx[int(np.argmax(eh[idx, 0]))]
        after = np.flatnonzero((ts >= max(fault.end, ts[peak])) & (eh[:, 0] <= ok))
        if eh[peak, 0] <= ok:
            recovery: float | None = 0.0  # never left the band
        else:
            recovery = max(float(ts[after[0]] - fault.end), 0.0) if after.size else None
        out["effect"].setdefault(vid, {})[m] = {"before_m": base, "max_m": float(eh[peak, 0]),
                                                "recovery_s": recovery}
    return out


def report_markdown(scn, metrics: dict) -> str:
    """The run's report: paper-style RMSE tables with along/cross-track split and NEES, the
    first-stopped detection scores, events and plots."""
    fusion = metrics.get("fusion", "split-ci")  # runs from before source CI did not record it
    lane = lane_keeping_label(metrics.get("lane_constraint"))
    lines = [
        f"# slcp run: {scn.name} (seed {metrics.get('seed', '?')}, fusion `{fusion}`{lane})",
        "",
        scn.description,
        "",
        "Horizontal RMSE [m] per window, vehicle and method, the paper's figure in brackets. Below each value: "
        "along-track / cross-track RMSE [m]; the mean horizontal NEES (2 for a consistent filter); the "
        "posterior Cramér-Rao bound (RMS over the window) and the share of time the reported σ is below it "
        "(an unbiased filter whose σ is below the bound is overconfident).",
        "",
    ]
    lines += _md_rmse(scn, metrics) + _md_detection(metrics) + _md_faults(metrics) + _md_restarts(metrics)
    lines += ["## Events", "", ", ".join(f"{k} = {v:.1f} s" for k, v in metrics["events"].items()), "",
              "![errors](errors.png)", "", "![map](map.png)", ""]
    return "\n".join(lines)


def _md_rmse(scn, metrics: dict) -> list[str]:
    """The RMSE tables, one per window."""
    lines: list[str] = []
    for w, table in metrics["rmse"].items():
        lines += [f"## {w}", "", "| vehicle | " + " | ".join(METHODS) + " |", "|---" * (len(METHODS) + 1) + "|"]
        for vid, cells in sorted(table.items()):
            row = []
            for m in METHODS:
                c = cells.get(m)
                p = scn.paper_table.get(w, {}).get(vid, {}).get(m)
                if c is None:
                    row.append("–")
                else:
                    row.append(
                        f"{c['rmse_m']:.2f}"
                        + (f" [{p:.2f}]" if p is not None else "")
                        + f"<br>{c['along_rmse_m']:.2f} / {c['cross_rmse_m']:.2f}"
                        + f"<br>NEES {c.get('nees_h', float('nan')):.1f}"
                        + f"<br>bound {c.get('bound_rms_m', float('nan')):.2f}, "
                        + f"σ<bound {100 * c.get('sigma_below_bound', 0):.0f} %"
                    )
            lines.append(f"| {vid} | " + " | ".join(row) + " |")
        lines.append("")
    return lines


def _md_detection(metrics: dict) -> list[str]:
    """First-stopped detection against the truth."""
    lines: list[str] = []
    det = metrics.get("first_stopped", {})
    if det:
        lines += ["## First-stopped detection", "",
                  "Against the emulator's truth (a claim within 0.3 s of a true first-stopped interval counts as "
                  "correct). SL RMSE: the stop-line method's horizontal error over the whole true interval "
                  "(detection latency included) and over its claimed part.", "",
                  "| vehicle | method | truly first [s] | claimed [s] | wrong [s] | precision | recall | latency [s] "
                  "| SL RMSE whole / claimed [m] |", "|---" * 9 + "|"]
        for vid, ms in sorted(det.items()):
            for m, d in ms.items():
                def f(x, fmt="{:.3f}"):
                    return "–" if x is None else fmt.format(x)
                lat = ", ".join("–" if x is None else f"{x:.1f}" for x in d["latency_s"]) or "–"
                lines.append(
                    f"| {vid} | {m} | {d['truth_s']:.1f} | {d['claimed_s']:.1f} | {d['wrong_s']:.1f} | "
                    f"{f(d['precision'])} | {f(d['recall'])} | {lat} | "
                    f"{f(d.get('sl_rmse_truth_first_m'), '{:.2f}')} / {f(d.get('sl_rmse_claimed_m'), '{:.2f}')} |"
                )
        lines.append("")
    return lines


def _md_faults(metrics: dict) -> list[str]:
    """Each fault's effect on the affected vehicles."""
    lines: list[str] = []
    if metrics.get("faults"):
        lines += ["## Faults", "", "Error of each affected vehicle: mean over 5 s before the fault, maximum until 10 s "
                  "after it, and the time from its end until the error, past that maximum, is back within "
                  "max(1.2 × before, before + 0.3 m).",
                  "", "| fault | window [s] | vehicle | method | before [m] | max [m] | recovery [s] |",
                  "|---|---|---|---|---|---|---|"]
        for f in metrics["faults"]:
            who = ",".join(f["vehicles"]) or "all"
            for vid, per in f["effect"].items():
                for m, e in per.items():
                    rec = "never" if e["recovery_s"] is None else f"{e['recovery_s']:.1f}"
                    lines.append(f"| {f['kind']} ({who}) | {f['start_s']:.1f}–{f['end_s']:.1f} | {vid} | {m} | "
                                 f"{e['before_m']:.2f} | {e['max_m']:.2f} | {rec} |")
        lines.append("")
    return lines


def _md_restarts(metrics: dict) -> list[str]:
    """The processes that were restarted."""
    lines: list[str] = []
    restarts = metrics.get("processes", {}).get("restarts", [])
    if restarts:
        lines += [
            "## Process faults",
            "",
            "| process | exit code | at [s wall] | rejoined after [s] |",
            "|---|---|---|---|",
        ]
        for r in restarts:
            rj = "never" if r["rejoined_after_s"] is None else f"{r['rejoined_after_s']:.2f}"
            lines.append(f"| {r['process']} | {r['exit_code']} | {r['at_s']:.1f} | {rj} |")
        lines.append("")
    return lines


def map_estimates(est: dict, truth, method: str | None) -> dict:
    """The recorded estimates of ``method`` per vehicle in the map frame, for the map:
    {vehicle: (t, north/east (n, 2), north/east covariance (n, 2, 2))}."""
    out = {}
    o = truth.scenario.origin_llh
    for vid in truth.vehicles:
        recs = sorted(est.get((vid, method), []), key=lambda r: r["t"])
        if not recs:
            continue
        ne = np.array([earth.ned_offset(*r["llh"], *o)[:2] for r in recs])
        cov = np.array([np.asarray(r["cov_pos"], float)[:2, :2] for r in recs])
        out[vid] = (np.array([r["t"] for r in recs]), ne, cov)
    return out


def recording_of(run_dir: Path) -> Path:
    """A run's recording: its JSON lines, or else its ROS 2 bag (``recorded/bag``)."""
    for rec in (run_dir / "recorded" / "messages.jsonl", run_dir / "recorded" / "bag"):
        if rec.exists():
            return rec
    raise ValueError(f"{run_dir}: not a run directory (no recorded/messages.jsonl or recorded/bag)")


def rebuild_report(run_dir: Path) -> dict:
    """Re-evaluate a single run directory from its recording (``slcp report``)."""
    import tomllib

    run_dir = Path(run_dir)
    mpath = run_dir / "metrics.json"
    rec = recording_of(run_dir)
    old: dict = {}
    if mpath.is_file():
        try:
            old = json.loads(mpath.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{mpath}: unreadable metrics ({exc})") from None
    run_cfg = run_dir / "config" / "run.json"
    if run_cfg.is_file():  # what the run was started with: the scenario's file, not only its name
        try:
            started = json.loads(run_cfg.read_text())
            old.update({k: v for k, v in started.items() if k in ("scenario", "methods") or k not in old})
        except (json.JSONDecodeError, AttributeError, TypeError) as exc:
            raise ValueError(f"{run_cfg}: unreadable ({exc})") from None
    name = old.get("scenario")
    for cfg in sorted((run_dir / "config").glob("agent-*.toml")) if name is None else ():
        try:  # a run that stopped before its evaluation: the agents' configs name the scenario
            agent = tomllib.loads(cfg.read_text()).get("agent", {})
        except (OSError, tomllib.TOMLDecodeError):
            continue
        name, old["fusion"] = agent.get("scenario"), agent.get("fusion", "split-ci")
        old["lane_constraint"] = agent.get("lane_constraint", True)
        break
    if not isinstance(name, str):
        raise ValueError(f"{run_dir}: cannot tell the scenario (no metrics.json or config/agent-*.toml)")
    scn = load_scenario(name)
    (run_dir / "estimates").mkdir(exist_ok=True)
    fpath = run_dir / "config" / "faults.toml"
    schedule = load_faults(fpath, {v.id for v in scn.vehicles}) if fpath.exists() else []
    seed = old.get("seed")
    truth = build_truth(scn, stop_seed=seed if isinstance(seed, int) and seed >= 0 else None)
    methods = tuple(m for m in old.get("methods", METHODS) if m in METHODS) or METHODS  # the run's own
    metrics = evaluate_recording(truth, rec, run_dir, methods, schedule, old.get("lane_constraint", True) is not False)
    for k in ("wall_s", "seed", "fusion", "lane_constraint", "processes"):
        if k in old:
            metrics[k] = old[k]
    metrics["scenario_source"] = name
    mpath.write_text(json.dumps(metrics, indent=2))
    (run_dir / "report.md").write_text(report_markdown(scn, metrics))
    return metrics
