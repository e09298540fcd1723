"""IMU adapter: raw samples of a real IMU to the agent's :class:`~transport.messages.ImuBatch`.

An IMU driver delivers samples ``(t, specific force, angular rate)`` in the *sensor* frame on
its own time stamps. The agent expects increments in the vehicle *body* frame (FRD: x forward,
y right, z down) on the fleet's sensor time. The adapter

1. shifts each time stamp by ``time_offset`` (the IMU's logging delay against GNSS time) [s];
2. rotates the sample into the body frame with the mounting rotation ``mount_rpy`` (roll,
   pitch, yaw of the sensor-to-body rotation, Groves' ``Euler_to_CTM`` convention, as in
   :class:`deploy.replay.ReplayConfig`) [rad];
3. integrates each interval between consecutive samples trapezoidally into ``(dθ, dv)``;
4. groups the intervals into batches of ``batch_period`` seconds (10 Hz by default).

A sample not newer than the previous one is dropped (``imu_out_of_order``); a sample with a
non-finite value is dropped (``imu_bad_sample``); an interval longer than ``max_gap`` is still
integrated (the filter needs a contiguous stream) but counted (``imu_gaps``).

The text line format read by :func:`parse_imu_line` (``slcp sensors --imu csv:…``) is one
sample per line, comma or whitespace separated::

    t, ax, ay, az, gx, gy, gz      # t [s], accelerometer, gyro in the --imu-units
    ax, ay, az, gx, gy, gz         # no time: the host clock at reception is used

Lines starting with ``#`` and empty lines are skipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slcp.agent.nav.rotation import euler_to_dcm
from slcp.transport.messages import ImuBatch

G0 = 9.80665  #: standard gravity, the unit "g" [m/s²]

#: accepted unit names -> factor to SI
ACCEL_UNITS = {"m/s2": 1.0, "g": G0, "mg": 1e-3 * G0}
GYRO_UNITS = {"rad/s": 1.0, "deg/s": math.pi / 180.0, "mrad/s": 1e-3}


class ImuFormatError(ValueError):
    """A line of IMU text cannot be read as a sample."""


def imu_increments(t: np.ndarray, accel_s: np.ndarray, gyro_s: np.ndarray, c_sb: np.ndarray):
    """Trapezoidal increments over each sample interval, rotated to the body frame.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Sample times [s].
    accel_s, gyro_s : ndarray, shape (n, 3)
        Specific force [m/s²] and angular rate [rad/s] in the sensor frame.
    c_sb : ndarray, shape (3, 3)
        Sensor-to-body rotation (``v_b = c_sb @ v_s``).

    Returns
    -------
    dtheta, dvel : ndarray, shape (n-1, 3)
        Angle [rad] and velocity [m/s] increments in the body frame.
    dt : ndarray, shape (n-1,)
        Interval lengths [s].
    """
    dt = np.diff(t)
    w_b = gyro_s @ c_sb.T
    f_b = accel_s @ c_sb.T
    dtheta = 0.5 * (w_b[1:] + w_b[:-1]) * dt[:, None]
    dvel = 0.5 * (f_b[1:] + f_b[:-1]) * dt[:, None]
    return dtheta, dvel, dt


def parse_units(text: str) -> tuple[float, float]:
    """``"ACCEL,GYRO"`` unit names (e.g. ``"g,deg/s"``) -> SI factors."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or parts[0] not in ACCEL_UNITS or parts[1] not in GYRO_UNITS:
        raise ValueError(f"IMU units {text!r}: expected ACCEL,GYRO with ACCEL in "
                         f"{'|'.join(ACCEL_UNITS)} and GYRO in {'|'.join(GYRO_UNITS)}")
    return ACCEL_UNITS[parts[0]], GYRO_UNITS[parts[1]]


def parse_imu_line(line: str, accel_unit: float = 1.0, gyro_unit: float = 1.0,
                   host_time: float | None = None) -> tuple[float, np.ndarray, np.ndarray] | None:
    """One text line -> ``(t [s], accel [m/s²] (3,), gyro [rad/s] (3,))``; None for a comment.

    Raises :class:`ImuFormatError` for anything else that is not a sample.
    """
    s = line.strip()
    if not s or s.startswith("#"):
        return None
    parts = s.replace(",", " ").split()
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ImuFormatError(f"not numbers: {s[:60]!r}") from None
    if len(vals) == 7:
        t = vals[0]
        vals = vals[1:]
    elif len(vals) == 6 and host_time is not None:
        t = host_time
    else:
        raise ImuFormatError(f"expected 7 columns (t, ax, ay, az, gx, gy, gz) or 6 without time, got {len(vals)}")
    a = np.array(vals[:3]) * accel_unit
    g = np.array(vals[3:]) * gyro_unit
    if not (math.isfinite(t) and np.all(np.isfinite(a)) and np.all(np.isfinite(g))):
        raise ImuFormatError("non-finite value")
    return t, a, g


@dataclass
class ImuAdapter:
    """Samples in, :class:`ImuBatch` out (see the module docstring).

    Parameters
    ----------
    vehicle : str
        Vehicle id of the batches.
    mount_rpy : tuple of float
        Sensor-to-body rotation as roll, pitch, yaw [rad].
    time_offset : float
        Added to every sample time [s].
    batch_period : float
        A batch is emitted once it spans this long [s].
    max_gap : float
        Intervals longer than this are counted as gaps [s].
    """

    vehicle: str
    mount_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    time_offset: float = 0.0
    batch_period: float = 0.1
    max_gap: float = 0.1
    counters: dict[str, int] = field(default_factory=lambda: {
        "imu_samples": 0, "imu_batches": 0, "imu_out_of_order": 0, "imu_bad_sample": 0, "imu_gaps": 0})

    def __post_init__(self) -> None:
        self._c_sb = euler_to_dcm(*self.mount_rpy).T
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None  # previous sample, body frame
        self._rows: list[tuple[float, float, np.ndarray, np.ndarray]] = []  # (t, dt, dθ, dv)
        self._seq = 0

    def push(self, t: float, accel_s: np.ndarray, gyro_s: np.ndarray) -> list[ImuBatch]:
        """Add one sample (sensor frame, SI); returns the batches completed by it (0 or 1)."""
        t = float(t) + self.time_offset
        a = np.asarray(accel_s, float)
        g = np.asarray(gyro_s, float)
        if (
            a.shape != (3,)
            or g.shape != (3,)
            or not (math.isfinite(t) and np.isfinite(a).all() and np.isfinite(g).all())
        ):
            self.counters["imu_bad_sample"] += 1
            return []
        f_b, w_b = self._c_sb @ a, self._c_sb @ g
        prev = self._last
        if prev is not None and t <= prev[0]:
            self.counters["imu_out_of_order"] += 1
            return []
        self._last = (t, f_b, w_b)
        self.counters["imu_samples"] += 1
        if prev is None:
            return []
        dt = t - prev[0]
        if dt > self.max_gap:
            self.counters["imu_gaps"] += 1
        self._rows.append((t, dt, 0.5 * (w_b + prev[2]) * dt, 0.5 * (f_b + prev[1]) * dt))
        if t - (self._rows[0][0] - self._rows[0][1]) >= self.batch_period - 1e-9:
            return [self.flush()]
        return []

    def push_many(self, t: np.ndarray, accel_s: np.ndarray, gyro_s: np.ndarray) -> list[ImuBatch]:
        """Add samples (n,), (n, 3), (n, 3); returns the completed batches. A clean stretch (finite,
        strictly increasing times) is taken at once, the same batches as sample by sample."""
        t = np.asarray(t, float) + self.time_offset
        a, g = np.asarray(accel_s, float), np.asarray(gyro_s, float)
        clean = (len(t) > 1 and a.shape == (len(t), 3) and g.shape == (len(t), 3)
                 and bool(np.isfinite(t).all() and np.isfinite(a).all() and np.isfinite(g).all())
                 and bool(np.all(np.diff(t) > 0)) and (self._last is None or t[0] > self._last[0]))
        if not clean:
            out: list[ImuBatch] = []
            for k in range(len(t)):
                out.extend(self.push(t[k] - self.time_offset, a[k], g[k]))
            return out
        return self._push_clean(t, a @ self._c_sb.T, g @ self._c_sb.T)

    def _push_clean(self, t: np.ndarray, f_b: np.ndarray, w_b: np.ndarray) -> list[ImuBatch]:
        """:meth:`push_many` of finite samples after the last one, in increasing time (body frame)."""
        if self._last is not None:  # the interval from the previous sample
            t = np.r_[self._last[0], t]
            f_b, w_b = np.vstack([self._last[1], f_b]), np.vstack([self._last[2], w_b])
            new = len(t) - 1
        else:
            new = len(t)
        self.counters["imu_samples"] += new
        self._last = (float(t[-1]), f_b[-1].copy(), w_b[-1].copy())
        dt = np.diff(t)
        self.counters["imu_gaps"] += int(np.count_nonzero(dt > self.max_gap))
        dth = 0.5 * (w_b[1:] + w_b[:-1]) * dt[:, None]
        dv = 0.5 * (f_b[1:] + f_b[:-1]) * dt[:, None]
        out: list[ImuBatch] = []
        start = self._rows[0][0] - self._rows[0][1] if self._rows else None
        first = 0  # first row of the batch being filled (rows pending from before come first)
        ends = t[1:].tolist()
        for k, te in enumerate(ends):
            if start is None:
                start = te - float(dt[k])
            if te - start >= self.batch_period - 1e-9:
                out.append(self._batch(ends[first:k + 1], dt[first:k + 1], dth[first:k + 1], dv[first:k + 1]))
                first, start = k + 1, None
        self._rows += [(ends[k], float(dt[k]), dth[k], dv[k]) for k in range(first, len(ends))]
        return out

    def _batch(self, t: list[float], dt: np.ndarray, dth: np.ndarray, dv: np.ndarray) -> ImuBatch:
        """A batch of the pending rows followed by these intervals."""
        rows, self._rows = self._rows, []
        b = ImuBatch(self.vehicle, self._seq, np.array([r[0] for r in rows] + list(t)),
                     np.r_[[r[1] for r in rows], dt], np.vstack([np.array([r[2] for r in rows]).reshape(-1, 3), dth]),
                     np.vstack([np.array([r[3] for r in rows]).reshape(-1, 3), dv]))
        self._seq += 1
        self.counters["imu_batches"] += 1
        return b

    def flush(self) -> ImuBatch | None:
        """The pending intervals as a batch (None if there are none)."""
        if not self._rows:
            return None
        rows, self._rows = self._rows, []
        b = ImuBatch(self.vehicle, self._seq, np.array([r[0] for r in rows]), np.array([r[1] for r in rows]),
                     np.array([r[2] for r in rows]), np.array([r[3] for r in rows]))
        self._seq += 1
        self.counters["imu_batches"] += 1
        return b
