"""Causal stationarity detection from IMU data (for ZUPT/ZARU gating).

A sample is *stationary* when, over the trailing window that ends at it, the specific-force
magnitude stays close to its mean (no acceleration or vibration from driving) and the mean
angular-rate magnitude is small. Only past samples are used, so the decision is causal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StationaryDetector:
    """Thresholds of the detector (SI units).

    Attributes
    ----------
    window : int
        Number of trailing samples (0.5 s at 100 Hz by default).
    accel_std : float
        Max standard deviation of |f| over the window [m/s²].
    gyro_mean : float
        Max mean |ω| over the window [rad/s].
    """

    window: int = 50
    accel_std: float = 0.1
    gyro_mean: float = np.radians(0.5)

    def detect(self, accel: np.ndarray, gyro: np.ndarray) -> np.ndarray:
        """Boolean per sample, shape (n,), for arrays of shape (n, 3) (any consistent frame)."""
        n = len(accel)
        w = self.window
        fa = np.linalg.norm(accel, axis=1)
        wm = np.linalg.norm(gyro, axis=1)
        c1 = np.concatenate([[0.0], np.cumsum(fa)])
        c2 = np.concatenate([[0.0], np.cumsum(fa * fa)])
        cw = np.concatenate([[0.0], np.cumsum(wm)])
        idx = np.arange(1, n + 1)
        lo = np.maximum(idx - w, 0)
        cnt = idx - lo
        mean = (c1[idx] - c1[lo]) / cnt
        var = np.maximum((c2[idx] - c2[lo]) / cnt - mean * mean, 0.0)
        gmean = (cw[idx] - cw[lo]) / cnt
        out = (np.sqrt(var) < self.accel_std) & (gmean < self.gyro_mean)
        out[: w - 1] = False  # not enough history yet
        return out

    def window_mean_gyro(self, gyro: np.ndarray, k: int) -> np.ndarray:
        """Mean angular rate over the trailing window ending at sample ``k``, shape (3,)."""
        return gyro[max(0, k - self.window + 1): k + 1].mean(axis=0)
