"""GNSS fixes from u-blox UBX ``NAV-PVT`` messages (decoded with pyubx2).

:class:`UbxFixReader` frames the byte stream itself (sync ``B5 62``, class, id, length,
Fletcher checksum) so that a corrupted length cannot swallow the stream, then hands each
``NAV-PVT`` frame to :meth:`pyubx2.UBXReader.parse`. Other messages are counted and ignored.

Fix from NAV-PVT (u-blox interface description):

* time: UTC date and time + ``nano`` as POSIX seconds; needs ``validDate`` and ``validTime``
  (else ``ubx_no_time``);
* position: ``lat``, ``lon`` [deg -> rad], ``height`` above the ellipsoid [mm -> m];
* velocity: ``velN``, ``velE``, ``velD`` [mm/s -> m/s];
* σ: ``hAcc``/√2 north and east, ``vAcc`` down [mm -> m]; ``sAcc`` for the velocity [mm/s -> m/s];
* accepted only with ``gnssFixOk`` and fix type 2D, 3D or GNSS+DR (else ``ubx_no_fix``);
* ``quality`` in the GGA codes: 4 RTK fixed, 5 RTK float (``carrSoln``), 2 differential
  (``diffSoln``), 1 otherwise.
"""

from __future__ import annotations

import calendar
import math
from dataclasses import dataclass, field

import numpy as np
from pyubx2 import UBXReader

from slcp.transport.messages import GnssFix

SYNC = b"\xb5\x62"
NAV_PVT = (0x01, 0x07)
MAX_PAYLOAD = 2048  #: longer declared payloads are treated as corruption [bytes]


def _checksum(data: bytes) -> bytes:
    a = b = 0
    for x in data:
        a = (a + x) & 0xFF
        b = (b + a) & 0xFF
    return bytes((a, b))


@dataclass
class UbxFixReader:
    """Feed bytes, get :class:`GnssFix` messages from NAV-PVT."""

    vehicle: str
    counters: dict[str, int] = field(default_factory=lambda: {
        "ubx_frames": 0, "ubx_bad": 0, "ubx_ignored": 0, "ubx_no_fix": 0, "ubx_no_time": 0, "gnss_fixes": 0})

    def __post_init__(self) -> None:
        self._buf = bytearray()
        self._seq = 0

    def feed(self, data: bytes) -> list[GnssFix]:
        """Append stream bytes; returns the fixes of the complete frames."""
        self._buf += data
        out: list[GnssFix] = []
        while True:
            i = self._buf.find(SYNC)
            if i < 0:
                if self._buf:
                    self.counters["ubx_bad"] += int(len(self._buf) > 1)
                    del self._buf[:-1]  # keep a trailing 0xB5
                return out
            if i > 0:
                del self._buf[:i]
            if len(self._buf) < 6:
                return out
            length = int.from_bytes(self._buf[4:6], "little")
            if length > MAX_PAYLOAD:
                self.counters["ubx_bad"] += 1
                del self._buf[:2]
                continue
            if len(self._buf) < 8 + length:
                return out
            frame = bytes(self._buf[:8 + length])
            if _checksum(frame[2:6 + length]) != frame[6 + length:]:
                self.counters["ubx_bad"] += 1
                del self._buf[:2]  # resynchronise on the next sync pattern
                continue
            del self._buf[:8 + length]
            self.counters["ubx_frames"] += 1
            if (frame[2], frame[3]) != NAV_PVT:
                self.counters["ubx_ignored"] += 1
                continue
            try:
                fix = self._fix(UBXReader.parse(frame))
            except Exception:  # noqa: BLE001 - pyubx2 raises several types for a bad payload
                self.counters["ubx_bad"] += 1
                continue
            if fix is not None:
                out.append(fix)

    def _fix(self, m) -> GnssFix | None:
        if not (m.validDate and m.validTime):
            self.counters["ubx_no_time"] += 1
            return None
        if not m.gnssFixOk or m.fixType not in (2, 3, 4):
            self.counters["ubx_no_fix"] += 1
            return None
        t = calendar.timegm((m.year, m.month, m.day, m.hour, m.min, m.second, 0, 0, 0)) + m.nano * 1e-9
        llh = np.array([math.radians(m.lat), math.radians(m.lon), m.height * 1e-3])
        v = np.array([m.velN, m.velE, m.velD], float) * 1e-3
        h = max(m.hAcc * 1e-3, 1e-3) / math.sqrt(2.0)
        sig = np.array([h, h, max(m.vAcc * 1e-3, 1e-3)])
        quality = {2: 4, 1: 5}.get(int(m.carrSoln), 2 if m.diffSoln else 1)
        if not (np.isfinite(llh).all() and np.isfinite(v).all()):
            self.counters["ubx_bad"] += 1
            return None
        fix = GnssFix(self.vehicle, self._seq, float(t), llh, v, sig, max(m.sAcc * 1e-3, 0.01), quality)
        self._seq += 1
        self.counters["gnss_fixes"] += 1
        return fix
