"""V2V radio channel: Bernoulli and Gilbert-Elliott packet loss, latency with jitter, rare stale
deliveries and a maximum range. Loopback Zenoh loses nothing, so all V2V loss comes from here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import params
from .processes import two_state_markov


@dataclass(frozen=True)
class RadioModel:
    """Parameters (SI). Transition probabilities are per packet.

    Attributes
    ----------
    loss : float
        Bernoulli loss probability in the good state.
    ge_p_good_to_bad, ge_p_bad_to_good : float
        Gilbert-Elliott transitions per packet (0 disables the bad state).
    ge_loss_bad : float
        Loss probability in the bad state.
    latency_min, latency_max : float
        Latency bounds [s]; latency = min + exponential jitter, clipped to max.
    jitter_mean : float
        Mean of the exponential jitter [s].
    stale_prob : float
        Probability that a delivered packet is held back 100-300 ms (``stale_min``-``stale_max``).
    stale_min, stale_max : float
        The range of a stale packet's extra delay [s].
    max_range : float
        No delivery beyond this distance [m].
    max_tx_rate : float
        Packets a station may transmit per second [1/s], with a burst of one second's worth: the
        channel's decentralised congestion control (ETSI TS 102 687: at least 25 ms between a
        station's packets when the channel is relaxed, 40 per second) keeps any one station,
        a faulty or hostile one too, from taking the channel. slcp's vehicles send 5 Hz per
        method, 20 per second with all four.
    """

    loss: float = 0.05
    ge_p_good_to_bad: float = 0.01
    ge_p_bad_to_good: float = 0.2
    ge_loss_bad: float = 0.8
    latency_min: float = 0.001
    latency_max: float = 0.020
    jitter_mean: float = 0.003
    stale_prob: float = 0.002
    stale_min: float = 0.100
    stale_max: float = 0.300
    max_range: float = 300.0
    max_tx_rate: float = 40.0

    def __post_init__(self) -> None:
        params.probability(self, "loss", "ge_p_good_to_bad", "ge_p_bad_to_good", "ge_loss_bad", "stale_prob")
        params.non_negative(self, "latency_min", "jitter_mean", "stale_min")
        params.positive(self, "max_range", "max_tx_rate")
        params.ordered(self, "latency_min", "latency_max")
        params.ordered(self, "stale_min", "stale_max")

    def expected_loss(self) -> float:
        """Long-run loss probability within range (stationary Gilbert-Elliott mixture)."""
        g2b, b2g = self.ge_p_good_to_bad, self.ge_p_bad_to_good
        pb = g2b / (g2b + b2g) if g2b + b2g > 0 else 0.0
        return (1 - pb) * self.loss + pb * self.ge_loss_bad


@dataclass(frozen=True)
class Deliveries:
    """Fate of a sequence of packets on one directed link."""

    t_send: np.ndarray
    delivered: np.ndarray
    t_arrive: np.ndarray
    bad_state: np.ndarray
    stale: np.ndarray


def simulate_link(model: RadioModel, t_send: np.ndarray, distance: np.ndarray, rng: np.random.Generator) -> Deliveries:
    """Simulate packets sent at ``t_send`` (n,) over distances (n,) [m] on one directed link."""
    t_send = np.asarray(t_send, float)
    n = len(t_send)
    bad = two_state_markov(n, model.ge_p_good_to_bad, model.ge_p_bad_to_good, rng)
    p_loss = np.where(bad, model.ge_loss_bad, model.loss)
    delivered = (rng.random(n) >= p_loss) & (np.asarray(distance, float) <= model.max_range)
    latency = np.minimum(model.latency_min + rng.exponential(model.jitter_mean, n), model.latency_max) \
        if model.jitter_mean > 0 else np.full(n, model.latency_min)
    stale = delivered & (rng.random(n) < model.stale_prob)
    latency = np.where(stale, rng.uniform(model.stale_min, model.stale_max, n), latency)
    return Deliveries(t_send, delivered, np.where(delivered, t_send + latency, np.nan), bad, stale)
