"""Causal stationarity detection from IMU data (for ZUPT/ZARU gating).

A sample is *stationary* when, over the trailing window that ends at it, the specific-force
magnitude stays close to its mean (no acceleration or vibration from driving) and the mean
angular-rate magnitude is small. Only past samples are used, so the decision is causal.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


class StationarityMonitor:
    """Streaming stationarity test on IMU increments (causal, pure).

    Over a trailing window of ``window`` samples the vehicle is at rest when the mean angular
    rate is below ``gyro_mean`` [rad/s], the specific-force magnitude varies by less than
    ``accel_std`` [m/s²], and the mean *horizontal* specific force in the navigation frame is
    below ``horizontal_accel`` [m/s²]. The last test is what tells rest from a constant
    acceleration (whose specific force is as steady as gravity alone).
    """

    def __init__(self, window: int = 50, gyro_mean: float = np.radians(0.5), accel_std: float = 0.1,
                 horizontal_accel: float = 0.25) -> None:
        from collections import deque

        self.window = window
        self.gyro_mean = gyro_mean
        self.accel_std = accel_std
        self.horizontal_accel = horizontal_accel
        self._w: deque[float] = deque(maxlen=window)
        self._f: deque[float] = deque(maxlen=window)
        self._fn: deque[tuple[float, float]] = deque(maxlen=window)

    def push(self, dtheta: np.ndarray, dvel: np.ndarray, dt: float, c_bn: np.ndarray) -> None:
        """Add one IMU interval (increments [rad], [m/s] over ``dt`` s, body-to-NED DCM ``c_bn``);
        :attr:`stationary` tells whether the window shows rest."""
        w = np.asarray(dtheta, float) / dt
        f = np.asarray(dvel, float) / dt
        fn = c_bn @ f
        self._w.append(float(np.linalg.norm(w)))
        self._f.append(float(np.linalg.norm(f)))
        self._fn.append((float(fn[0]), float(fn[1])))

    def push_batch(self, dtheta: np.ndarray, dvel: np.ndarray, dt: np.ndarray, c_bn: np.ndarray) -> None:
        """Add consecutive IMU intervals at once: ``dtheta`` [rad], ``dvel`` [m/s] shape (n, 3),
        ``dt`` [s] shape (n,), resolved with one body-to-NED DCM ``c_bn`` (3, 3) (the attitude
        of a batch of a tenth of a second is one for this test). Same as ``n`` calls of
        :meth:`push` with that DCM."""
        inv = 1.0 / np.asarray(dt, float)[:, None]
        w = np.asarray(dtheta, float) * inv
        f = np.asarray(dvel, float) * inv
        fn = f @ c_bn[:2].T
        self._w.extend(np.sqrt(np.einsum("ij,ij->i", w, w)).tolist())
        self._f.extend(np.sqrt(np.einsum("ij,ij->i", f, f)).tolist())
        self._fn.extend(map(tuple, fn.tolist()))

    @property
    def stationary(self) -> bool:
        if len(self._w) < self.window:
            return False
        fn = np.mean(np.array(self._fn), axis=0)
        return (float(np.mean(self._w)) < self.gyro_mean and float(np.std(self._f)) < self.accel_std
                and float(np.hypot(fn[0], fn[1])) < self.horizontal_accel)


class ZuptGate:
    """When a vehicle filter should apply a zero-velocity update.

    GNSS Doppler already pins the velocity while fixes arrive, so ZUPT is for stops without
    GNSS: no fix came for ``gnss_gap`` s, the IMU window shows rest, and the filter's own speed
    is below ``max_speed`` [m/s] by ``k_sigma`` of its standard deviation. The last condition
    matters: to an IMU without vibration, cruising or creeping at constant speed looks like
    rest, but the INS velocity still says "moving" (it integrated the deceleration of a real
    stop) -- if the filter is sure of it: after a long GNSS outage a creeping vehicle's INS
    speed can be below the threshold with a σ larger than it, and a ZUPT then would shrink a
    position σ of metres around an error of metres that every later fix fails the χ² gate on.
    At most once per ``interval`` s.
    """

    def __init__(self, gnss_gap: float = 0.5, max_speed: float = 1.0, interval: float = 0.1,
                 k_sigma: float = 2.0) -> None:
        self.gnss_gap = gnss_gap
        self.max_speed = max_speed
        self.interval = interval
        self.k_sigma = k_sigma
        self._gnss_t = -np.inf
        self._last = -np.inf

    def gnss(self, t: float) -> None:
        """A GNSS fix arrived for time ``t`` [s]."""
        self._gnss_t = max(self._gnss_t, t)

    def due(self, t: float, monitor: StationarityMonitor, filter_speed: float,
            speed_sigma: Callable[[], float] | float = 0.0) -> bool:
        """Whether to apply ZUPT at time ``t`` [s], given the filter's horizontal speed [m/s]
        and its standard deviation [m/s] (a number, or a function evaluated only if needed, as
        is the IMU window)."""
        if (t - self._last < self.interval or t - self._gnss_t < self.gnss_gap
                or filter_speed >= self.max_speed or not monitor.stationary):
            return False
        sigma = speed_sigma() if callable(speed_sigma) else speed_sigma
        if filter_speed + self.k_sigma * sigma >= self.max_speed:
            return False
        self._last = t
        return True


def speed_sigma(v_ned: np.ndarray, cov_v: np.ndarray) -> float:
    """Standard deviation [m/s] of the horizontal speed of velocity ``v_ned`` (3,) [m/s] with
    error covariance ``cov_v`` (3, 3) [m²/s²]: along the velocity, or the larger horizontal
    axis when the speed is near zero."""
    vh = np.asarray(v_ned, float)[:2]
    c = np.asarray(cov_v, float)[:2, :2]
    n = float(np.hypot(vh[0], vh[1]))
    if n < 1e-6:
        return float(np.sqrt(np.linalg.eigvalsh(c)[-1]))
    u = vh / n
    return float(np.sqrt(max(float(u @ c @ u), 0.0)))
