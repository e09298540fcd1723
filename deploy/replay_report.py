"""A replay's report (``report.md`` in its output folder): the command that made it, the outage
metrics, the phases with ``--phases``, and, with ``--compare``, another filter's figures on the
same protocol beside ours.

A comparison is a TOML file of figures measured elsewhere (another filter run on the same
recording and protocol); it is read, never computed here::

    name = "the data authors' filter with its NHC"
    source = "how and where these figures were measured"

    [[phase]]
    first_outage_s = 40.0        # the protocol's first outage after t0 [s]
    outage_h_rms_m = 2.42
    outage_h_end_mean_m = 4.81
    outage_h_max_m = 10.31       # optional, as are the other two metrics

A phase of the comparison is matched to ours by its first outage (to the millisecond).
"""

from __future__ import annotations

import argparse
import math
import shlex
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

#: the metrics a comparison may give for a phase, and their row names
METRICS = (("outage_h_rms_m", "outage horizontal RMS"), ("outage_h_end_mean_m", "end-of-outage mean"),
           ("outage_h_max_m", "outage maximum"))
_KEYS = frozenset(("first_outage_s", *(k for k, _ in METRICS)))


@dataclass(frozen=True)
class Comparison:
    """Another filter's outage figures on the same recording and protocol, by phase."""

    name: str
    source: str = ""
    #: first outage after t0 [s] -> metric name -> value [m]
    phases: dict[float, dict[str, float]] = field(default_factory=dict)

    def at(self, first_outage_s: float | None) -> dict[str, float]:
        """Its figures at the phase whose first outage is ``first_outage_s`` (empty: none)."""
        if first_outage_s is None:
            return {}
        for first, figures in self.phases.items():
            if abs(first - first_outage_s) < 1e-3:
                return figures
        return {}


def load_comparison(path: Path) -> Comparison:
    """Read a comparison file; a clear ``ValueError`` for anything that is not one."""
    try:
        doc = tomllib.loads(Path(path).read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--compare {path}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    name = doc.get("name")
    if not isinstance(name, str) or not name.strip():
        raise ValueError(f"{path}: a comparison needs a name (the filter the figures are of)")
    source = doc.get("source", "")
    if not isinstance(source, str):
        raise ValueError(f"{path}: source must be a string")
    unknown = set(doc) - {"name", "source", "phase"}
    if unknown:
        raise ValueError(f"{path}: unknown keys {sorted(unknown)} (name, source, [[phase]])")
    rows = doc.get("phase", [])
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"{path}: a comparison needs at least one [[phase]] table")
    phases: dict[float, dict[str, float]] = {}
    for k, row in enumerate(rows):
        where = f"{path}: phase {k + 1}"
        if not isinstance(row, dict) or "first_outage_s" not in row:
            raise ValueError(f"{where}: needs first_outage_s")
        if set(row) - _KEYS:
            raise ValueError(f"{where}: unknown keys {sorted(set(row) - _KEYS)}")
        values = {}
        for key, val in row.items():
            if isinstance(val, bool) or not isinstance(val, int | float) or not math.isfinite(val) or val < 0:
                raise ValueError(f"{where}: {key} must be a non-negative number, got {val!r}")
            values[key] = float(val)
        first = values.pop("first_outage_s")
        if any(abs(first - f) < 1e-3 for f in phases):
            raise ValueError(f"{where}: a second phase at first_outage_s = {first:g}")
        phases[first] = values
    return Comparison(name.strip(), source.strip(), phases)


def replay_command(args: argparse.Namespace) -> str:
    """The ``slcp replay`` command line of ``args``, its non-default options only."""
    from .replay import OutageProtocol

    default = OutageProtocol()  # the protocol's defaults, which the command line's are
    parts = ["slcp", "replay", args.format, str(args.path)]
    if args.vehicle is not None:
        parts += ["--vehicle", str(args.vehicle)]
    if args.no_outage:
        parts.append("--no-outage")
    elif tuple(args.outage) != (default.length, default.period - default.length):
        parts += ["--outage", f"{args.outage[0]:g}:{args.outage[1]:g}"]
    if args.first_outage != default.first:
        parts += ["--first-outage", f"{args.first_outage:g}"]
    if args.end_margin != default.end_margin:
        parts += ["--end-margin", f"{args.end_margin:g}"]
    if args.phases != 1:
        parts += ["--phases", str(args.phases)]
    for flag in ("no_nhc", "no_zupt", "no_time_offset_estimation"):
        if getattr(args, flag):
            parts.append("--" + flag.replace("_", "-"))
    if args.imu_time_offset is not None:
        parts += ["--imu-time-offset", f"{args.imu_time_offset:g}"]
    if getattr(args, "compare", None) is not None:
        parts += ["--compare", str(args.compare)]
    parts += ["--out", str(args.out)]
    return " ".join(shlex.quote(p) for p in parts)


def _m(x: float | None) -> str:
    return "" if x is None else f"{x:.2f}"


def replay_report(command: str, metrics: dict, other: Comparison | None = None, title: str = "SP replay") -> str:
    """The report of one replay (``metrics``: its ``metrics.json``, with ``phases_pooled`` when
    it ran several phases) as Markdown, with ``other``'s figures beside."""
    cfg = metrics.get("config", {})
    prof, outage = cfg.get("profile", {}), cfg.get("outage", {})
    pooled = metrics.get("phases_pooled")
    phases = pooled["phases"] if pooled else [{"first_outage_s": outage.get("first"), **metrics}]
    lines = [f"# {title}", "", f"`{command}`", ""]
    if metrics["n_outages"]:
        protocol = (f"{metrics['n_outages']} GNSS outages of {outage.get('length', 0):g} s every "
                    f"{outage.get('period', 0):g} s, the first {outage.get('first', 0):g} s after the first fix "
                    f"({metrics['n_withheld_fixes']} fixes withheld); the estimates are scored at the antenna "
                    "against the withheld fixes")
    else:
        protocol = "no GNSS outage: every fix is used, and each scores the estimate before its update"
    lines.append(
        f"Vehicle profile: {prof.get('name', '?')}. {metrics['imu_span_s']:.0f} s of IMU; {protocol}. The "
        f"estimated IMU time offset: {metrics['imu_time_offset_s']:+.3f} s. The filter loop took "
        f"{metrics['wall_s']:.2f} s ({metrics['realtime_factor']:.0f}× real time) on the machine that wrote this.")
    lines.append("")
    ref0 = other.at(outage.get("first")) if other is not None else {}
    head = "| metric [m] | slcp |" + (f" {other.name} |" if other is not None else "")
    lines += [head, "|---|---|" + ("---|" if other is not None else "")]
    rows = [*METRICS[:2], ("outage_h_end_max_m", "end-of-outage maximum"), METRICS[2],
            ("gnss_on_h_rms_m", "RMS with GNSS on")]
    for key, label in rows:
        ours = metrics.get(key)
        if (ours is None or not math.isfinite(ours)) and key not in ref0:
            continue  # not measured (no outage) and not compared
        cell = f"| {label} | {_m(ours)} |"
        lines.append(cell + (f" {_m(ref0.get(key))} |" if other is not None else ""))
    if pooled:
        lines += ["", f"## The protocol at {pooled['n_phases']} phases", "",
                  "The same outages started at other times of the drive: the first outage at FIRST + k·period/N.", ""]
        ref_cols = other is not None
        head = "| first outage [s] | outages | RMS | end mean | end max | max |"
        lines += [head + (" compared: RMS / end mean |" if ref_cols else ""),
                  "|---|---|---|---|---|---|" + ("---|" if ref_cols else "")]
        wins = compared = 0
        for ph in phases:
            row = (f"| {ph['first_outage_s']:g} | {ph['n_outages']} | {_m(ph['outage_h_rms_m'])} | "
                   f"{_m(ph['outage_h_end_mean_m'])} | {_m(ph['outage_h_end_max_m'])} | {_m(ph['outage_h_max_m'])} |")
            if ref_cols:
                r = other.at(ph["first_outage_s"]) if other is not None else {}
                row += f" {_m(r.get('outage_h_rms_m'))} / {_m(r.get('outage_h_end_mean_m'))} |"
                if "outage_h_rms_m" in r and "outage_h_end_mean_m" in r:
                    compared += 1
                    wins += (ph["outage_h_rms_m"] < r["outage_h_rms_m"]
                             and ph["outage_h_end_mean_m"] < r["outage_h_end_mean_m"])
            lines.append(row)
        lines.append(f"| pooled | {pooled['n_outages']} | {_m(pooled['outage_h_rms_m'])} | "
                     f"{_m(pooled['outage_h_end_mean_m'])} | {_m(pooled['outage_h_end_max_m'])} | "
                     f"{_m(pooled['outage_h_max_m'])} |" + (" |" if ref_cols else ""))
        if compared:
            lines += ["", f"slcp has the lower RMS and end mean at {wins} of the {compared} phases the "
                          "comparison gives."]
    if other is not None:
        lines += ["", f"Compared with {other.name}." + (f" {other.source}" if other.source else "")]
    return "\n".join(lines) + "\n"
