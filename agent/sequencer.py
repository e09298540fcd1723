"""Time ordering of measurements against the IMU stream (pure logic, sensor time).

Measurements (GNSS fixes, UWB ranges, ...) arrive over the network in any order and with
latency; the filter can only apply a measurement when its own time has reached the
measurement's time. The sequencer holds measurements in a time-ordered heap and, for each IMU
interval, yields the interval split at every pending measurement time inside it, with the
measurement applied exactly there.

A measurement older than the filter time is *late*: within ``late_tolerance`` it is applied at
once (its time error is below what the models resolve); beyond that it is dropped and counted.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Propagate:
    """Integrate these increments over ``dt`` seconds (a whole or partial IMU interval)."""

    dtheta: tuple[float, float, float]
    dvel: tuple[float, float, float]
    dt: float


@dataclass(frozen=True)
class Apply:
    """Apply a measurement at filter time ``t``."""

    t: float
    kind: str
    payload: Any


@dataclass
class Sequencer:
    """Merges measurements into the IMU stream by sensor time.

    Parameters
    ----------
    late_tolerance : float
        Measurements at most this much older than the filter time are applied late [s].
    max_pending : int
        Bound on buffered measurements; beyond it the oldest is dropped and counted.
    """

    late_tolerance: float = 0.05
    max_pending: int = 10_000
    t: float | None = None
    _heap: list = field(default_factory=list)
    _order: itertools.count = field(default_factory=itertools.count)
    counters: dict[str, int] = field(default_factory=lambda: {"queued": 0, "late_applied": 0,
                                                              "late_dropped": 0, "overflow": 0,
                                                              "imu_gaps": 0, "imu_out_of_order": 0})

    def push(self, t: float, kind: str, payload: Any) -> list[Apply]:
        """Queue a measurement; returns measurements to apply *now* (late but tolerable)."""
        if self.t is not None and t <= self.t:
            if self.t - t <= self.late_tolerance:
                self.counters["late_applied"] += 1
                return [Apply(self.t, kind, payload)]
            self.counters["late_dropped"] += 1
            return []
        heapq.heappush(self._heap, (t, next(self._order), kind, payload))
        self.counters["queued"] += 1
        if len(self._heap) > self.max_pending:
            heapq.heappop(self._heap)
            self.counters["overflow"] += 1
        return []

    def _interval_start(self, t_end: float, dt: float, max_gap: float) -> float | None:
        """Start of the IMU interval ending at ``t_end`` as integrated (None: out of order)."""
        t0 = t_end - dt
        if self.t is not None:
            if t_end <= self.t:
                self.counters["imu_out_of_order"] += 1
                return None
            if t0 - self.t > max_gap:
                self.counters["imu_gaps"] += 1
            elif abs(t0 - self.t) > 1e-9:
                t0 = self.t  # absorb jitter: intervals are contiguous
        return t0

    def gap_before(self, t_end: float, dt: float, max_gap: float = 0.1) -> float:
        """The time without IMU data before the interval ending at ``t_end`` lasting ``dt`` [s]
        (0 when it follows on); :meth:`skip_gap` moves the clock over it."""
        if self.t is None:
            return 0.0
        gap = (t_end - dt) - self.t
        return gap if gap > max_gap else 0.0

    def skip_gap(self, gap: float) -> None:
        """The clock moved over a gap of ``gap`` s that the filters coasted through."""
        if self.t is not None:
            self.t += gap
            self.counters["imu_gaps"] += 1

    def pending_by(self, t: float) -> bool:
        """Whether a queued measurement is due at or before sensor time ``t`` [s]."""
        return bool(self._heap) and self._heap[0][0] <= t

    def imu_plain(self, t_end: float, dt: float, max_gap: float = 0.1) -> float | None:
        """:meth:`imu` for an interval with no queued measurement in it (``pending_by(t_end)``
        is False): advances the clock and returns the length [s] to integrate the whole
        interval's increments over, or None (out of order, or nothing left to integrate)."""
        t0 = self._interval_start(t_end, dt, max_gap)
        if t0 is None:
            return None
        self.t = t_end
        return t_end - t0 if t_end - t0 > 1e-12 else None

    def imu(self, t_end: float, dtheta, dvel, dt: float, max_gap: float = 0.1) -> Iterator[Propagate | Apply]:
        """Steps for one IMU interval ending at ``t_end`` lasting ``dt`` seconds."""
        t0 = self._interval_start(t_end, dt, max_gap)
        if t0 is None:
            return
        th = tuple(float(x) for x in dtheta)
        dv = tuple(float(x) for x in dvel)
        span = t_end - t0
        cur = t0
        done = 0.0  # fraction of the interval already yielded
        while self._heap and self._heap[0][0] <= t_end:
            tm, _, kind, payload = heapq.heappop(self._heap)
            if tm > cur:
                frac = (tm - cur) / span
                yield Propagate(tuple(frac * x for x in th), tuple(frac * x for x in dv), tm - cur)
                done += frac
                cur = tm
            self.t = cur
            yield Apply(cur, kind, payload)
        rest = 1.0 - done
        if t_end - cur > 1e-12:
            yield Propagate(tuple(rest * x for x in th), tuple(rest * x for x in dv), t_end - cur)
        self.t = t_end
