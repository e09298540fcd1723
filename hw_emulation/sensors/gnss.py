"""Urban GNSS position/velocity error model.

Error = white noise + per-vehicle Gauss-Markov multipath (long correlation time when static)
+ a common-mode part shared by nearby vehicles (passed in, one realisation per scenario)
+ NLOS jump events (a bias of 5-50 m lasting 5-60 s) ; fixes are missing during outages. The
receiver's *reported* σ follows the white + multipath level with a random mis-scaling and does not
know about NLOS biases, as real receivers' σ is imperfect. Its reported velocity σ does see the
extra Doppler noise of NLOS epochs (receivers scale it from the Doppler residuals and C/N0),
with the same mis-scaling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import params
from .processes import gauss_markov, gauss_markov_varying


@dataclass(frozen=True)
class GnssModel:
    """Parameters (SI). Horizontal values apply per north/east axis; vertical ones to down.

    Attributes
    ----------
    rate : float
        Fix rate [Hz].
    white_h, white_v : float
        White position noise [m].
    multipath_h, multipath_v : float
        Multipath Gauss-Markov standard deviation [m].
    multipath_tau_moving, multipath_tau_static : float
        Multipath correlation time while moving / standing still [s].
    nlos_rate : float
        NLOS events per second (Poisson).
    nlos_bias_min, nlos_bias_max : float
        Horizontal NLOS bias magnitude range [m] (uniform, random direction).
    nlos_duration_min, nlos_duration_max : float
        NLOS event duration range [s] (uniform).
    outage_rate : float
        Outages per second (Poisson).
    outage_duration_min, outage_duration_max : float
        Outage duration range [s].
    velocity_white : float
        White velocity noise [m/s] per axis.
    velocity_nlos : float
        Extra velocity noise during NLOS [m/s].
    sigma_misscale : float
        Log-normal σ of the factor between reported and true (white + multipath) σ.
    """

    rate: float = 5.0
    white_h: float = 0.5
    white_v: float = 0.8
    multipath_h: float = 2.0
    multipath_v: float = 3.0
    multipath_tau_moving: float = 30.0
    multipath_tau_static: float = 300.0
    nlos_rate: float = 1.0 / 120.0
    nlos_bias_min: float = 5.0
    nlos_bias_max: float = 50.0
    nlos_duration_min: float = 5.0
    nlos_duration_max: float = 60.0
    outage_rate: float = 1.0 / 300.0
    outage_duration_min: float = 2.0
    outage_duration_max: float = 20.0
    velocity_white: float = 0.05
    velocity_nlos: float = 0.3
    sigma_misscale: float = 0.3

    def __post_init__(self) -> None:
        params.positive(self, "rate", "multipath_tau_moving", "multipath_tau_static")
        params.non_negative(self, "white_h", "white_v", "multipath_h", "multipath_v", "nlos_rate",
                            "nlos_bias_min", "nlos_duration_min", "outage_rate", "outage_duration_min",
                            "velocity_white", "velocity_nlos", "sigma_misscale")
        params.ordered(self, "nlos_bias_min", "nlos_bias_max")
        params.ordered(self, "nlos_duration_min", "nlos_duration_max")
        params.ordered(self, "outage_duration_min", "outage_duration_max")


@dataclass(frozen=True)
class GnssErrors:
    """Per-epoch GNSS errors (measured = truth + error), all NED.

    Attributes
    ----------
    t : ndarray, shape (n,)
    pos_error : ndarray, shape (n, 3) [m]
    vel_error : ndarray, shape (n, 3) [m/s]
    reported_sigma : ndarray, shape (n, 3)
        What the receiver claims (position σ per axis) [m].
    reported_sigma_v : ndarray, shape (n,)
        What the receiver claims for the velocity (σ per axis) [m/s].
    valid : ndarray of bool, shape (n,)
        False during outages (no fix delivered).
    nlos : ndarray of bool, shape (n,)
        True while an NLOS bias is present.
    """

    t: np.ndarray
    pos_error: np.ndarray
    vel_error: np.ndarray
    reported_sigma: np.ndarray
    reported_sigma_v: np.ndarray
    valid: np.ndarray
    nlos: np.ndarray


def _events(t: np.ndarray, rate: float, dmin: float, dmax: float, rng: np.random.Generator):
    """Poisson event windows [start, end) over the span of ``t``."""
    span = float(t[-1] - t[0]) if len(t) else 0.0
    n = rng.poisson(rate * span) if rate > 0 and span > 0 else 0
    starts = np.sort(t[0] + rng.random(n) * span)
    return starts, starts + rng.uniform(dmin, dmax, n)


def common_mode_error(t: np.ndarray, sigma: float, tau: float, rng: np.random.Generator) -> np.ndarray:
    """Common-mode (atmosphere/ephemeris-like) error shared by nearby vehicles, shape (n, 3) [m]."""
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    e = gauss_markov(len(t), dt, sigma, tau, rng, 3)
    e[:, 2] *= 1.5
    return e


def simulate_gnss(model: GnssModel, t: np.ndarray, moving: np.ndarray, rng: np.random.Generator,
                  common_mode: np.ndarray | None = None) -> GnssErrors:
    """Errors of one receiver at epochs ``t`` (n,); ``moving`` (n,) selects the multipath τ."""
    t = np.asarray(t, float)
    n = len(t)
    dt = np.diff(t, prepend=t[0] - 1.0 / model.rate) if n else t
    tau = np.where(np.asarray(moving, bool), model.multipath_tau_moving, model.multipath_tau_static)
    mp = gauss_markov_varying(dt, 1.0, tau, rng, 3) * np.array(
        [model.multipath_h, model.multipath_h, model.multipath_v]
    )
    white = rng.normal(0.0, 1.0, (n, 3)) * np.array([model.white_h, model.white_h, model.white_v])
    err = mp + white
    if common_mode is not None:
        err = err + common_mode
    nlos = np.zeros(n, bool)
    starts, ends = _events(t, model.nlos_rate, model.nlos_duration_min, model.nlos_duration_max, rng)
    for s, e in zip(starts, ends):
        m = (t >= s) & (t < e)
        mag = rng.uniform(model.nlos_bias_min, model.nlos_bias_max)
        ang = rng.uniform(0.0, 2.0 * math.pi)
        err[m] += np.array([mag * math.cos(ang), mag * math.sin(ang), -0.3 * mag])
        nlos |= m
    valid = np.ones(n, bool)
    starts, ends = _events(t, model.outage_rate, model.outage_duration_min, model.outage_duration_max, rng)
    for s, e in zip(starts, ends):
        valid &= ~((t >= s) & (t < e))
    vel = rng.normal(0.0, model.velocity_white, (n, 3))
    vel[nlos] += rng.normal(0.0, model.velocity_nlos, (int(nlos.sum()), 3))
    level = np.sqrt(np.array([model.white_h, model.white_h, model.white_v]) ** 2
                    + np.array([model.multipath_h, model.multipath_h, model.multipath_v]) ** 2)
    factor = np.exp(rng.normal(0.0, model.sigma_misscale, (n, 1)))
    sigma_v = np.hypot(model.velocity_white, np.where(nlos, model.velocity_nlos * factor[:, 0], 0.0))
    return GnssErrors(t, err, vel, level * factor, np.maximum(sigma_v, 0.02), valid, nlos)
