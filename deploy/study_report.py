"""A study's report (``report.md``): the RMSE tables, paired differences, consistency, the
drivers' draws and first-stopped detection of :func:`deploy.study.aggregate`'s statistics."""

from __future__ import annotations

from slcp.agent.methods import METHODS

PAIRS = (("CP", "SP"), ("SL-CP", "SP"), ("SL-CP", "CP"), ("SL-SP", "SP"))


def study_markdown(scn, study: dict) -> str:
    n = len(study["seeds"])
    from .run_report import lane_keeping_label

    lane = lane_keeping_label(study.get("lane_constraint"))
    lines = [f"# slcp study: {scn.name}, {n} seeds, fusion `{study.get('fusion', '?')}`{lane}", "",
             "Horizontal RMSE [m]: mean ± sd over the seeds, the paper's figure in brackets; below, the mean "
             "along-track / cross-track RMSE [m], the posterior CRLB (RMS over the window, mean over the seeds), "
             "the RMSE over it, the share of estimates whose reported σ is below it, and the window's horizontal "
             "ANEES (n = 2) over every estimate of every seed, marked when outside the two-sided 95 % band.", ""]
    failed = study.get("failed_seeds") or {}
    if failed:
        lines += [f"**{len(failed)} seed(s) failed and are left out** (their files: `failed-seed-*`):", ""]
        lines += [f"- seed {s}: {r}" for s, r in sorted(failed.items(), key=lambda kv: int(kv[0]))] + [""]
    lines += _md_rmse(scn, study)
    lines += _md_paired(study)
    lines += _md_anees(study)
    lines += _md_stances(study)
    lines += _md_detection(study)
    return "\n".join(lines)


def _md_rmse(scn, study: dict) -> list[str]:
    """The RMSE tables, one per window."""
    lines: list[str] = []
    for w, table in study["rmse"].items():
        lines += [f"## {w}", "", "| vehicle | " + " | ".join(METHODS) + " |", "|---" * (len(METHODS) + 1) + "|"]
        for vid, cells in table.items():
            row = []
            for m in METHODS:
                c = cells.get(m)
                p = scn.paper_table.get(w, {}).get(vid, {}).get(m)
                row.append(
                    "–"
                    if c is None
                    else f"{c['mean_rmse_m']:.2f} ± {c['sd_rmse_m']:.2f}"
                    + (f" [{p:.2f}]" if p is not None else "")
                    + f"<br>{c['along_rmse_m']:.2f} / {c['cross_rmse_m']:.2f}"
                    + (
                        f"<br>bound {c['bound_rms_m']:.2f}"
                        + (f" (RMSE {c['mean_rmse_m'] / c['bound_rms_m']:.1f}×)" if c["bound_rms_m"] > 0.0 else "")
                        + f", σ<bound {100 * c['sigma_below_bound']:.0f} %"
                        if "bound_rms_m" in c
                        else ""
                    )
                    + (
                        f"<br>ANEES {c['anees']['anees']:.2f}" + ("" if c["anees"]["inside"] else " (outside)")
                        if "anees" in c
                        else ""
                    )
                )
            lines.append(f"| {vid} | " + " | ".join(row) + " |")
        lines.append("")
    return lines


def _md_paired(study: dict) -> list[str]:
    """The paired RMSE differences."""
    lines: list[str] = []
    if study.get("paired"):
        lines += ["## Cooperation against the reference: paired RMSE differences [m]", "",
                  "Mean over the seeds of (method − reference) ± the half-width of its 95 % Student-t "
                  "interval; **better** / **worse**: the whole interval is below / above 0, n.s.: neither.", ""]
        names = [f"{m} - {ref}" for m, ref in PAIRS]
        header = "| vehicle | " + " | ".join(f"{m} − {ref}" for m, ref in PAIRS) + " |"
        for w, table in study["paired"].items():
            lines += [f"### {w}", "", header, "|---" * (len(names) + 1) + "|"]
            for vid, cells in table.items():
                row = []
                for k in names:
                    c = cells.get(k)
                    if c is None:
                        row.append("–")
                        continue
                    if c["mean_m"] is None:
                        row.append("–")
                        continue
                    hw = "" if c["half_width_m"] is None else f" ± {c['half_width_m']:.2f}"
                    v = c["verdict"]
                    row.append(f"{c['mean_m']:+.2f}{hw} " + (f"**{v}**" if v != "n.s." else v))
                lines.append(f"| {vid} | " + " | ".join(row) + " |")
            lines.append("")
    return lines


def _md_anees(study: dict) -> list[str]:
    """The whole-run ANEES per vehicle and method."""
    lines: list[str] = []
    if study["anees"]:
        lo, hi = next(iter(study["anees"].values()))["band"]
        n = len(study["seeds"])
        lines += [f"## Consistency: horizontal ANEES (n = 2), 95 % band for {n} runs: {lo:.2f}–{hi:.2f}", "",
                  "| vehicle/method | ANEES | inside |", "|---|---|---|"]
        lines += [f"| {k} | {a['anees']:.2f} | {'yes' if a['inside'] else 'no'} |" for k, a in study["anees"].items()]
        lines.append("")
    return lines


def _md_stances(study: dict) -> list[str]:
    """How spread the drivers' draws are."""
    lines: list[str] = []
    if study.get("stance_draws"):
        b1, b2 = (next(iter(study["stance_draws"].values()))[k]["band"] for k in ("stop_gap", "both"))
        lines += ["## The drivers' draws", "",
                  "Mean over the seeds of z², the deviation of each driver's stop gap d_s and lateral offset d_l "
                  "from the scenario's mean in units of its σ, beside the 95 % band of as many draws "
                  f"({b1[0]:.2f}–{b1[1]:.2f}; for the sum {b2[0]:.2f}–{b2[1]:.2f}). The sum is the ANEES of an "
                  "estimator whose error were exactly the two draws. A column outside its band: these seeds "
                  "drew the stances more (or less) spread than the model, and where that error dominates (standing "
                  "first at a line, keeping to a lane) a consistent filter's ANEES is expected outside its band too.",
                  "", "| vehicle | d_s | d_l | sum |", "|---|---|---|---|"]
        for vid, c in study["stance_draws"].items():
            lines.append(
                f"| {vid} | "
                + " | ".join(
                    f"{c[k]['mean_z2']:.2f}" + ("" if c[k]["inside"] else " (outside)")
                    for k in ("stop_gap", "lateral", "both")
                )
                + " |"
            )
        lines.append("")
    return lines


def _md_detection(study: dict) -> list[str]:
    """First-stopped detection pooled over the seeds."""
    lines: list[str] = []
    if study["first_stopped"]:
        lines += ["## First-stopped detection (pooled over the seeds)", "",
                  "SL RMSE: the stop-line method's horizontal error while the vehicle is truly first stopped, "
                  "over the whole time (detection latency included) and over the claimed part, RMS over the seeds.", "",
                  "| vehicle/method | truly first [s] | claimed [s] | wrong [s] | precision | recall "
                  "| latency mean / max [s] | SL RMSE whole / claimed [m] |", "|---|---|---|---|---|---|---|---|"]
        for k, a in study["first_stopped"].items():
            def f(x, fmt="{:.3f}"):
                return "–" if x is None else fmt.format(x)

            lines.append(
                f"| {k} | {a['truth_s']:.1f} | {a['claimed_s']:.1f} | {a['wrong_s']:.1f} | {f(a['precision'])} "
                f"| {f(a['recall'])} | {f(a['mean_latency_s'], '{:.2f}')} / {f(a.get('max_latency_s'), '{:.2f}')} "
                f"| {f(a.get('sl_rmse_truth_first_m'), '{:.2f}')} / {f(a.get('sl_rmse_claimed_m'), '{:.2f}')} |"
            )
        lines.append("")
    return lines
