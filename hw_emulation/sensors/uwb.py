"""UWB two-way ranging between a pair of vehicles (DW1000 class).

Line-of-sight noise; a Markov NLOS state adding a positive bias; rare gross outliers; a success
probability that falls with distance (logistic, ≈95 % at 30 m and 50 % at 100 m by default); no
range beyond ``max_range``. One value per pair and epoch: both ends receive the same range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import params
from .processes import two_state_markov


@dataclass(frozen=True)
class UwbModel:
    """Parameters (SI).

    Attributes
    ----------
    rate : float
        Ranging rate per pair [Hz] (≤ 100).
    sigma_los : float
        LOS range noise [m].
    nlos_enter, nlos_exit : float
        NLOS transition rates [1/s] (mean NLOS duration 1/nlos_exit).
    nlos_bias_min, nlos_bias_max : float
        Positive NLOS bias range [m] (uniform, drawn per NLOS episode).
    outlier_prob : float
        Probability that a delivered range is a gross outlier.
    outlier_min, outlier_max : float
        Outlier magnitude range [m] (added with a random sign, result kept positive).
    d50, d_scale : float
        Logistic success probability ``1 / (1 + exp((d - d50)/d_scale))`` [m].
    max_range : float
        No range beyond this distance [m].
    """

    rate: float = 10.0
    sigma_los: float = 0.07
    nlos_enter: float = 0.02
    nlos_exit: float = 0.2
    nlos_bias_min: float = 0.3
    nlos_bias_max: float = 3.0
    outlier_prob: float = 0.007
    outlier_min: float = 3.0
    outlier_max: float = 30.0
    d50: float = 100.0
    d_scale: float = 70.0 / math.log(19.0)
    max_range: float = 200.0

    def __post_init__(self) -> None:
        params.positive(self, "rate", "d50", "d_scale", "max_range")
        if self.rate > 100.0:
            raise ValueError(f"UwbModel.rate must be <= 100 Hz, got {self.rate!r}")
        params.non_negative(self, "sigma_los", "nlos_enter", "nlos_exit", "nlos_bias_min", "outlier_min")
        params.probability(self, "outlier_prob")
        params.ordered(self, "nlos_bias_min", "nlos_bias_max")
        params.ordered(self, "outlier_min", "outlier_max")

    def success_probability(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, float)
        p = 1.0 / (1.0 + np.exp((d - self.d50) / self.d_scale))
        return np.where(d <= self.max_range, p, 0.0)


@dataclass(frozen=True)
class UwbRanges:
    """Ranges of one pair at epochs ``t``: NaN where no range was obtained.

    ``nlos`` and ``outlier`` flag the injected error types (for evaluating rejection).
    """

    t: np.ndarray
    range: np.ndarray
    true_range: np.ndarray
    nlos: np.ndarray
    outlier: np.ndarray

    @property
    def delivered(self) -> np.ndarray:
        return np.isfinite(self.range)


def simulate_pair(model: UwbModel, t: np.ndarray, true_range: np.ndarray, rng: np.random.Generator) -> UwbRanges:
    """Simulate one vehicle pair's ranges at epochs ``t`` (n,) for true distances (n,) [m]."""
    t = np.asarray(t, float)
    d = np.asarray(true_range, float)
    n = len(t)
    step = float(np.median(np.diff(t))) if n > 1 else 1.0 / model.rate
    nlos = two_state_markov(n, min(1.0, model.nlos_enter * step), min(1.0, model.nlos_exit * step), rng)
    # one bias per NLOS episode
    starts = np.flatnonzero(nlos & ~np.concatenate([[False], nlos[:-1]]))
    episode = np.cumsum(np.isin(np.arange(n), starts))
    bias_per_ep = rng.uniform(model.nlos_bias_min, model.nlos_bias_max, len(starts) + 1)
    bias = np.where(nlos, bias_per_ep[episode], 0.0)
    r = d + bias + rng.normal(0.0, model.sigma_los, n)
    outlier = rng.random(n) < model.outlier_prob
    r = np.where(
        outlier, np.abs(r + rng.choice([-1.0, 1.0], n) * rng.uniform(model.outlier_min, model.outlier_max, n)), r
    )
    ok = rng.random(n) < model.success_probability(d)
    return UwbRanges(t, np.where(ok, r, np.nan), d, nlos & ok, outlier & ok)
