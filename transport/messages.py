"""Wire messages (frozen dataclasses). SI units, radians, sensor time in seconds.

Array fields are numpy float64 arrays with the shapes given per field; the codec checks them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np


@dataclass(frozen=True, eq=False)
class Message:
    """Base class: value equality that understands numpy arrays."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if not np.array_equal(np.asarray(a), np.asarray(b)):
                    return False
            elif f.name in ("sources", "constants"):  # (labels, array) pairs
                if len(a) != len(b) or any(tuple(la) != tuple(lb) or not np.array_equal(ca, cb)
                                           for (la, ca), (lb, cb) in zip(a, b)):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class ImuBatch(Message):
    """IMU increments of several samples. ``t[k]`` ends interval ``k`` of length ``dt[k]``.

    Shapes: ``t``, ``dt`` (n,); ``dtheta`` [rad], ``dvel`` [m/s] (n, 3), body FRD.
    """

    vehicle: str
    seq: int
    t: np.ndarray
    dt: np.ndarray
    dtheta: np.ndarray
    dvel: np.ndarray


@dataclass(frozen=True, eq=False)
class GnssFix(Message):
    """A GNSS fix: ``llh`` (lat, lon rad; h m ellipsoidal), ``v_ned`` [m/s], reported ``sigma_ned`` [m]
    and ``sigma_v`` [m/s]. A receiver that reports positions only sends ``sigma_v = 0`` (and
    ``v_ned`` zeros): the fix carries no velocity."""

    vehicle: str
    seq: int
    t: float
    llh: np.ndarray
    v_ned: np.ndarray
    sigma_ned: np.ndarray
    sigma_v: float
    quality: int = 1


@dataclass(frozen=True, eq=False)
class LaneMarkings(Message):
    """The camera's classes of the markings left and right of the ego lane at ``t`` [s]:
    0 unseen, 1 divider (a lane of my direction beyond it), 2 boundary (centre line, road edge).
    See :mod:`geo.lane_markings`; receivers treat any other value as unseen."""

    vehicle: str
    seq: int
    t: float
    left: int
    right: int


@dataclass(frozen=True, eq=False)
class UwbRange(Message):
    """A two-way range between vehicles ``a`` and ``b`` measured at ``t`` [s]; both ends receive it."""

    a: str
    b: str
    seq: int
    t: float
    range_m: float


@dataclass(frozen=True, eq=False)
class UwbRound(Message):
    """One UWB ranging round of ``vehicle`` at ``t`` [s]: its ranges [m] to ``peers`` (n,),
    ``ranges`` (n,). One message per vehicle and round instead of one per range and end: the
    same information as the :class:`UwbRange` of each pair, in a fifth of the messages."""

    vehicle: str
    seq: int
    t: float
    peers: tuple[str, ...]
    ranges: np.ndarray


@dataclass(frozen=True, eq=False)
class Beacon(Message):
    """A vehicle's broadcast estimate: time, id, sequence, method, position, velocity, covariance.

    ``cov_pos`` is the NED position covariance [m²] (3, 3). ``first_stopped`` is the sender's
    claim to be the first stopped vehicle of its lane (used by the receivers' detectors).
    ``sources`` splits ``cov_pos`` by the source of the information (:mod:`agent.nav.source_fusion`);
    ``constants`` carries the position error's sensitivity to random constants tracked exactly,
    whose outer products complete the sum.
    ``auth`` carries an optional signature block (key id + signature), opaque to the codec.
    """

    vehicle: str
    seq: int
    method: str
    t: float
    llh: np.ndarray
    v_ned: np.ndarray
    cov_pos: np.ndarray
    auth: bytes = b""
    first_stopped: bool = False
    #: ``cov_pos`` by information source (source CI): ``(labels, (3, 3) [m²])`` pairs, the
    #: sender's own first; empty when the sender does not split its covariance
    sources: tuple[tuple[tuple[str, ...], np.ndarray], ...] = ()
    #: the position error's sensitivity to each exactly tracked random constant: ``(name, (3,)
    #: [m per σ of the constant])`` pairs; ``cov_pos`` = Σ sources + Σ g gᵀ
    constants: tuple[tuple[str, np.ndarray], ...] = ()


@dataclass(frozen=True, eq=False)
class Estimate(Message):
    """An agent's estimate for recording: state, attitude (roll, pitch, yaw rad), covariance."""

    vehicle: str
    method: str
    t: float
    llh: np.ndarray
    v_ned: np.ndarray
    rpy: np.ndarray
    cov_pos: np.ndarray
    first_stopped: bool = False


@dataclass(frozen=True, eq=False)
class Diagnostics(Message):
    """Counters and status of a process (``counters``: name -> count)."""

    source: str
    t: float
    counters: dict[str, int] = field(default_factory=dict)
    status: dict[str, Any] = field(default_factory=dict)


#: message type names on the wire
MESSAGE_TYPES: dict[str, type[Message]] = {
    "imu": ImuBatch, "gnss": GnssFix, "lane": LaneMarkings, "uwb": UwbRange, "uwb_round": UwbRound, "beacon": Beacon,
    "estimate": Estimate, "diag": Diagnostics,
}
