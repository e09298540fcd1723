"""Misbehaviour detection: is a neighbour's beacon believable? (pure logic, SI units)

A signed beacon proves who sent it, not that it is true: an insider (a faulty or compromised
vehicle) can claim any position and covariance. Before a receiver fuses a neighbour's beacon it
checks it against what it can observe independently:

* **covariance plausibility** -- a horizontal standard deviation below ``min_sigma`` (5 cm; the
  best honest figure in the fleet runs is 0.12 m, a first stopped vehicle on its stop line) or a
  covariance that is not positive semi-definite is implausible: flagged at once;
* **motion consistency** -- each beacon against the same stream's previous one: no sudden stop
  (from above 3 m/s to standing, faster than ``max_accel`` = 1 g plus a velocity step at an
  update), and the displacement must match the reported velocities within the two covariances
  plus an acceleration allowance (a χ² test on 2 degrees of freedom);
* **range consistency** -- each UWB range to the neighbour against the distance between the
  receiver's *own-sensor* estimate (independent of every neighbour) and the neighbour's claimed
  position, normalised by ``σ_uwb² + uᵀ(P_own + P_nb)u`` plus the NLOS bias allowance; and the
  change of range over the last 0.4-1 s against the change of that distance, where the
  receiver's own (metre-level) position error cancels, so that a claim that does not move with
  the vehicle (an eventual stop) is caught within a second.

A failed motion or range test is a *strike*; ``strikes`` strikes within ``window`` seconds flag
the neighbour. A flagged neighbour is excluded (its beacons and ranges are not used) until
``hold`` seconds have passed without a strike; the detector keeps checking it meanwhile.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from slcp.geo import earth


@dataclass(slots=True)
class _Beacon:
    """A checked beacon in Python floats: the tests run at every beacon and range an agent hears
    (hundreds a second in a fleet), where numpy's per-call overhead on 3-vectors dominates."""

    t: float
    llh: list[float]  #: lat, lon [rad], h [m]
    v: list[float]  #: NED [m/s]
    cov: list[list[float]]  #: (3, 3) NED position covariance [m²]


@dataclass
class MisbehaviourDetector:
    """Parameters (SI) and per-neighbour state.

    Attributes
    ----------
    min_sigma : float
        Smallest plausible horizontal standard deviation of a beacon [m].
    motion_chi2 : float
        χ² (2 dof) threshold of the motion test (default: probability 1e-7 under honesty).
    accel : float
        Acceleration allowance between two beacons [m/s²].
    range_k : float
        Range test threshold in standard deviations (high: the receiver's and the neighbour's
        errors are time-correlated, so one excursion lasts, and their reported σ can be too small
        by a factor up to 1.7 (ANEES 3) in dense traffic; a false flag needs three failures).
    rate_k : float
        Range-rate test threshold in standard deviations (beyond the NLOS allowance).
    nlos_bias : float
        Largest positive NLOS range bias allowed for [m].
    strikes, window : int, float
        ``strikes`` failed tests within ``window`` seconds flag a neighbour.
    hold : float
        A flagged neighbour stays excluded until this long [s] after its last strike.
    max_extrapolation : float
        Ranges are checked only against a beacon at most this old [s].
    """

    min_sigma: float = 0.05
    motion_chi2: float = 32.2
    accel: float = 6.0
    #: velocity-change test: largest plausible horizontal acceleration [m/s²] and a velocity
    #: estimate's step at an update [m/s]
    max_accel: float = 10.0
    velocity_step: float = 1.0
    #: the sudden-stop test applies from above ``stop_from`` to below ``stopped`` [m/s]
    stop_from: float = 3.0
    stopped: float = 0.3
    range_k: float = 10.0
    rate_k: float = 5.0
    nlos_bias: float = 3.0
    strikes: int = 3
    window: float = 1.0
    hold: float = 10.0
    max_extrapolation: float = 0.3
    #: range-rate test: reference ranges between these ages [s]; relative-velocity uncertainty
    #: [m/s]; a step of the receiver's own estimate within the window (GNSS update) [m]
    rate_window: tuple[float, float] = (0.4, 1.0)
    #: run the range-rate test. Off by default: it flags honest vehicles around the moments a
    #: receiver's own estimate steps (its first fixes, a multipath jump) and moves every claimed
    #: distance at once
    rate_test: bool = False
    sigma_rate: float = 0.5
    sigma_step: float = 0.5
    _last: dict[tuple[str, str], _Beacon] = field(default_factory=dict)
    _latest: dict[str, _Beacon] = field(default_factory=dict)
    _ranges: dict[str, deque] = field(default_factory=dict)  #: (t, range, claimed distance, struck)
    _range_stream: dict[str, str] = field(default_factory=dict)
    preferred_stream: str = "CP"
    _strikes: dict[str, deque] = field(default_factory=dict)
    #: vehicle -> (time flagged [s], reason) while flagged
    flagged: dict[str, tuple[float, str]] = field(default_factory=dict)
    _last_strike: dict[str, float] = field(default_factory=dict)
    #: every flag raised: (time [s], vehicle, reason)
    events: list[tuple[float, str, str]] = field(default_factory=list)
    counters: dict[str, int] = field(default_factory=lambda: {
        "implausible_covariance": 0, "motion_strikes": 0, "acceleration_strikes": 0, "range_strikes": 0,
        "flags": 0, "cleared": 0})

    # ----------------------------------------------------------------- checks
    def beacon(self, vehicle: str, stream: str, t: float, llh: np.ndarray, v_ned: np.ndarray,
               cov_ned: np.ndarray) -> str | None:
        """Check a beacon (``stream``: the method it belongs to); returns the failed test's name
        (``"covariance"`` or ``"motion"``) or None."""
        b = _Beacon(float(t), np.asarray(llh, float).tolist(), np.asarray(v_ned, float).tolist(),
                    np.asarray(cov_ned, float).reshape(3, 3).tolist())
        bc = b.cov
        # smallest eigenvalue of the symmetric horizontal block, in closed form
        c00, c11, c01 = bc[0][0], bc[1][1], 0.5 * (bc[0][1] + bc[1][0])
        eig_min = 0.5 * (c00 + c11) - math.hypot(0.5 * (c00 - c11), c01)
        prev = self._last.get((vehicle, stream))
        self._last[(vehicle, stream)] = b
        # ranges are checked against one stream per neighbour (the first seen, CP preferred):
        # the methods' estimates differ by metres, and a stop-line fix moves an SL stream at once
        ref = self._range_stream.get(vehicle)
        if ref is None or (stream == self.preferred_stream and ref != stream):
            self._range_stream[vehicle] = ref = stream
            self._ranges.pop(vehicle, None)
        if stream == ref:
            self._latest[vehicle] = b
        if not math.isfinite(eig_min) or eig_min < self.min_sigma**2:
            self.counters["implausible_covariance"] += 1
            self._flag(vehicle, b.t, "implausible covariance", at_once=True)
            return "covariance"
        if prev is None or not 0.0 < b.t - prev.t <= 1.0:
            return None
        dt = b.t - prev.t
        v0, v1 = math.hypot(prev.v[0], prev.v[1]), math.hypot(b.v[0], b.v[1])
        if v0 > self.stop_from and v1 < self.stopped and v0 - v1 > self.max_accel * dt + self.velocity_step:
            # from driving to standing within one beacon period: a stop no vehicle makes (an
            # emergency stop is about 1 g), the signature of a claim frozen in place
            self.counters["acceleration_strikes"] += 1
            self._strike(vehicle, b.t, "acceleration")
            return "acceleration"
        # the displacement (on the previous beacon's curvature) less the one the mean velocity predicts
        mn, me, _ = earth.ned_offset_scalars(*b.llh, *prev.llh)
        e0 = mn - 0.5 * (b.v[0] + prev.v[0]) * dt
        e1 = me - 0.5 * (b.v[1] + prev.v[1]) * dt
        q = (0.5 * self.accel * dt * dt) ** 2
        pc = prev.cov
        s00 = bc[0][0] + pc[0][0] + q
        s11 = bc[1][1] + pc[1][1] + q
        s01 = bc[0][1] + pc[0][1]
        s10 = bc[1][0] + pc[1][0]
        det = s00 * s11 - s01 * s10
        if not det > 0.0:  # only with an implausible previous covariance, flagged when it came
            return None
        # eᵀ S⁻¹ e of the 2×2 S written out
        if (s11 * e0 * e0 - (s01 + s10) * e0 * e1 + s00 * e1 * e1) / det > self.motion_chi2:
            self.counters["motion_strikes"] += 1
            self._strike(vehicle, b.t, "motion")
            return "motion"
        return None

    def range(self, vehicle: str, t: float, measured: float, own_llh: np.ndarray, own_cov_ned: np.ndarray,
              sigma_uwb: float) -> str | None:
        """Check a UWB range [m] at time ``t`` against the neighbour's latest beacon and the
        receiver's own-sensor estimate (llh, NED covariance (3, 3)); returns ``"range"`` if it
        fails, else None (also when no recent beacon is known)."""
        b = self._latest.get(vehicle)
        if b is None or abs(t - b.t) > self.max_extrapolation:
            return None
        # the neighbour's claim moved to ``t`` with its velocity, and its NED offset from my own
        # estimate (on my curvature)
        tau = t - b.t
        nb = earth.offset_llh_scalars(*b.llh, b.v[0] * tau, b.v[1] * tau, b.v[2] * tau)
        d = earth.ned_offset_scalars(*nb, *np.asarray(own_llh, float).tolist())
        dist = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if dist < 1e-3:
            return None
        u = (d[0] / dist, d[1] / dist, d[2] / dist)
        own = np.asarray(own_cov_ned, float).reshape(3, 3).tolist()
        quad = 0.0  # uᵀ (P_own + P_nb) u
        for i in range(3):
            oi, ci = own[i], b.cov[i]
            quad += u[i] * ((oi[0] + ci[0]) * u[0] + (oi[1] + ci[1]) * u[1] + (oi[2] + ci[2]) * u[2])
        var = sigma_uwb**2 + quad
        resid = measured - dist
        # NLOS only lengthens a range: a positive residual up to nlos_bias is no evidence
        excess = resid if resid < 0 else max(resid - self.nlos_bias, 0.0)
        hist = self._ranges.setdefault(vehicle, deque())
        while hist and hist[0][0] < t - self.rate_window[1]:
            hist.popleft()
        failed = None
        if abs(excess) > self.range_k * math.sqrt(var):
            failed = "range"
        elif self.rate_test:
            # range change against claimed change of distance: the receiver's own position error
            # (metres) is nearly the same at both ends of a short window and cancels; what is
            # left is UWB noise, velocity errors and an NLOS bias starting or ending
            ref = next((h for h in hist if t - h[0] >= self.rate_window[0] and not h[3]), None)
            if ref is not None:
                dt = t - ref[0]
                e = (measured - ref[1]) - (dist - ref[2])
                sd = math.sqrt(2 * sigma_uwb**2 + (self.sigma_rate * dt) ** 2 + self.sigma_step**2)
                if abs(e) - self.nlos_bias > self.rate_k * sd:
                    failed = "range rate"
        hist.append((t, measured, dist, failed is not None))
        if failed:
            self.counters["range_strikes"] += 1
            self._strike(vehicle, t, failed)
            return failed
        return None

    # ----------------------------------------------------------------- state
    def excluded(self, vehicle: str, t: float) -> bool:
        """Whether ``vehicle`` is flagged at time ``t`` (cleared after ``hold`` without strikes)."""
        if vehicle not in self.flagged:
            return False
        if t - self._last_strike.get(vehicle, -math.inf) > self.hold:
            del self.flagged[vehicle]
            self.counters["cleared"] += 1
            return False
        return True

    def forget(self, vehicle: str) -> None:
        for k in [k for k in self._last if k[0] == vehicle]:
            del self._last[k]
        self._latest.pop(vehicle, None)
        self._ranges.pop(vehicle, None)
        self._range_stream.pop(vehicle, None)

    def _strike(self, vehicle: str, t: float, kind: str) -> None:
        q = self._strikes.setdefault(vehicle, deque())
        q.append(t)
        while q and q[0] < t - self.window:
            q.popleft()
        self._last_strike[vehicle] = max(t, self._last_strike.get(vehicle, -math.inf))
        if len(q) >= self.strikes:
            self._flag(vehicle, t, f"{kind} inconsistent")

    def _flag(self, vehicle: str, t: float, reason: str, at_once: bool = False) -> None:
        if at_once:
            self._last_strike[vehicle] = max(t, self._last_strike.get(vehicle, -math.inf))
        if vehicle not in self.flagged:
            self.flagged[vehicle] = (t, reason)
            self.events.append((t, vehicle, reason))
            self.counters["flags"] += 1
