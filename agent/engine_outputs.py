"""What the vehicle engine sends, on sensor-time timers: beacons (5 Hz), estimates (10 Hz),
first-stopped decisions (10 Hz) and diagnostics (1 Hz) (:class:`EngineOutputs`, one part of
:class:`agent.engine.VehicleEngine`)."""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable

from slcp.transport.messages import Beacon, Diagnostics, Estimate, Message

from .engine_config import AgentConfig
from .first_stopped import StopTracker
from .methods import MethodFilter
from .misbehaviour import MisbehaviourDetector
from .nav.rotation import quat_to_euler
from .neighbours import NeighbourTable
from .sequencer import Sequencer


def _next_tick(due: float, period: float, t: float) -> float:
    """The first tick of the ``period`` grid through ``due`` after ``t``: after a gap in the
    data, the timers skip the ticks they missed instead of catching up one per IMU sample."""
    nxt = due + period
    if nxt <= t:
        nxt = due + period * (math.floor((t - due) / period) + 1)
    return nxt


class EngineOutputs:
    """The engine's timers and the messages they send to its ``outbox``."""

    cfg: AgentConfig
    outbox: list[Message]
    filters: dict[str, MethodFilter]
    tables: dict[str, NeighbourTable]
    trackers: dict[str, StopTracker]
    decision_reason: dict[str, str]
    counters: dict[str, int]
    seq: Sequencer
    misbehaviour: MisbehaviourDetector | None
    lost: dict[str, tuple[float, str]]
    departures: deque
    beacons_from: dict[str, int]
    MAX_LOST: int
    extra_counters: Callable[[], dict[str, int]] | None
    _next: dict[str, float | None]
    _timer_due: float
    _beacon_seq: int

    def claim(self, method: str) -> bool:
        """Whether ``method``'s filter currently claims "first stopped"."""
        tr = self.trackers.get(method)
        return tr is not None and tr.claim

    def _decide(self, t: float) -> None:  # the engine's first-stopped decisions
        raise NotImplementedError

    # ----------------------------------------------------------------- sensor-time timers
    def _timers(self, t: float) -> None:
        try:
            self._run_timers(t)
        finally:
            self._timer_due = min((v for v in self._next.values() if v is not None), default=math.inf)

    def _run_timers(self, t: float) -> None:
        due = self._next
        if due["decision"] is not None and t >= due["decision"]:
            due["decision"] = _next_tick(due["decision"], 1.0 / self.cfg.decision_rate, t)
            self._decide(t)
        if due["beacon"] is not None and t >= due["beacon"]:
            due["beacon"] = _next_tick(due["beacon"], 1.0 / self.cfg.beacon_rate, t)
            self._send_beacons(t)
        if due["estimate"] is not None and t >= due["estimate"]:
            due["estimate"] = _next_tick(due["estimate"], 1.0 / self.cfg.estimate_rate, t)
            self._send_estimates(t)
        if due["diag"] is not None and t >= due["diag"]:
            due["diag"] = _next_tick(due["diag"], 1.0, t)
            self.outbox.append(self.diagnostics(t))

    def _send_beacons(self, t: float) -> None:
        self._beacon_seq += 1
        for m, f in self.filters.items():
            if f.spec.ranges or f.spec.stop_line:
                llh, v, cov = f.beacon()
                self.outbox.append(Beacon(self.cfg.vehicle, self._beacon_seq, m, t, llh, v, cov,
                                          first_stopped=self.claim(m), sources=f.beacon_sources(),
                                          constants=f.beacon_constants()))
                self.counters["beacons_tx"] += 1

    def _send_estimates(self, t: float) -> None:
        for m, f in self.filters.items():
            s = f.filter.state
            # stamped in GNSS time: the IMU's time stamps lag it by the estimated offset
            self.outbox.append(Estimate(self.cfg.vehicle, m, t + f.time_offset, s.llh.copy(), s.v.copy(),
                                        quat_to_euler(s.q), f.position_cov, self.claim(m)))
            self.counters["estimates_tx"] += 1

    def diagnostics(self, t: float) -> Diagnostics:
        """The counters (flat, ``<part>_<name>``) and the neighbour status at sensor time ``t``."""
        counters = dict(self.counters)
        counters.update({f"seq_{k}": v for k, v in self.seq.counters.items()})
        for m, tab in self.tables.items():
            counters.update({f"{m}_{k}": v for k, v in tab.counters.items()})
        for m, f in self.filters.items():
            counters.update({f"{m}_{k}": v for k, v in f.counters.items()})
        if self.extra_counters is not None:
            counters.update(self.extra_counters())
        mb = self.misbehaviour
        status = {"t": t, "neighbours": len(set().union(*(tab.vehicles() for tab in self.tables.values()))),
                  "first_stopped": [m for m in self.trackers if self.claim(m)],
                  # why each stop-line method claims or does not (its latest decision)
                  "decisions": dict(self.decision_reason),
                  "lost": {v: [lt, how] for v, (lt, how) in self.lost.items()},
                  "departures": [list(d) for d in self.departures],
                  # verified beacons per sender (the most frequent, within the codec's map limit)
                  "beacons_from": dict(sorted(self.beacons_from.items(), key=lambda kv: -kv[1])[:self.MAX_LOST]),
                  "flagged": {v: [ft, why] for v, (ft, why) in mb.flagged.items()} if mb else {}}
        if mb:
            counters.update({f"mb_{k}": v for k, v in mb.counters.items()})
        return Diagnostics(self.cfg.vehicle, t, counters, status)
