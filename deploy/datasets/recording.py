"""A recording as every reader returns it: IMU samples and GNSS epochs in SI units.

Readers (:mod:`.formats`) convert their file's units and conventions here, at the edge; what the
vehicle's installation does to the data (the IMU's mount, its time offset, the height type) is
the vehicle profile's, applied by the replay.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import DatasetError


@dataclass(frozen=True)
class ImuLog:
    """IMU samples: time [s], specific force [m/s²] and angular rate [rad/s] in the sensor frame."""

    t: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray


@dataclass(frozen=True)
class GnssLog:
    """GNSS solution epochs.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Epoch time [s], on the IMU's time scale.
    llh : ndarray, shape (n, 3)
        Latitude, longitude [rad] and height [m] *as the receiver reports it* (the profile says
        whether it is ellipsoidal or above mean sea level).
    quality : ndarray, shape (n,)
        1 fixed RTK, 2 float RTK, anything else a code solution (RTKLIB's Q flag).
    n_sat : ndarray, shape (n,)
        Satellites used (0 when unknown).
    sd_neu : ndarray, shape (n, 3)
        Position standard deviations north, east, up [m].
    v_ned : ndarray, shape (n, 3)
        Velocity north, east, down [m/s]; NaN where the receiver reported none.
    sd_v : ndarray, shape (n, 3)
        Velocity standard deviations [m/s]; NaN where there is no velocity.
    """

    t: np.ndarray
    llh: np.ndarray
    quality: np.ndarray
    n_sat: np.ndarray
    sd_neu: np.ndarray
    v_ned: np.ndarray
    sd_v: np.ndarray

    @property
    def has_velocity(self) -> np.ndarray:
        """(n,) bool: the epoch carries a velocity."""
        return np.all(np.isfinite(self.v_ned), axis=1) & np.all(np.isfinite(self.sd_v), axis=1)

    def select(self, keep: np.ndarray) -> GnssLog:
        """The epochs where ``keep`` (a mask or indices)."""
        return GnssLog(self.t[keep], self.llh[keep], self.quality[keep], self.n_sat[keep], self.sd_neu[keep],
                       self.v_ned[keep], self.sd_v[keep])

    def position_only(self) -> GnssLog:
        """The same epochs without their velocities."""
        nan = np.full_like(self.v_ned, np.nan)
        return GnssLog(self.t, self.llh, self.quality, self.n_sat, self.sd_neu, nan, nan.copy())


@dataclass(frozen=True)
class Recording:
    """One vehicle's recorded IMU and GNSS."""

    imu: ImuLog
    gnss: GnssLog


def gnss_log(t, lat_deg, lon_deg, h, sd_neu, v_ned=None, sd_v=None, quality=None, n_sat=None,
             source: str = "<gnss>") -> GnssLog:
    """A checked :class:`GnssLog` from columns (degrees at the edge; velocity optional)."""
    t = np.asarray(t, float)
    n = len(t)
    if n < 2:
        raise DatasetError(f"{source}: fewer than 2 GNSS epochs")
    if np.any(np.diff(t) <= 0):
        raise DatasetError(f"{source}: GNSS epochs are not in increasing time order")
    llh = np.column_stack([np.radians(np.asarray(lat_deg, float)), np.radians(np.asarray(lon_deg, float)),
                           np.asarray(h, float)])
    sd = np.asarray(sd_neu, float).reshape(n, 3)
    if not (np.all(np.isfinite(llh)) and np.all(np.isfinite(sd)) and np.all(sd >= 0)):
        raise DatasetError(f"{source}: non-finite positions or negative σ")
    if np.any(np.abs(llh[:, 0]) > np.pi / 2):
        raise DatasetError(f"{source}: latitude outside ±90°")
    v = np.full((n, 3), np.nan) if v_ned is None else np.asarray(v_ned, float).reshape(n, 3)
    sv = np.full((n, 3), np.nan) if sd_v is None else np.asarray(sd_v, float).reshape(n, 3)
    q = np.ones(n, int) if quality is None else np.asarray(quality).astype(int)
    ns = np.zeros(n, int) if n_sat is None else np.asarray(n_sat).astype(int)
    return GnssLog(t, llh, q, ns, sd, v, sv)


def imu_log(t, accel, gyro, source: str = "<imu>") -> ImuLog:
    """A checked :class:`ImuLog` (SI units)."""
    t = np.asarray(t, float)
    a = np.asarray(accel, float).reshape(len(t), 3)
    g = np.asarray(gyro, float).reshape(len(t), 3)
    if len(t) < 100:
        raise DatasetError(f"{source}: only {len(t)} IMU samples")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(a)) and np.all(np.isfinite(g))):
        raise DatasetError(f"{source}: non-finite values in IMU data")
    if np.any(np.diff(t) <= 0):
        raise DatasetError(f"{source}: IMU times are not strictly increasing")
    return ImuLog(t, a, g)


def rates_from_increments(t, d_theta, d_vel, source: str = "<imu>") -> ImuLog:
    """Increments over the interval ending at each stamp -> mean rates over it; the first
    sample, whose interval is unknown, is dropped."""
    t = np.asarray(t, float)
    dt = np.diff(t)
    if len(t) and np.any(dt <= 0):
        raise DatasetError(f"{source}: IMU times are not strictly increasing")
    dth = np.asarray(d_theta, float).reshape(len(t), 3)[1:]
    dv = np.asarray(d_vel, float).reshape(len(t), 3)[1:]
    return imu_log(t[1:], dv / dt[:, None], dth / dt[:, None], source)
