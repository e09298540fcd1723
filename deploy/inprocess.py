"""All vehicles and methods of a scenario in one process, in lockstep on sensor time.

The vehicles run the engine a vehicle computer runs (:class:`agent.engine.VehicleEngine`), fed
the emulator's own messages (:class:`hw_emulation.playback.SensorPlayback`) and each other's
beacons through the emulator's V2V radio (:class:`hw_emulation.playback.Radio`); only the bus is
missing. Every sensor event is handed to the engines in sensor-time order, after the beacons the
radio has delivered by then; the estimates the engines send (10 Hz) are scored against the truth.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from slcp.agent.engine import VehicleEngine
from slcp.agent.methods import DEFAULT_FUSION, METHODS
from slcp.geo import earth
from slcp.hw_emulation.playback import Radio, SensorPlayback
from slcp.hw_emulation.truth import ScenarioTruth
from slcp.transport.messages import Beacon, Estimate, Message

from .agent_configs import agent_config

#: the common record grid [s]: the engines' estimate period
RECORD_PERIOD = 0.1


@dataclass
class RunResult:
    t: np.ndarray
    err: dict[tuple[str, str], np.ndarray]  #: (vehicle, method) -> horizontal error [m]
    sigma: dict[tuple[str, str], np.ndarray]
    first: dict[tuple[str, str], np.ndarray]  #: detector decisions at the record times
    counters: dict[tuple[str, str], dict[str, int]] = field(default_factory=dict)
    decisions: list[tuple[float, str, str, str]] = field(default_factory=list)  #: (t, vehicle, method, reason)
    #: (vehicle, method) -> signed along-track error [m] (truth heading)
    along: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    #: method -> injected error kind ("clean", "nlos", "outlier") -> range outcome -> count
    range_outcomes: dict[str, dict[str, dict[str, int]]] = field(default_factory=dict)
    #: (vehicle, method) -> horizontal NEES at the record times (n = 2)
    nees: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    #: (vehicle, method) -> horizontal error (north, east) [m], shape (n, 2), and the reported
    #: horizontal covariance [m²], shape (n, 2, 2), at the record times
    err_ne: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    cov_ne: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)


def run_inprocess(truth: ScenarioTruth, seed: int, methods: tuple[str, ...] = METHODS,
                  fusion: str = DEFAULT_FUSION,
                  on_message: Callable[[str, Message], None] | None = None,
                  on_output: Callable[[str, Message], None] | None = None) -> RunResult:
    """One seeded run of every vehicle's engine. ``on_message(vehicle, msg)`` sees every message
    handed to an engine, in order, and ``on_output(vehicle, msg)`` every message an engine sends
    (to play the same run to another host and compare)."""
    scn = truth.scenario
    playback = SensorPlayback(truth, seed)
    radio = Radio(truth, seed)
    ids = playback.ids
    engines = {vid: VehicleEngine(agent_config(scn, vid, methods, fusion)) for vid in ids}
    estimates: dict[tuple[str, str], list[Estimate]] = {(v, m): [] for v in ids for m in methods}
    range_outcomes: dict[str, dict[str, dict[str, int]]] = {}
    kinds = _injected_kinds(playback)
    for vid, eng in engines.items():
        eng.range_observer = _tally(vid, kinds, range_outcomes)
    now = float(truth.vehicles[ids[0]].truth.t[0])

    def route(vid: str) -> None:
        """What engine ``vid`` sent: beacons into the radio, estimates to the score."""
        for out in engines[vid].take_outbox():
            if on_output is not None:
                on_output(vid, out)
            if isinstance(out, Beacon):
                radio.send(out, out, now)
            elif isinstance(out, Estimate):
                estimates[(vid, out.method)].append(out)

    def deliver(vid: str, msg: Message) -> None:
        if on_message is not None:
            on_message(vid, msg)
        engines[vid].handle(msg)
        route(vid)

    for now, messages in playback.messages():
        for _, rx, beacon in radio.due(now):
            deliver(rx, beacon)
        for msg in messages:
            deliver(msg.vehicle, msg)
    for vid, eng in engines.items():  # what the engines still hold back
        eng.finish()
        route(vid)
    decisions = sorted((t, vid, m, why) for vid, eng in engines.items() for t, m, why in eng.decision_log)
    counters = {(vid, m): dict(f.counters) for vid, eng in engines.items() for m, f in eng.filters.items()}
    return _score(truth, estimates, counters, decisions, range_outcomes)


def _injected_kinds(playback: SensorPlayback) -> dict[tuple[frozenset, float], str]:
    """(pair, range time) -> the error the emulator injected: "clean", "nlos" or "outlier"."""
    out = {}
    for (a, b), rr in playback.ranges.items():
        for i in np.flatnonzero(np.isfinite(rr.range)):
            kind = "outlier" if rr.outlier[i] else "nlos" if rr.nlos[i] else "clean"
            out[(frozenset((a, b)), float(rr.t[i]))] = kind
    return out


def _tally(vid: str, kinds: dict, outcomes: dict[str, dict[str, dict[str, int]]]):
    def observe(method: str, other: str, t: float, outcome: str | None) -> None:
        kind = kinds.get((frozenset((vid, other)), t), "clean")
        tally = outcomes.setdefault(method, {}).setdefault(kind, {})
        tally[outcome] = tally.get(outcome, 0) + 1
    return observe


def _score(truth: ScenarioTruth, estimates: dict[tuple[str, str], list[Estimate]], counters: dict,
           decisions: list, range_outcomes: dict) -> RunResult:
    """Each (vehicle, method)'s estimates against the truth at their own times, held on a
    common grid of ``RECORD_PERIOD`` (the latest estimate at or before each grid time)."""
    firsts = [es[0].t for es in estimates.values() if es]
    lasts = [es[-1].t for es in estimates.values() if es]
    if not firsts or len(firsts) < len(estimates):
        raise ValueError("a vehicle sent no estimate: its filters never started")
    # vehicles that come and go (external trajectories): the union of their spans, NaN where a
    # vehicle is off the air; else the span every vehicle has estimates in
    coming_and_going = any(v.present is not None for v in truth.vehicles.values())
    grid = (np.arange(min(firsts), max(lasts) + 1e-9, RECORD_PERIOD) if coming_and_going
            else np.arange(max(firsts), min(lasts) + 1e-9, RECORD_PERIOD))
    res = RunResult(grid, {}, {}, {}, counters, decisions=decisions, range_outcomes=range_outcomes)
    for (vid, m), es in estimates.items():
        vt = truth.vehicles[vid].truth
        te = np.array([e.t for e in es])
        pick = np.searchsorted(te, grid + 1e-9, side="right") - 1
        off = (pick < 0) | ~truth.vehicles[vid].present_over(grid)
        pick = np.maximum(pick, 0)
        idx = np.clip(np.searchsorted(vt.t, te - 1e-9), 0, len(vt.t) - 1)
        err_ne, cov_ne, along, first = [], [], [], []
        for j in pick.tolist():
            e, k = es[j], int(idx[j])
            d = earth.ned_offset(float(e.llh[0]), float(e.llh[1]), float(e.llh[2]), *vt.llh[k])
            yaw = vt.euler[k, 2]
            err_ne.append((d[0], d[1]))
            along.append(d[0] * math.cos(yaw) + d[1] * math.sin(yaw))
            cov_ne.append(e.cov_pos[:2, :2])
            first.append(e.first_stopped)
        en = np.array(err_ne).reshape(-1, 2)
        cn = np.array(cov_ne).reshape(-1, 2, 2)
        key = (vid, m)
        res.err[key] = np.hypot(en[:, 0], en[:, 1])
        res.sigma[key] = np.sqrt(np.array([e.cov_pos[0, 0] + e.cov_pos[1, 1] for e in es])[pick])
        res.first[key] = np.array(first, bool)
        res.along[key] = np.array(along)
        res.nees[key] = np.einsum("ni,nij,nj->n", en, np.linalg.inv(cn), en)
        res.err_ne[key], res.cov_ne[key] = en, cn
        if off.any():
            for arr in (res.err[key], res.sigma[key], res.along[key], res.nees[key], en):
                arr[off] = np.nan
            res.first[key][off] = False
    return res
