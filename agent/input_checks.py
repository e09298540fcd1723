"""Checks of the sensor messages a vehicle receives: repeats, and times that jump ahead of the
IMU stream (a clock error, a replay, a forgery) are counted and dropped."""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable

from slcp.transport.messages import ImuBatch

log = logging.getLogger(__name__)


class InputChecks:
    """The newest accepted IMU time and the keys of the latest sensor messages.

    ``max_time_jump`` [s]: an IMU batch starting more than this after the newest IMU time is a
    jump, accepted as the new timeline only once ``jump_confirm`` consecutive batches continue
    it; a measurement this far ahead of the IMU is dropped. ``count(name)`` counts a drop.
    """

    def __init__(self, vehicle: str, max_time_jump: float, jump_confirm: int, count: Callable[[str], None],
                 recent: int = 1024) -> None:
        self.vehicle = vehicle
        self.max_time_jump = max_time_jump
        self.jump_confirm = jump_confirm
        self._count = count
        self.imu_newest: float | None = None  #: newest accepted IMU time [s]
        self._jump_run: list[float] = []  #: ends of consecutive batches that jumped ahead
        self._recent: deque = deque(maxlen=recent)  #: keys of the latest sensor messages
        self._recent_set: set = set()

    def duplicate(self, kind: str, key: tuple) -> bool:
        """True (counted ``duplicate_<kind>``) for a sensor message seen already (same stream, seq
        and time); the last ``recent`` keys are remembered."""
        k = (kind, *key)
        if k in self._recent_set:
            self._count(f"duplicate_{kind}")
            return True
        if len(self._recent) == self._recent.maxlen:
            self._recent_set.discard(self._recent[0])
        self._recent.append(k)
        self._recent_set.add(k)
        return False

    def imu_in_time(self, msg: ImuBatch) -> bool:
        """False (counted ``imu_time_jump``) for a batch that jumps ahead of the stream; a jump
        that ``jump_confirm`` consecutive batches continue is accepted as the new timeline."""
        t0, t1 = float(msg.t[0]), float(msg.t[-1])
        if self.imu_newest is None or t0 - self.imu_newest <= self.max_time_jump:
            self.imu_newest = t1 if self.imu_newest is None else max(self.imu_newest, t1)
            self._jump_run = []
            return True
        if self._jump_run and 0.0 < t0 - self._jump_run[-1] <= self.max_time_jump:
            self._jump_run.append(t1)
        else:
            self._jump_run = [t1]
        if len(self._jump_run) >= self.jump_confirm:
            log.warning("%s: IMU time jumped from %.3f to %.3f s; following it", self.vehicle,
                        self.imu_newest, t0)
            self.imu_newest, self._jump_run = t1, []
            self._count("imu_time_resync")
            return True
        self._count("imu_time_jump")
        return False

    def ahead(self, t: float, kind: str) -> bool:
        """True (counted ``<kind>_time_jump``) for a measurement too far ahead of the IMU stream."""
        if self.imu_newest is not None and t - self.imu_newest > self.max_time_jump:
            self._count(f"{kind}_time_jump")
            return True
        return False
