"""The vehicle engine's configuration (:class:`AgentConfig`, SI units, built at the config
edge) and the shapes of what hosts plug into it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from slcp.transport.messages import Beacon

from .first_stopped import ApproachLane
from .lane_map import LaneMap
from .nav.measurements.stop_line import StopGapModel
from .settings import FilterSettings

#: (method, neighbour, range time [s], outcome) of every range a filter weighed
RangeObserver = Callable[[str, str, float, "str | None"], None]


class BeaconSigner(Protocol):
    """Signs beacons (the host's; e.g. :class:`transport.security.BeaconSigner`)."""

    def sign(self, beacon: Beacon) -> Beacon: ...


class BeaconVerifier(Protocol):
    """Checks a beacon's signature: "ok" or why not (e.g. :class:`transport.security.TrustStore`)."""

    def verify(self, beacon: Beacon) -> str: ...

    def precheck(self, beacon: Beacon) -> str: ...

    def check_signature(self, beacon: Beacon) -> str: ...

    def precheck_fields(self, vehicle: str, auth: bytes) -> str: ...

    def is_vehicle(self, name: str) -> bool: ...

    def identities(self, role: str) -> list[str]: ...


@dataclass(frozen=True)
class AgentConfig:
    """Everything an agent needs (SI units; built at the config edge)."""

    vehicle: str
    methods: tuple[str, ...]
    settings: FilterSettings
    gap: StopGapModel
    lanes: dict[str, ApproachLane]
    origin_llh: tuple[float, float, float]
    beacon_rate: float = 5.0
    estimate_rate: float = 10.0
    decision_rate: float = 10.0
    queue_size: int = 4096
    #: IMU batches are processed only once this much newer IMU data has arrived [s], so that
    #: GNSS/UWB of earlier times, travelling on other topics, are applied in order
    imu_hold: float = 0.25
    #: a UWB range waits up to this long (filter time) for the neighbour's beacon of its time,
    #: then is fused with the nearest beacon (or counted stale) [s]
    range_defer: float = 1.0
    #: signs this agent's beacons (None: unsigned)
    signer: BeaconSigner | None = None
    #: when set, only beacons signed by a key of this store for the sending vehicle are accepted
    trust: BeaconVerifier | None = None
    #: a beacon generated more than this before the agent's filter time is refused as stale, and
    #: one more than ``max_beacon_future`` after it as from the future [s]. (Fusion itself uses a
    #: beacon only within 0.3 s of the range time, see :class:`agent.neighbours.NeighbourTable`.)
    max_beacon_age: float = 1.0
    max_beacon_future: float = 2.0
    #: a neighbour silent this long [s of sensor time] is gone (also when its liveliness token
    #: vanishes, which is usually sooner)
    neighbour_timeout: float = 1.5
    #: an IMU batch starting more than this after the newest IMU time is a time jump, dropped
    #: unless ``jump_confirm`` consecutive batches continue it (then the stream re-synchronises);
    #: a GNSS fix or range this far ahead of the newest IMU time is dropped too [s]
    max_time_jump: float = 5.0
    jump_confirm: int = 5
    #: check every neighbour's beacons and ranges for misbehaviour and exclude the flagged ones
    #: (:mod:`agent.misbehaviour`); ``nlos_bias_max`` is the largest NLOS range bias expected [m]
    misbehaviour_detection: bool = True
    nlos_bias_max: float = 3.0
    #: a neighbour lost (not excluded) counts, for ``ghost_memory`` seconds or until heard
    #: again, as standing where it was last heard, with its covariance grown at ``ghost_speed``
    #: [m/s]: a vehicle that cannot hear the queue ahead does not take the stop line
    ghost_memory: float = 30.0
    ghost_speed: float = 1.0
    #: every lane of the site, for the SL methods' lane-keeping row (None: no lane map)
    lane_map: LaneMap | None = None
