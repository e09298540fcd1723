"""GNSS fixes from NMEA 0183 sentences (parsed with pynmea2).

One fix is assembled per epoch (sentences sharing a UTC time of day) from:

* ``GGA`` (required): latitude, longitude, altitude above MSL + geoid separation (so the height
  is ellipsoidal), fix quality, HDOP;
* ``RMC`` (gives the date; epochs before the first date are dropped, ``nmea_no_date``) and/or
  ``VTG``: speed over ground and true course -> north and east velocity. NMEA has no vertical
  velocity: down is set to 0 and covered by ``sigma_v``;
* ``GST`` (optional): the receiver's 1σ latitude, longitude and altitude errors [m]. Without
  it, σ = HDOP × ``uere`` horizontally and 1.5 × that vertically.

An epoch is emitted as soon as it has every sentence type the previous epoch had (the receiver's
output set is learned; the first epoch waits for the second), or when the next epoch starts. Fix
time: UTC seconds since the Unix epoch (POSIX time); a time of day that goes back by more than 12 h starts a new day.
Bad sentences (checksum, syntax) are counted (``nmea_bad``), a fix quality of 0 is counted
(``nmea_no_fix``); unknown sentence types are ignored (``nmea_ignored``).

GGA quality codes are kept as the fix's ``quality``: 1 autonomous, 2 DGNSS/SBAS, 4 RTK fixed,
5 RTK float, 6 dead reckoning.
"""

from __future__ import annotations

import calendar
import math
from dataclasses import dataclass, field

import numpy as np
import pynmea2

from slcp.transport.messages import GnssFix

KNOT = 1852.0 / 3600.0  #: [m/s]
_USED = {"GGA", "RMC", "VTG", "GST"}


@dataclass
class NmeaFixAssembler:
    """Feed NMEA lines, get :class:`GnssFix` messages.

    Parameters
    ----------
    vehicle : str
        Vehicle id of the fixes.
    uere : float
        User equivalent range error used with HDOP when there is no GST [m].
    sigma_v : float
        Velocity σ of every axis [m/s] (NMEA reports none).
    """

    vehicle: str
    uere: float = 2.5
    sigma_v: float = 0.5
    counters: dict[str, int] = field(default_factory=lambda: {
        "nmea_sentences": 0, "nmea_bad": 0, "nmea_ignored": 0, "nmea_no_fix": 0, "nmea_no_date": 0,
        "gnss_fixes": 0})

    def __post_init__(self) -> None:
        self._date = None  #: datetime.date of the latest RMC
        self._tod: float | None = None  #: current epoch's time of day [s]
        self._epoch: dict[str, object] = {}
        #: sentence types of the previous epoch (None until one epoch has been seen whole)
        self._pattern: set[str] | None = None
        self._emitted = False
        self._seq = 0
        self._t_last: float | None = None

    def feed(self, line: str | bytes) -> list[GnssFix]:
        """One sentence; returns the fixes it completed (0, 1 or 2)."""
        if isinstance(line, bytes):
            line = line.decode("ascii", errors="replace")
        line = line.strip()
        if not line:
            return []
        try:
            msg = pynmea2.parse(line, check=True)
        except (pynmea2.ParseError, ValueError, TypeError, AttributeError):
            self.counters["nmea_bad"] += 1
            return []
        self.counters["nmea_sentences"] += 1
        kind = getattr(msg, "sentence_type", "")
        if kind not in _USED:
            self.counters["nmea_ignored"] += 1
            return []
        try:
            ts = getattr(msg, "timestamp", None)
            if kind == "RMC" and getattr(msg, "datestamp", None):
                self._date = msg.datestamp
        except (ValueError, TypeError):
            self.counters["nmea_bad"] += 1
            return []
        out: list[GnssFix] = []
        if ts is not None and kind != "VTG":
            tod = ts.hour * 3600 + ts.minute * 60 + ts.second + ts.microsecond * 1e-6
            if self._tod is not None and abs(tod - self._tod) > 1e-3:  # a new epoch
                out.extend(self._emit())
                self._pattern = set(self._epoch)
                self._epoch, self._emitted = {}, False
            self._tod = tod
        elif self._tod is None:  # a VTG (no time) before any epoch
            return out
        self._epoch[kind] = msg
        if self._pattern and self._pattern <= set(self._epoch):
            out.extend(self._emit())
        return out

    def flush(self) -> list[GnssFix]:
        """Emit the pending epoch, if it has a GGA."""
        return self._emit()

    # ------------------------------------------------------------------ internals
    def _emit(self) -> list[GnssFix]:
        ep, tod = self._epoch, self._tod
        if self._emitted or "GGA" not in ep or tod is None:
            return []
        self._emitted = True
        gga = ep["GGA"]
        try:
            fix = self._fix(ep, gga, tod)
        except (ValueError, TypeError, AttributeError):
            self.counters["nmea_bad"] += 1
            return []
        return [fix] if fix is not None else []

    def _fix(self, ep: dict, gga, tod: float) -> GnssFix | None:
        q = int(gga.gps_qual or 0)
        if q == 0 or not gga.lat or not gga.lon:
            self.counters["nmea_no_fix"] += 1
            return None
        if self._date is None:
            self.counters["nmea_no_date"] += 1
            return None
        t = calendar.timegm(self._date.timetuple()) + tod
        if self._t_last is not None and t < self._t_last - 43200.0:  # crossed midnight before the next RMC
            t += 86400.0
        self._t_last = t
        lat, lon = math.radians(gga.latitude), math.radians(gga.longitude)
        h = float(gga.altitude) + float(gga.geo_sep or 0.0)
        gst = ep.get("GST")
        if gst is not None and gst.std_dev_latitude and gst.std_dev_longitude:
            sig = np.array([float(gst.std_dev_latitude), float(gst.std_dev_longitude),
                            float(gst.std_dev_altitude or 1.5 * float(gst.std_dev_latitude))])
        else:
            hdop = float(gga.horizontal_dil or 99.0)
            sig = np.array([hdop * self.uere, hdop * self.uere, 1.5 * hdop * self.uere])
        v, sigma_v = np.zeros(3), 100.0  # no velocity: uninformative
        vel = ep.get("RMC") or ep.get("VTG")
        if vel is not None:
            rmc = vel.sentence_type == "RMC"
            sog = vel.spd_over_grnd if rmc else vel.spd_over_grnd_kts
            cog = vel.true_course if rmc else vel.true_track
            if sog is not None and (cog is not None or float(sog) == 0.0):
                s = float(sog) * KNOT
                c = math.radians(float(cog or 0.0))
                v, sigma_v = np.array([s * math.cos(c), s * math.sin(c), 0.0]), self.sigma_v
        if not (np.isfinite([lat, lon, h]).all() and np.isfinite(sig).all() and np.all(sig > 0)):
            self.counters["nmea_bad"] += 1
            return None
        fix = GnssFix(self.vehicle, self._seq, float(t), np.array([lat, lon, h]), v, sig, float(sigma_v), q)
        self._seq += 1
        self.counters["gnss_fixes"] += 1
        return fix
