"""Receivers that report positions only: a velocity derived from successive positions.

A fix that carries no velocity (on the wire: ``sigma_v == 0``, see
:class:`transport.messages.GnssFix`) still has to start the filter, tell a moving vehicle from a
standing one and give the course that sets the heading. :class:`PositionCourse` derives the
velocity from the previous fix at least :data:`MIN_BASELINE` s older and at most
:data:`MAX_BASELINE` s: ``v = Δp / Δt`` with ``σ_v = √2 σ_h / Δt`` (two independent horizontal
position errors). The result is a :class:`PositionOnlyFix`: its velocity is used for those
decisions, never as a measurement, since it shares its errors with the position updates.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from slcp.geo import earth
from slcp.transport.messages import GnssFix

#: shortest and longest time between the two positions of a derived velocity [s]
MIN_BASELINE = 0.2
MAX_BASELINE = 2.0


@dataclass(frozen=True, eq=False)
class PositionOnlyFix(GnssFix):
    """A fix without a measured velocity; ``v_ned`` and ``sigma_v`` are derived from the
    positions (``sigma_v`` is infinite when no earlier fix was near enough in time)."""


def has_velocity(fix: GnssFix) -> bool:
    """Whether the receiver reported a velocity with ``fix`` (``sigma_v > 0``)."""
    return fix.sigma_v > 0.0 and not isinstance(fix, PositionOnlyFix)


class PositionCourse:
    """Derives the velocity of position-only fixes from the fixes before them."""

    def __init__(self) -> None:
        self._recent: deque[GnssFix] = deque(maxlen=64)

    def derive(self, fix: GnssFix) -> PositionOnlyFix:
        """``fix`` with the velocity of its positions (infinite σ when there is no baseline)."""
        base = None
        for old in reversed(self._recent):
            dt = fix.t - old.t
            if MIN_BASELINE <= dt <= MAX_BASELINE:
                base = old
                break
        if not self._recent or fix.t > self._recent[-1].t:
            self._recent.append(fix)
        if base is None:
            return PositionOnlyFix(fix.vehicle, fix.seq, fix.t, fix.llh, np.zeros(3), fix.sigma_ned, math.inf,
                                   fix.quality)
        dt = fix.t - base.t
        d = earth.ned_offset(float(fix.llh[0]), float(fix.llh[1]), float(fix.llh[2]),
                             float(base.llh[0]), float(base.llh[1]), float(base.llh[2]))
        sigma_h = math.hypot(float(fix.sigma_ned[0]), float(fix.sigma_ned[1])) / math.sqrt(2.0)
        return PositionOnlyFix(fix.vehicle, fix.seq, fix.t, fix.llh, d / dt, fix.sigma_ned,
                               math.sqrt(2.0) * sigma_h / dt, fix.quality)
