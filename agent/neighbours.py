"""Neighbour table: the latest beacon of each neighbour, aged out, time-aligned for fusion.

Pure logic (no I/O). A range measured at time ``t`` needs the neighbour's position at ``t``:
the beacon is extrapolated with its velocity and its covariance inflated with the age
(``P(t) = P + (age² σ_v² + age³ q_a / 3) I_h``, a constant-velocity model with white
acceleration of density ``q_a``). Beacons older than ``max_age`` are never fused; neighbours not
heard for ``timeout`` are dropped. Duplicates, replays and out-of-order beacons (generation time
not newer than the last stored) are counted and ignored.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from slcp.geo import earth

#: labels seen as sets (a beacon's labels recur at every beacon; bounded)
_LABEL_SETS: dict[tuple[str, ...], frozenset[str]] = {}


def _label_set(labels: Iterable[str]) -> frozenset[str]:
    """``frozenset(labels)``, shared between the beacons that carry the same labels."""
    key = tuple(labels)
    got = _LABEL_SETS.get(key)
    if got is None:
        got = frozenset(key)
        if len(_LABEL_SETS) < 4096:
            _LABEL_SETS[key] = got
    return got


@dataclass(frozen=True)
class NeighbourState:
    """A neighbour's position at a requested time, ready for a range update."""

    vehicle: str
    llh: np.ndarray  #: (3,) lat, lon [rad], h [m]
    cov_ned: np.ndarray  #: (3, 3) [m²]
    age: float  #: [s] since the beacon's time
    v_ned: np.ndarray = field(default_factory=lambda: np.zeros(3))  #: (3,) [m/s]
    #: ``cov_ned`` by information source (:mod:`agent.nav.source_fusion`): each component's
    #: sources, and the components, shape (k, 3, 3) [m²], summing to it; k = 0 if the beacon
    #: had no breakdown
    source_labels: tuple[frozenset[str], ...] = ()
    source_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    #: the position error's sensitivity to exactly tracked random constants: ``(name, (3,)
    #: [m per σ])`` pairs; their outer products are the part of ``cov_ned`` the breakdown
    #: leaves out
    constants: tuple[tuple[str, np.ndarray], ...] = ()

    @property
    def sources(self) -> tuple[tuple[frozenset[str], np.ndarray], ...]:
        """The breakdown as ``(labels, (3, 3))`` pairs; empty if none."""
        return tuple(zip(self.source_labels, self.source_cov))


@dataclass
class _Entry:
    seq: int
    t: float
    llh: np.ndarray
    v_ned: np.ndarray
    cov: np.ndarray
    method: str
    received_at: float
    source_labels: tuple[frozenset[str], ...] = ()
    source_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    constants: tuple[tuple[str, np.ndarray], ...] = ()


@dataclass
class NeighbourTable:
    """Latest beacons per neighbour.

    Parameters
    ----------
    max_age : float
        Beacons older than this [s] at the time of use are not fused (default 0.3 s).
    timeout : float
        A neighbour not heard for this long [s] is removed (default 2 s).
    sigma_v : float
        Velocity uncertainty used when extrapolating [m/s].
    accel_psd : float
        White-acceleration density for extrapolation [m²/s³].
    """

    max_age: float = 0.3
    timeout: float = 2.0
    sigma_v: float = 0.5
    accel_psd: float = 1.0
    history: int = 10  #: beacons kept per neighbour; the one nearest the requested time is used
    entries: dict[str, _Entry] = field(default_factory=dict)
    _past: dict[str, deque] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=lambda: {
        "beacons": 0, "duplicate_or_old": 0, "stale": 0, "timed_out": 0, "sources_dropped": 0})

    def update(self, vehicle: str, seq: int, t: float, llh: np.ndarray, v_ned: np.ndarray,
               cov_pos: np.ndarray, method: str, now: float, sources=(), constants=()) -> bool:
        """Store a beacon; returns False (and counts) for a duplicate, replayed or out-of-order one
        (generation time ``t`` not newer than the last stored). ``sources``: the covariance by
        information source, ``(labels, (3, 3) [m²])`` pairs (labels: a sequence of str);
        ``constants``: the sensitivities to exactly tracked constants, ``(name, (3,) [m])``
        pairs, whose outer products complete the sources' sum to ``cov_pos``."""
        old = self.entries.get(vehicle)
        if old is not None and t <= old.t:  # by generation time: a restarted sender restarts seq
            self.counters["duplicate_or_old"] += 1
            return False
        cov_pos = np.asarray(cov_pos, float)
        labels = tuple(_label_set(lab) for lab, _ in sources)
        split = np.array([c for _, c in sources], float).reshape(-1, 3, 3)
        consts: tuple[tuple[str, np.ndarray], ...] = ()
        total = split.sum(axis=0)
        if labels and constants:  # a dozen a beacon: one array, a row each, and one product
            g_rows = np.array([g for _, g in constants], float).reshape(-1, 3)
            consts = tuple(zip([str(lab) for lab, _ in constants], g_rows))
            total = total + g_rows.T @ g_rows
        if labels and float(np.abs(total - cov_pos).max()) > 1e-9 + 1e-6 * float(np.abs(cov_pos).max()):
            # a breakdown that does not add up is not used: the estimate counts as of unknown
            # composition (plain CI)
            self.counters["sources_dropped"] += 1
            labels, split, consts = (), split[:0], ()
        e = _Entry(seq, float(t), np.asarray(llh, float), np.asarray(v_ned, float),
                   cov_pos, method, float(now), labels, split, consts)
        self.entries[vehicle] = e
        self._past.setdefault(vehicle, deque(maxlen=self.history)).append(e)
        self.counters["beacons"] += 1
        return True

    def expire(self, now: float) -> list[str]:
        """Drop neighbours not heard for ``timeout``; returns their ids."""
        gone = [v for v, e in self.entries.items() if now - e.received_at > self.timeout]
        for v in gone:
            del self.entries[v]
            self._past.pop(v, None)
        self.counters["timed_out"] += len(gone)
        return gone

    def remove(self, vehicle: str) -> None:
        """Forget a neighbour (e.g. its liveliness token disappeared)."""
        self.entries.pop(vehicle, None)
        self._past.pop(vehicle, None)

    def at(self, vehicle: str, t: float) -> NeighbourState | None:
        """The neighbour's position and covariance at time ``t``, or None if unknown or stale."""
        past = self._past.get(vehicle)
        if not past:
            return None
        # the beacon nearest in time: extrapolated forwards, or backwards from a newer one
        e = min(past, key=lambda b: abs(t - b.t))
        age = t - e.t
        if age > self.max_age or age < -self.max_age:
            self.counters["stale"] += 1
            return None
        llh = earth.offset_llh(e.llh, e.v_ned * age)
        a = abs(age)
        grow = a * a * self.sigma_v**2 + a**3 * self.accel_psd / 3.0
        G = np.diag([grow, grow, grow])
        # the extrapolation's uncertainty is the sender's own (its motion)
        labels, split = e.source_labels, e.source_cov
        if labels and grow > 0.0:
            k = next((i for i, lab in enumerate(labels) if vehicle in lab), None)
            if k is None:
                labels, split = labels + (frozenset({vehicle}),), np.concatenate([split, G[None]])
            else:
                split = split.copy()
                split[k] += G
        return NeighbourState(vehicle, llh, e.cov + G, age, e.v_ned, labels, split, e.constants)

    def newest_time(self, vehicle: str) -> float | None:
        """Time [s] of the newest beacon of ``vehicle``, or None."""
        e = self.entries.get(vehicle)
        return None if e is None else e.t

    def vehicles(self) -> list[str]:
        return sorted(self.entries)
