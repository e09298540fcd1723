"""The engine's neighbours: liveliness, departures, misbehaviour exclusions (a mixin of
:class:`agent.engine.VehicleEngine`)."""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable

import numpy as np

from slcp.transport.messages import Beacon
from slcp.transport.rate_limit import TokenBuckets

from .engine_config import AgentConfig
from .first_stopped import StopTracker
from .misbehaviour import MisbehaviourDetector
from .neighbours import NeighbourTable
from .sequencer import Sequencer

log = logging.getLogger("slcp.agent.engine")  # the engine's log


class EngineNeighbours:
    """Who the engine hears from, who is gone, who is excluded."""

    #: neighbours gone that the diagnostics list (the latest); a long-lived fleet sees thousands
    MAX_LOST = 64
    #: senders whose verified beacons are counted one by one (``beacons_from``); an unsigned fleet
    #: open to strangers would otherwise count every name it hears
    MAX_SENDERS = 256

    tables: dict[str, NeighbourTable]
    trackers: dict[str, StopTracker]
    misbehaviour: MisbehaviourDetector | None
    seq: Sequencer
    lost: dict[str, tuple[float, str]]
    departures: deque
    _ghosts: dict[str, dict[str, tuple[np.ndarray, np.ndarray, float]]]

    cfg: AgentConfig
    _count: Callable[..., None]
    _verify_budget: TokenBuckets | None

    def neighbour_alive(self, other: str, alive: bool) -> None:
        """A neighbour's liveliness token appeared (``alive``) or vanished."""
        if other == self.cfg.vehicle:
            return
        trust = self.cfg.trust
        if trust is not None and not trust.is_vehicle(other):
            # not a vehicle of the fleet: no beacon of it can pass, so it is no neighbour, and a
            # stranger churning thousands of tokens must not fill the departures or the log
            self._count("liveliness_unknown")
            return
        if alive:
            self.lost.pop(other, None)
            return
        self._lose(other, "liveliness")

    def _untrusted(self, msg: Beacon) -> bool:
        """Misbehaviour check of a verified beacon; True (counted ``beacon_excluded``) while its
        sender is flagged, in which case the sender is also dropped from the tables."""
        mb = self.misbehaviour
        if mb is None:
            return False
        was = msg.vehicle in mb.flagged
        mb.beacon(msg.vehicle, msg.method, msg.t, msg.llh, msg.v_ned, msg.cov_pos)
        if not mb.excluded(msg.vehicle, msg.t):
            return False
        if not was:
            self._exclude(msg.vehicle)
        self._count("beacon_excluded")
        return True

    def _exclude(self, other: str) -> None:
        t, reason = self.misbehaviour.flagged[other]
        log.warning("%s: neighbour %s flagged at t=%.2f (%s); excluded", self.cfg.vehicle, other, t, reason)
        self._drop(other)

    def _drop(self, other: str) -> None:
        """Forget neighbour ``other`` in every method's table and first-stopped tracker."""
        for tab in self.tables.values():
            tab.remove(other)
        for tr in self.trackers.values():
            tr.forget(other)

    def _lose(self, other: str, how: str) -> None:
        """Stop using neighbour ``other`` (gone: its liveliness token vanished, or silent for the
        table timeout); remembered in ``lost`` as (sensor time, how) for the diagnostics, and its
        last beacon per method as a ghost for the first-stopped decisions (``ghost_memory``)."""
        t = self.seq.t if self.seq.t is not None else math.nan
        for m, tab in self.tables.items():
            e = tab.entries.get(other)
            if e is not None:
                self._ghosts.setdefault(m, {})[other] = (e.llh, e.cov, t)
        self._drop(other)
        if other not in self.lost:
            self.lost[other] = (self.seq.t if self.seq.t is not None else math.nan, how)
            self.departures.append((self.lost[other][0], other, how))
            self._count(f"neighbour_lost_{how}")
            log.info("%s: neighbour %s gone (%s) at t=%.2f", self.cfg.vehicle, other, how, self.lost[other][0])
            while len(self.lost) > self.MAX_LOST:  # the oldest first (insertion order)
                del self.lost[next(iter(self.lost))]
                self._count("neighbour_lost_forgotten")

    def _may_verify(self, msg: Beacon) -> bool:
        """Whether a beacon that names a fleet vehicle and carries its key id may cost a signature
        verification: a token bucket per vehicle and method on the filter time, twice the beacon
        rate and two seconds' worth of burst. Genuine beacons come at the beacon rate, so only a
        flood of forgeries in a vehicle's name (bad signatures, fresh times) meets the bound: it
        then costs at most twice the genuine verifications, and that vehicle's genuine beacons
        compete with it (counted ``beacon_verify_budget``) until it stops."""
        now = self.seq.t
        if now is None:
            return True
        if self._verify_budget is None:
            rate = 2.0 * self.cfg.beacon_rate
            self._verify_budget = TokenBuckets(rate, 2.0 * rate)
        return self._verify_budget.take((msg.vehicle, msg.method), now)

    def _stale_or_future(self, msg: Beacon) -> str | None:
        """``stale`` or ``future`` for a beacon outside the time window of the filter time, or None."""
        now = self.seq.t
        if now is not None:
            if now - msg.t > self.cfg.max_beacon_age:
                return "stale"
            if msg.t - now > self.cfg.max_beacon_future:
                return "future"
        return None
