"""Forward camera's lane-marking classes (left and right of the ego lane).

Each side is reported as divider / boundary (see :mod:`geo.lane_markings`), or unseen inside
the junction and in a share ``unseen`` of frames (worn paint, a vehicle alongside). A side's
class is wrong for episodes: a two-state Markov chain per side that is wrong a share ``error``
of the time with a mean episode of ``error_tau`` seconds (the same wear or shadow fools many
frames in a row).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slcp.geo.lane_markings import BOUNDARY, DIVIDER, UNSEEN

from . import params
from .processes import two_state_markov


@dataclass(frozen=True)
class LaneCameraModel:
    """Parameters (SI).

    Attributes
    ----------
    enabled : bool
        Whether the vehicles have the camera (no reports at all if not).
    rate : float
        Report rate [Hz].
    error : float
        Share of time a side's class is reported wrong (divider for boundary or back).
    error_tau : float
        Mean duration of a wrong episode [s].
    unseen : float
        Probability that a frame reports a side as unseen.
    """

    enabled: bool = True
    rate: float = 5.0
    error: float = 0.02
    error_tau: float = 1.0
    unseen: float = 0.05

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ValueError(f"LaneCameraModel.enabled must be true or false, got {self.enabled!r}")
        params.positive(self, "rate", "error_tau")
        params.probability(self, "unseen")
        if not 0.0 <= self.error < 0.5:
            raise ValueError(f"LaneCameraModel.error must be in [0, 0.5), got {self.error!r}")
        if self.rate > 100.0:
            raise ValueError(f"LaneCameraModel.rate must be <= 100 Hz, got {self.rate!r}")


def simulate_markings(model: LaneCameraModel, truth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Reported classes for the true classes ``truth`` ((n, 2) ints, one row per report).

    Returns (n, 2) ints; rows whose truth is unseen stay unseen."""
    truth = np.asarray(truth, dtype=np.int64).reshape(-1, 2)
    n = len(truth)
    out = truth.copy()
    dt = 1.0 / model.rate
    p_exit = min(1.0, dt / model.error_tau)
    p_enter = min(1.0, p_exit * model.error / (1.0 - model.error))
    for side in range(2):
        wrong = two_state_markov(n, p_enter, p_exit, rng) & (truth[:, side] != UNSEEN)
        out[wrong, side] = np.where(truth[wrong, side] == DIVIDER, BOUNDARY, DIVIDER)
        out[rng.random(n) < model.unseen, side] = UNSEEN
    return out
