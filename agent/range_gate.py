"""Physical range-rate gate on UWB ranges, one track per neighbour (pure logic).

A gross UWB outlier (3-30 m) or the onset of an NLOS bias is a jump in range that the two
vehicles' motion cannot explain. The gate predicts the range from the last accepted one and the
relative velocity along the line of sight, and rejects a range that differs from the prediction
by more than ``max_jump + k σ_rate Δt``. After ``reset_after`` consecutive rejections it accepts
the next range as a new reference (the reference itself may have been wrong, or the geometry
changed while ranges were missing).
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
    reset_after : int
        Consecutive rejections after which the next range restarts the track.
    max_gap : float
        A track older than this [s] is restarted rather than extrapolated.
    """

    max_jump: float = 0.6
    sigma_rate: float = 0.5
    k: float = 3.0
    reset_after: int = 10
    max_gap: float = 2.0
    _last: dict[str, tuple[float, float]] = field(default_factory=dict)
    _rejects: dict[str, int] = field(default_factory=dict)

    def check(self, neighbour: str, t: float, measured: float, range_rate: float) -> bool:
        """True if ``measured`` [m] at time ``t`` [s] is plausible given the last accepted range of
        this neighbour and the predicted range rate [m/s]; the track is updated."""
        last = self._last.get(neighbour)
        n_rej = self._rejects.get(neighbour, 0)
        if last is not None and n_rej < self.reset_after:
            dt = abs(t - last[0])
            if dt <= self.max_gap:
                predicted = last[1] + range_rate * (t - last[0])
                if abs(measured - predicted) > self.max_jump + self.k * self.sigma_rate * dt:
                    self._rejects[neighbour] = n_rej + 1
                    return False
        self._last[neighbour] = (t, measured)
        self._rejects[neighbour] = 0
        return True

    def forget(self, neighbour: str) -> None:
        self._last.pop(neighbour, None)
        self._rejects.pop(neighbour, None)
