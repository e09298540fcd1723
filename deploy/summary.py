"""The terminal summary of a run: a compact plain table (the markdown stays in ``report.md``)."""

from __future__ import annotations

import math

from slcp.agent.methods import METHODS

from .study import anees_band

#: a single run's window: its errors are correlated over the whole window, so its mean
#: horizontal NEES is treated as one 2-degree-of-freedom draw (a study of one run); outside this
#: two-sided 95 % band a filter is flagged as over- or under-confident
NEES_BAND = anees_band(1)


def _cell(c: dict | None, paper: float | None) -> str:
    if c is None:
        return "–"
    text = f"{c['rmse_m']:.2f}" + (f" [{paper:.2f}]" if paper is not None else "")
    nees = c.get("nees_h")
    if nees is not None and math.isfinite(nees) and not NEES_BAND[0] <= nees <= NEES_BAND[1]:
        text += " !"
    return text


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    return ["  ".join(x.ljust(w) for x, w in zip(r, widths)).rstrip() for r in [header, *rows]]


def terminal_summary(scn, metrics: dict, report_path) -> str:
    """Horizontal RMSE per window, vehicle and method beside the paper's figure, a ``!`` where
    the mean NEES is outside :data:`NEES_BAND`, first-stopped detection in one line per claim,
    and where the full report is."""
    methods = [m for m in METHODS if any(m in cells for t in metrics["rmse"].values() for cells in t.values())]
    lo, hi = NEES_BAND
    out = [f"{scn.name}, seed {metrics.get('seed', '?')}: horizontal RMSE [m], the paper's figure in brackets; "
           f"! mean NEES outside [{lo:.2f}, {hi:.1f}]"]
    for w, table in metrics["rmse"].items():
        rows = [[vid] + [_cell(cells.get(m), scn.paper_table.get(w, {}).get(vid, {}).get(m)) for m in methods]
                for vid, cells in sorted(table.items())]
        out += ["", f"window {w}"] + ["  " + line for line in _table(["vehicle", *methods], rows)]
    det = metrics.get("first_stopped", {})
    claims = []
    for vid, ms in sorted(det.items()):
        for m, d in ms.items():
            p, r = d.get("precision"), d.get("recall")
            claims.append(f"{vid} {m} precision {'–' if p is None else f'{p:.3f}'}, "
                          f"recall {'–' if r is None else f'{r:.3f}'}")
    if claims:
        out += ["", "first stopped: " + "; ".join(claims)]
    faults = metrics.get("faults") or []
    restarts = metrics.get("processes", {}).get("restarts", [])
    if faults or restarts:
        out += ["", f"{len(faults)} scheduled faults, {len(restarts)} process restarts (see the report)"]
    out += ["", f"full report: {report_path}"]
    return "\n".join(out)
