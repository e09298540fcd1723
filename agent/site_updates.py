"""A stop-line method's site updates: the stop-line fix, lane keeping, and the random
constants they share (:class:`SiteUpdates`, one part of :class:`agent.methods.MethodFilter`)."""

from __future__ import annotations

import math

import numpy as np

from .nav.ins_filter import InsFilter
from .nav.kalman import Measurement, UpdateResult
from .nav.measurements.lane_line import lane_line_measurement
from .nav.measurements.stop_line import Line2D, StopLineApproach, stop_line_fix, stop_line_measurement
from .nav.source_fusion import CONSTANT_MARK
from .settings import FilterSettings, MethodSpec

#: σ [m] of the map's stop line and lane lines (their survey)
STOP_LINE_MAP_SIGMA = 0.03


class SiteUpdates:
    """The site part of a method's filter: the stop-line fix while first stopped and the
    lane-keeping row, with the stop's gap and the lane's offset as random constants."""

    filter: InsFilter
    settings: FilterSettings
    spec: MethodSpec
    vehicle: str
    counters: dict[str, int]

    def stop_line(self, approach: StopLineApproach, along_only: bool = False,
                  stop_id: float | None = None, lane: str | None = None) -> UpdateResult | None:
        """Apply the stop-line fix (only for SL methods, at most once per interval).

        ``stop_id`` identifies the physical stop (e.g. the time it began): a new one resets the
        stop-gap error states to their prior, since each stop draws its own d_s and d_l.
        ``lane`` names the approach lane: with the lane-keeping constraint on, a full fix's
        lateral row acts on that lane's offset state (the driver's d_l in it).
        """
        if not self.spec.stop_line or self.gap is None or self.origin is None or self._sl is None:
            return None
        f = self.filter
        if stop_id != self._stop_id:
            self._stop_id = stop_id
            self.last_stop_line = -math.inf
            self._reset_stop_gap()
        if self.t - self.last_stop_line < self.settings.stop_line_interval:
            return None
        self.last_stop_line = self.t
        m = stop_line_measurement(f.state, approach, self.gap, self.origin, along_only=along_only)
        # predicted fix = p - J ê, with J = ∂p/∂(d_e, d_l): the gap error is a state, not noise
        _, J = stop_line_fix(approach, self.gap.m_xb + self.gap.l0, self.gap.m_yb)
        hx = np.zeros((m.dim, len(f.extra)))
        if along_only:
            hx[:, self._sl] = -(approach.stop_line_normal() @ J)[None, :]
        elif self._lane is not None and lane is not None:
            self._enter_lane(lane)
            hx[:, self._sl.start] = -J[:, 0]
            hx[:, self._lane.start] = -J[:, 1]
        else:
            hx[:, self._sl] = -J
        self._sl_full = not along_only
        m = Measurement(m.z + hx @ f.extra, f.full_jacobian(m.H, hx), np.eye(m.dim) * STOP_LINE_MAP_SIGMA**2, m.name)
        res = f.update(m)
        self.counters["stop_line"] += int(res.accepted)
        return res

    def lane_due(self) -> bool:
        """Whether :meth:`lane_line` wants a lane now (``lane_interval`` after its last call)."""
        return (self._lane is not None and self.origin is not None
                and self.t - self._lane_checked >= self.settings.lane_interval)

    def lane_line(self, lane: str | None, left_line: Line2D | None = None) -> UpdateResult | None:
        """Keep to the lane: ``lane`` (and its ``left_line`` where the vehicle is, map frame) is
        the lane the vehicle drives in, None if no lane is certain now. Skipped while the stop
        line's full fix holds the lateral position (the same d_l). Only for SL methods with the
        lane-keeping constraint; the caller paces it (:meth:`lane_due`)."""
        if self._lane is None or self.origin is None:
            return None
        t = self.t
        self._lane_checked = t
        if lane is None:
            if t - self._lane_seen > self.settings.lane_memory:
                self._leave_lane()
            return None
        self._enter_lane(lane)
        if self._stop_id is not None and self._sl_full:
            return None
        f = self.filter
        m = lane_line_measurement(f.state, left_line, self.gap.m_yb, STOP_LINE_MAP_SIGMA, self.origin)
        hx = np.zeros((1, len(f.extra)))
        hx[0, self._lane.start] = -1.0  # predicted distance = d_l - (offset error)
        m = Measurement(m.z + hx @ f.extra, f.full_jacobian(m.H, hx), m.R, m.name)
        res = f.update(m, self.settings.range_gate)
        self.counters["lane_line" if res.accepted else "lane_line_rejected"] += 1
        if not res.accepted:  # the estimate and the lane disagree: the lane is not kept
            self._leave_lane()
        return res

    @property
    def lane(self) -> str | None:
        """The lane whose offset state the vehicle keeps now (lane keeping), or None."""
        return self._lane_id

    def _enter_lane(self, lane: str) -> None:
        if lane != self._lane_id or self.t - self._lane_seen > self.settings.lane_memory:
            self._leave_lane()
            self._lane_id = lane
        self._lane_seen = self.t

    def _leave_lane(self) -> None:
        """The lane is over: its offset state back to its prior (the next lane draws its own)."""
        if self._lane_id is not None:
            self._lane_id = None
            self._reset_extra(self._lane, np.array([self.gap.sigma_yb]))

    def end_stop(self) -> None:
        """The vehicle moves: a stop whose line it fixed on is over. Its stop-gap states go back
        to their prior, uncorrelated with the rest: nothing observes them until the next stop,
        which draws its own d_s and d_l, and left correlated, each split-CI range would inflate
        their dependent part by 1/ω with nothing to shrink it. No-op outside such a stop (a
        claim that ends while the vehicle stands keeps them: a new claim in the same stop
        shares their error)."""
        if self._sl is not None and self._stop_id is not None:
            self._stop_id = None
            self._reset_stop_gap()

    def _reset_stop_gap(self) -> None:
        self._sl_full = False
        self._reset_extra(self._sl, np.array([self.gap.sigma_xb, self.gap.sigma_yb]))

    def _reset_extra(self, states: slice, sigma: np.ndarray) -> None:
        """Extra ``states`` back to their prior σ ``sigma`` [(k,)], uncorrelated with the rest."""
        f = self.filter
        f.flush_covariance()
        k = np.arange(f.extra_offset + states.start, f.extra_offset + states.stop)
        for P in (f.P, f.P_ind):
            if P is not None:
                P[k, :] = 0.0
                P[:, k] = 0.0
                P[k, k] = sigma**2
        if f.sources is not None:
            f.sources.clear_states(k)
        f.extra[states] = 0.0
        self._track_constant(states, sigma)

    def _track_constant(self, states: slice, sigma: np.ndarray) -> None:
        """Extra ``states``, just at their prior σ ``sigma`` [(k,)], are new random constants:
        under source CI with ``exact_constants``, tracked exactly (one name per state, unique
        to this vehicle, also across restarts: the sensor time is in it)."""
        f = self.filter
        if f.sources is None or not self.settings.exact_constants:
            return
        k = np.arange(f.extra_offset + states.start, f.extra_offset + states.stop)
        names = []
        for _ in k:
            self._n_constants += 1
            names.append(f"{self.vehicle}{CONSTANT_MARK}{self._n_constants}.{self.t:.3f}")
        f.sources.new_constants(names, k, sigma)

