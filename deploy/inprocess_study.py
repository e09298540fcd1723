"""A seeded study in process (``slcp scenario study``): every seed a full in-process run of the
vehicle engines (:func:`deploy.inprocess.run_inprocess`, the code a vehicle runs, fed the
emulator's own messages and radio, without the bus), spread over the cores.

It answers what a fleet study (``slcp run --seeds``) does, per vehicle and method, for a fleet too
large to run as processes seed after seed on one machine: the RMSE over the times each vehicle is
on the air (mean and sd over the seeds), the paired differences CP - SP and SL-CP - CP, and the
first-stopped detection of the stop-line methods, pooled over the seeds and the fleet. With
``bound``, also each seed's posterior CRLB (:func:`deploy.bound.posterior_crlb`) and the
estimates' horizontal NEES, on the air and while each vehicle truly stands: the RMSE over the
bound and the ANEES, as the fleet study reports them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from slcp.agent.methods import METHODS

from .detection import score_first_stopped
from .study import paired_difference
from .worker_pool import worker_pool

#: the pairs whose differences the study tests (the first is the one that should be lower)
PAIRS = (("CP", "SP"), ("SL-CP", "CP"), ("SL-SP", "SP"))


#: the windows of the study's bound: every vehicle's times on the air, and those it truly stands
BOUND_WINDOWS = ("on the air", "standing")


def one_seed(args: tuple[str, int] | tuple[str, int, bool]) -> dict:
    """One seed: vehicle -> method -> RMSE [m] on the air, and the detection per SL method; with
    the third element true, also ``bound``: window -> vehicle -> method -> the RMSE, the bound's
    RMS [m], the mean horizontal NEES and the number of estimates (:data:`BOUND_WINDOWS`)."""
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.truth import build_truth

    from .inprocess import run_inprocess

    scenario, seed = args[0], args[1]
    with_bound = len(args) > 2 and bool(args[2])
    truth = build_truth(load_scenario(scenario), stop_seed=seed)
    r = run_inprocess(truth, seed)
    out: dict = {"seed": seed, "rmse": {}, "first_stopped": {}}
    b = None
    if with_bound:
        from .bound import posterior_crlb

        b = posterior_crlb(truth, METHODS)
        out["bound"] = {}
    for vid, vt in truth.vehicles.items():
        k = vt.samples_over(r.t)
        on = vt.present_over(r.t)
        for m in METHODS:
            e = r.err[(vid, m)][on]
            e = e[np.isfinite(e)]
            if len(e):
                out["rmse"].setdefault(vid, {})[m] = float(np.sqrt(np.mean(e**2)))
            if b is not None:
                for w, sel in zip(BOUND_WINDOWS, (on, on & vt.stopped[k])):
                    cell = _against_bound(r.err[(vid, m)][sel], r.nees[(vid, m)][sel], b.at(m, vid, r.t[sel]))
                    if cell is not None:
                        out["bound"].setdefault(w, {}).setdefault(vid, {})[m] = cell
            if m.startswith("SL-"):
                sc = score_first_stopped(r.t[on], vt.first_stopped[k][on], r.first[(vid, m)][on],
                                         zone=vt.first_stop_zone[k][on])
                out["first_stopped"].setdefault(vid, {})[m] = {x: sc[x] for x in ("truth_s", "claimed_s", "wrong_s",
                                                                                   "covered_s")}
    return out


def _against_bound(err: np.ndarray, nees: np.ndarray, bound: np.ndarray) -> dict | None:
    """A window's RMSE [m], the bound's RMS over the same estimates [m], their mean horizontal
    NEES and their number (None for a window without a scored estimate)."""
    ok = np.isfinite(err) & np.isfinite(nees)
    if not ok.any():
        return None
    return {"rmse_m": float(np.sqrt(np.mean(err[ok] ** 2))), "bound_rms_m": float(np.sqrt(np.mean(bound[ok] ** 2))),
            "nees_h": float(np.mean(nees[ok])), "n": int(ok.sum())}


def run_study(scenario: str, seeds: list[int], processes: int | None = None, progress=None,
              bound: bool = False) -> dict:
    """The study's per-seed results and their summary (:func:`summarise`); ``bound``: also each
    seed's posterior CRLB and the estimates' NEES (:func:`one_seed`)."""
    workers = max(1, min(processes or os.cpu_count() or 1, len(seeds)))
    per_seed = []
    with worker_pool(workers) as pool:
        for res in pool.map(one_seed, [(scenario, s, bound) for s in seeds]):
            per_seed.append(res)
            if progress is not None:
                progress(res["seed"], len(per_seed), len(seeds))
    return {"scenario": scenario, "seeds": seeds, "per_seed": per_seed, "summary": summarise(per_seed)}


def summarise(per_seed: list[dict]) -> dict:
    """Per vehicle and method the RMSE's mean and sd over the seeds; per vehicle the paired
    differences (:data:`PAIRS`); per SL method the detection pooled over seeds and vehicles."""
    vehicles = sorted({v for s in per_seed for v in s["rmse"]}, key=lambda v: (len(v), v))
    rmse: dict = {}
    paired: dict = {}
    for vid in vehicles:
        for m in METHODS:
            vals = np.array([s["rmse"][vid][m] for s in per_seed if m in s["rmse"].get(vid, {})])
            if len(vals):
                rmse.setdefault(vid, {})[m] = {"mean_m": float(vals.mean()),
                                               "sd_m": float(vals.std(ddof=1)) if len(vals) > 1 else 0.0,
                                               "n_seeds": len(vals)}
        for a, b in PAIRS:
            both = [s for s in per_seed if {a, b} <= set(s["rmse"].get(vid, {}))]
            x = np.array([s["rmse"][vid][a] for s in both])
            y = np.array([s["rmse"][vid][b] for s in both])
            paired.setdefault(vid, {})[f"{a} - {b}"] = paired_difference(x, y)
    detection: dict = {}
    for s in per_seed:
        for ms in s["first_stopped"].values():
            for m, d in ms.items():
                acc = detection.setdefault(m, {"truth_s": 0.0, "claimed_s": 0.0, "wrong_s": 0.0, "covered_s": 0.0})
                for k in acc:
                    acc[k] += d[k]
    for acc in detection.values():
        acc["precision"] = 1.0 - acc["wrong_s"] / acc["claimed_s"] if acc["claimed_s"] else None
        acc["recall"] = acc["covered_s"] / acc["truth_s"] if acc["truth_s"] else None
    order = {f"{a} <= {b}": [v for v in vehicles if rmse[v].get(a, {}).get("mean_m", np.inf)
                             > rmse[v].get(b, {}).get("mean_m", -np.inf)] for a, b in PAIRS}
    out = {"vehicles": vehicles, "rmse": rmse, "paired": paired, "first_stopped": detection,
           "not_ordered": order}
    if per_seed and all("bound" in s for s in per_seed):
        out["bound"] = _bound_summary(per_seed, vehicles)
    return out


def _bound_summary(per_seed: list[dict], vehicles: list[str]) -> dict:
    """Window -> vehicle -> method -> the RMSE's and the bound's means over the seeds, their
    ratio, and the window's ANEES over every estimate of every seed with its band (as the fleet
    study's, :func:`deploy.study._window_anees`)."""
    from .study import _window_anees

    out: dict = {}
    for w in BOUND_WINDOWS:
        for vid in vehicles:
            for m in METHODS:
                cells = [s["bound"][w][vid][m] for s in per_seed if m in s["bound"].get(w, {}).get(vid, {})]
                if not cells:
                    continue
                rmse = float(np.mean([c["rmse_m"] for c in cells]))
                bound = float(np.mean([c["bound_rms_m"] for c in cells]))
                out.setdefault(w, {}).setdefault(vid, {})[m] = {
                    "mean_rmse_m": rmse, "bound_rms_m": bound, "ratio": rmse / bound if bound > 0 else None,
                    "anees": _window_anees(cells), "n_seeds": len(cells)}
    return out


def study_markdown(study: dict, title: str) -> str:
    """The study as a markdown page: the ordering check, the detection, a row per vehicle."""
    s = study["summary"]
    n = len(study["seeds"])
    lines = [f"# {title}", "", f"{n} seeds ({study['seeds'][0]}–{study['seeds'][-1]}), in process "
             "(`slcp scenario study`); RMSE [m] over the times each vehicle is on the air, mean ± sd over the seeds.",
             ""]
    for pair, bad in s["not_ordered"].items():
        lines.append(f"- mean RMSE {pair}: " + ("every vehicle" if not bad else f"not for {', '.join(bad)}"))
    for m, d in sorted(s["first_stopped"].items()):
        p = "–" if d["precision"] is None else f"{d['precision']:.4f}"
        r = "–" if d["recall"] is None else f"{d['recall']:.4f}"
        lines.append(f"- first stopped, {m}: precision {p}, recall {r} (truly first {d['truth_s']:.0f} s, "
                     f"claimed {d['claimed_s']:.0f} s, wrong {d['wrong_s']:.1f} s, pooled over seeds and vehicles)")
    lines += ["", "| vehicle | " + " | ".join(METHODS) + " | CP − SP | SL-CP − CP |",
              "|---|" + "---|" * (len(METHODS) + 2)]
    for vid in s["vehicles"]:
        cells = [f"{s['rmse'][vid][m]['mean_m']:.2f} ± {s['rmse'][vid][m]['sd_m']:.2f}" if m in s["rmse"][vid] else "–"
                 for m in METHODS]
        diffs = []
        for pair in ("CP - SP", "SL-CP - CP"):
            d = s["paired"][vid][pair]
            diffs.append("–" if d["mean_m"] is None else f"{d['mean_m']:+.2f} ({d['verdict']})")
        lines.append(f"| {vid} | " + " | ".join(cells) + " | " + " | ".join(diffs) + " |")
    if "bound" in s:
        lines += _bound_markdown(s["bound"])
    return "\n".join(lines) + "\n"


def _bound_markdown(bound: dict) -> list[str]:
    """The bound's tables: per window, vehicle and method the RMSE over the bound (means over the
    seeds) and the ANEES (n = 2; marked when outside its two-sided 95 % band)."""
    lines = ["", "## Against the bound", "",
             "The mean RMSE over the mean posterior CRLB (RMS over the same estimates) and the horizontal "
             "ANEES (n = 2) over every estimate of every seed, marked when outside its 95 % band; "
             "*standing*: the times each vehicle truly stands."]
    for w, cells in bound.items():
        lines += ["", f"### {w}", "", "| vehicle | " + " | ".join(METHODS) + " |", "|---|" + "---|" * len(METHODS)]
        for vid, ms in cells.items():
            row = []
            for m in METHODS:
                c = ms.get(m)
                if c is None or c["ratio"] is None:
                    row.append("–")
                    continue
                a = c["anees"]
                mark = "" if a is None or a["inside"] else " (outside)"
                row.append(f"{c['ratio']:.2f}× ({c['mean_rmse_m']:.2f} / {c['bound_rms_m']:.2f} m)"
                           + ("" if a is None else f", ANEES {a['anees']:.2f}{mark}"))
            lines.append(f"| {vid} | " + " | ".join(row) + " |")
    return lines


def write_study(study: dict, out: Path, title: str) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    (out / "study.json").write_text(json.dumps(study, indent=1))
    (out / "report.md").write_text(study_markdown(study, title))
    return out / "report.md"
