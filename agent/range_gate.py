"""Physical range-rate gate on UWB ranges, one track per neighbour (pure logic).

A gross UWB outlier (3-30 m) is an isolated jump in range that the two vehicles' motion cannot
explain. The gate predicts the range from the last accepted one and the relative velocity along
the line of sight, and rejects a range that differs from the prediction by more than
``max_jump + k σ_rate Δt`` -- unless it agrees with the range rejected just before it: a jump
that persists is a change of level (the start or end of an NLOS bias, a reference that was
itself wrong), and the track restarts there. So an isolated outlier costs one range, and a level
change costs one range too.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class RangeRateGate:
    """Parameters (SI units) and per-neighbour state.

    Attributes
    ----------
    max_jump : float
        Allowed difference from the predicted range at zero elapsed time [m].
    sigma_rate : float
        Uncertainty of the predicted range rate [m/s] (velocity errors of both vehicles).
    k : float
        Gate width in σ.
    max_gap : float
        A track older than this [s] is restarted rather than extrapolated.
    """

    max_jump: float = 0.6
    sigma_rate: float = 0.5
    k: float = 3.0
    max_gap: float = 2.0
    _last: dict[str, tuple[float, float]] = field(default_factory=dict)
    _rejected: dict[str, tuple[float, float]] = field(default_factory=dict)

    def _agrees(self, ref: tuple[float, float] | None, t: float, measured: float, range_rate: float) -> bool:
        if ref is None or abs(t - ref[0]) > self.max_gap:
            return ref is None
        predicted = ref[1] + range_rate * (t - ref[0])
        return abs(measured - predicted) <= self.max_jump + self.k * self.sigma_rate * abs(t - ref[0])

    def check(self, neighbour: str, t: float, measured: float, range_rate: float) -> bool:
        """True if ``measured`` [m] at time ``t`` [s] is plausible given this neighbour's track and
        the predicted range rate [m/s]; the track is updated."""
        last = self._last.get(neighbour)
        stale = last is not None and abs(t - last[0]) > self.max_gap
        if stale or self._agrees(last, t, measured, range_rate) or \
                (neighbour in self._rejected and self._agrees(self._rejected[neighbour], t, measured, range_rate)):
            self._last[neighbour] = (t, measured)
            self._rejected.pop(neighbour, None)
            return True
        self._rejected[neighbour] = (t, measured)
        return False

    def forget(self, neighbour: str) -> None:
        self._last.pop(neighbour, None)
        self._rejected.pop(neighbour, None)
