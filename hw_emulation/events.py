"""Event times and evaluation windows computed from a scenario's truth."""

from __future__ import annotations

import math

import numpy as np

from slcp.geo import earth

from .scenario import EventSpec
from .truth import ScenarioTruth


def _first(t: np.ndarray, mask: np.ndarray) -> float:
    idx = np.flatnonzero(mask)
    return float(t[idx[0]]) if idx.size else math.nan


def event_time(truth: ScenarioTruth, ev: EventSpec) -> float:
    """Time [s] of an event (NaN if it never happens within the scenario)."""
    scn = truth.scenario
    if ev.kind == "time":
        return float(ev.time)
    if ev.kind == "end":
        return float(scn.duration)
    if ev.kind == "green":
        t = truth.traffic.t
        g = np.array([scn.signals.is_green(ev.lane, x) for x in t])
        return _first(t[1:], g[1:] & ~g[:-1])
    vt = truth.vehicles[ev.vehicle]
    t = vt.truth.t
    if ev.kind == "first_stopped":
        return _first(t, vt.first_stopped)
    if ev.kind == "stopped":  # first moving -> stopped transition
        s = vt.stopped
        return _first(t[1:], s[1:] & ~s[:-1])
    if ev.kind == "moving":
        s = vt.stopped
        return _first(t[1:], ~s[1:] & s[:-1])
    if ev.kind == "passes_stop_line":
        route = truth.traffic.routes[ev.vehicle]
        stop = route.next_stop_line(float(vt.arc[0]))
        return _first(t, vt.arc >= stop.s1) if stop is not None else math.nan
    if ev.kind == "near":
        a, b = vt.truth.llh, truth.vehicles[ev.other].truth.llh
        rm, rn = earth.radii(float(a[0, 0]))
        dn = (a[:, 0] - b[:, 0]) * rm
        de = (a[:, 1] - b[:, 1]) * rn * np.cos(a[:, 0])
        return _first(t, np.hypot(dn, de) < ev.distance)
    raise ValueError(f"unknown event kind {ev.kind!r}")


def event_times(truth: ScenarioTruth) -> dict[str, float]:
    """All named events of the scenario, in the order defined."""
    return {ev.name: event_time(truth, ev) for ev in truth.scenario.events}


def window_bounds(truth: ScenarioTruth, times: dict[str, float] | None = None) -> dict[str, tuple[float, float]]:
    """Evaluation windows ``name -> (start, end)`` [s]."""
    times = times if times is not None else event_times(truth)
    return {w: (times[a], times[b]) for w, (a, b) in truth.scenario.windows.items()}
