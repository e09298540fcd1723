"""A stand-in for the engine, for benchmarks: an agent process's cost without its estimation.

:class:`StandInEngine` runs the real engine until it has sent its first beacon and its first
estimate, then estimates nothing: it counts every message it is given, and on each of its own
IMU batches sends the beacons, estimates and diagnostics due by the batch's last sample, at the
engine's rates, as copies of the latest ones the engine sent, restamped (beacons with their
sequence numbers going on). The fleet around it sees the same traffic (the same messages, of the
same sizes, at the same times) from an agent whose estimation costs nothing; what such a fleet
costs is the floor that a faster engine cannot go below: the processes, Zenoh, the codec, the
emulated hardware and the launcher (``slcp bench --fleet-engine stand-in``).
"""

from __future__ import annotations

import dataclasses

from slcp.transport.messages import Beacon, Estimate, ImuBatch, Message

from .engine import VehicleEngine
from .engine_config import AgentConfig

#: rate of the diagnostics while standing in [Hz] (the engine's)
DIAGNOSTICS_RATE = 1.0


class StandInEngine(VehicleEngine):
    """The engine until its first beacon and estimate; then copies at the engine's rates.

    ``counters["stand_in_inputs"]`` counts the messages taken while standing in. With several
    methods, the beacons and estimates re-sent are those of the methods that had sent one when
    the engine stopped (every method sends its first at the same timer tick).
    """

    def __init__(self, cfg: AgentConfig) -> None:
        super().__init__(cfg)
        self._beacons: dict[str, Beacon] = {}
        self._estimates: dict[str, Estimate] = {}
        self._standing_in = False
        self._due: dict[str, float] = {}
        self._seq = 0
        self._t_last: float | None = None
        self._estimate_base = 0.0
        self.counters["stand_in_inputs"] = 0

    @property
    def standing_in(self) -> bool:
        """Whether the engine has stopped estimating."""
        return self._standing_in

    def handle(self, msg: Message) -> None:
        if not self._standing_in:
            super().handle(msg)
            for m in self.outbox:  # the latest of each: the copies follow on from them
                if isinstance(m, Beacon):
                    self._beacons[m.method] = m
                elif isinstance(m, Estimate):
                    self._estimates[m.method] = m
            if self._beacons and self._estimates:
                self._stand_in()
            return
        self.counters["stand_in_inputs"] += 1
        if type(msg) is not ImuBatch or msg.vehicle != self.cfg.vehicle or not len(msg.t):
            return
        t = float(msg.t[-1])
        if self._t_last is not None and t <= self._t_last:
            return
        self._t_last = t
        self._send_due(t)

    def finish(self) -> None:
        if not self._standing_in:
            super().finish()
        elif self._t_last is not None:
            self.outbox.append(self.diagnostics(self._t_last))

    def _stand_in(self) -> None:
        self._standing_in = True
        self._seq = max(b.seq for b in self._beacons.values())
        b_t = max(b.t for b in self._beacons.values())
        # estimates are stamped in GNSS time (the IMU's plus the estimated offset, which now
        # stands still): the copies keep their stamps' offsets to the latest one's
        self._estimate_base = max(e.t for e in self._estimates.values())
        self._due = {"beacon": b_t + 1.0 / self.cfg.beacon_rate,
                     "estimate": self._estimate_base + 1.0 / self.cfg.estimate_rate,
                     "diag": b_t + 1.0 / DIAGNOSTICS_RATE}

    def _send_due(self, t: float) -> None:
        due = self._due
        while t >= due["beacon"]:
            self._seq += 1
            for b in self._beacons.values():
                self.outbox.append(dataclasses.replace(b, seq=self._seq, t=due["beacon"]))
            due["beacon"] += 1.0 / self.cfg.beacon_rate
        while t >= due["estimate"]:
            for e in self._estimates.values():
                self.outbox.append(dataclasses.replace(e, t=due["estimate"] + (e.t - self._estimate_base)))
            due["estimate"] += 1.0 / self.cfg.estimate_rate
        while t >= due["diag"]:
            self.outbox.append(self.diagnostics(due["diag"]))
            due["diag"] += 1.0 / DIAGNOSTICS_RATE
