"""Gates on UWB ranges (pure logic): a physical range-rate gate, one track per neighbour, an
NLOS classifier (:meth:`NlosModel.classify`) and a per-link NLOS tracker
(:class:`NlosLinkTracker`) that follows each link's bias episodes from the range series itself.

A gross UWB outlier (3-30 m) is an isolated jump in range that the two vehicles' motion cannot
explain. The gate predicts the range from the last accepted one and the relative velocity along
the line of sight, and rejects a range that differs from the prediction by more than
``max_jump + k σ_rate Δt`` -- unless it agrees with the range rejected just before it: a jump
that persists is a change of level (the start or end of an NLOS bias, a reference that was
itself wrong), and the track restarts there. So an isolated outlier costs one range, and a level
change costs one range too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


@dataclass
class RangeRateGate:
    """Parameters (SI units) and per-neighbour state.

    Attributes
    ----------
    max_jump : float
        Allowed difference from the predicted range at zero elapsed time [m].
    sigma_rate : float
        Uncertainty of the predicted range rate [m/s] (velocity errors of both vehicles).
    k : float
        Gate width in σ.
    max_gap : float
        A track older than this [s] is restarted rather than extrapolated.
    """

    max_jump: float = 0.6
    sigma_rate: float = 0.5
    k: float = 3.0
    max_gap: float = 2.0
    _last: dict[str, tuple[float, float]] = field(default_factory=dict)
    _rejected: dict[str, tuple[float, float]] = field(default_factory=dict)

    def _agrees(self, ref: tuple[float, float] | None, t: float, measured: float, range_rate: float) -> bool:
        if ref is None or abs(t - ref[0]) > self.max_gap:
            return ref is None
        predicted = ref[1] + range_rate * (t - ref[0])
        return abs(measured - predicted) <= self.max_jump + self.k * self.sigma_rate * abs(t - ref[0])

    def check(self, neighbour: str, t: float, measured: float, range_rate: float) -> bool:
        """True if ``measured`` [m] at time ``t`` [s] is plausible given this neighbour's track and
        the predicted range rate [m/s]; the track is updated."""
        last = self._last.get(neighbour)
        stale = last is not None and abs(t - last[0]) > self.max_gap
        if stale or self._agrees(last, t, measured, range_rate) or \
                (neighbour in self._rejected and self._agrees(self._rejected[neighbour], t, measured, range_rate)):
            self._last[neighbour] = (t, measured)
            self._rejected.pop(neighbour, None)
            return True
        self._rejected[neighbour] = (t, measured)
        return False

    def forget(self, neighbour: str) -> None:
        self._last.pop(neighbour, None)
        self._rejected.pop(neighbour, None)


_SQRT2 = math.sqrt(2.0)
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def _cdf_between(a: float, b: float) -> float:
    """P(a < X < b) for a standard normal X, accurate in both tails."""
    if a >= 0.0:
        return 0.5 * (math.erfc(a / _SQRT2) - math.erfc(b / _SQRT2))
    if b <= 0.0:
        return 0.5 * (math.erfc(-b / _SQRT2) - math.erfc(-a / _SQRT2))
    return 1.0 - 0.5 * (math.erfc(-a / _SQRT2) + math.erfc(b / _SQRT2))


def _log_normal(x: float, var: float) -> float:
    """log N(x; 0, var)."""
    var = max(var, 1e-12)
    return -0.5 * x * x / var - 0.5 * math.log(var) - _LOG_SQRT_2PI


def _log_lower_tail(x: float) -> float:
    """log Φ(x) for a standard normal, x ≤ -30 (where Φ underflows), by its asymptotic series
    (relative error below 1e-7 there). An agent process loads no scipy (its memory budget)."""
    x2 = x * x
    return -0.5 * x2 - math.log(-x) - _LOG_SQRT_2PI + math.log1p(-1.0 / x2 + 3.0 / (x2 * x2))


@dataclass(frozen=True)
class NlosModel:
    """A UWB link's NLOS state: a two-state Markov chain (entered at ``enter`` [1/s], left at
    ``exit`` [1/s]) adding a positive range bias drawn uniformly in [``bias_min``, ``bias_max``]
    [m] per episode (the emulator's model, :mod:`hw_emulation.sensors.uwb`; a receiver's
    characteristic to calibrate on a real fleet)."""

    enter: float
    exit: float
    bias_min: float
    bias_max: float
    #: probability that a range is a gross outlier, and the outlier's size range [m] (added
    #: with either sign); 0 leaves outliers to :class:`RangeRateGate`
    outlier_prob: float = 0.0
    outlier_min: float = 3.0
    outlier_max: float = 30.0

    def __post_init__(self) -> None:
        if not (self.enter > 0.0 and self.exit > 0.0 and 0.0 <= self.bias_min < self.bias_max
                and 0.0 <= self.outlier_prob < 1.0 and 0.0 <= self.outlier_min < self.outlier_max):
            raise ValueError(f"invalid NLOS model {self}")

    @property
    def steady(self) -> float:
        """Share of time a link spends in NLOS."""
        return self.enter / (self.enter + self.exit)

    @property
    def bias_mean(self) -> float:
        """E[b] of an episode's bias [m]."""
        return 0.5 * (self.bias_min + self.bias_max)

    @property
    def bias_mean_square(self) -> float:
        """E[b²] of an episode's bias [m²]."""
        a, b = self.bias_min, self.bias_max
        return (a * a + a * b + b * b) / 3.0

    def log_bias_likelihood(self, nu: float, var: float) -> float:
        """log of ∫ U(b) N(nu − b; 0, var) db: the density of an innovation ``nu`` [m] that
        carries a fresh bias on top of a zero-mean error of variance ``var`` [m²]."""
        s = math.sqrt(max(var, 1e-12))
        lo, hi = (self.bias_min - nu) / s, (self.bias_max - nu) / s
        z = _cdf_between(lo, hi)
        if z > 1e-300:
            log_z = math.log(z)
        else:  # the innovation is many σ from every bias: in logarithms
            log_z = _log_lower_tail(hi) if hi < 0.0 else _log_lower_tail(-lo)
        return log_z - math.log(self.bias_max - self.bias_min)

    def posterior(self, prior: float, nu: float, var: float) -> float:
        """Probability that a range is NLOS.

        Parameters
        ----------
        prior : float
            Probability of NLOS before the range.
        nu : float
            Innovation [m], measured minus predicted range (an NLOS bias makes it positive).
        var : float
            Innovation variance without any NLOS bias [m²]: the two positions' uncertainty
            along the line of sight plus the UWB noise.
        """
        if prior <= 0.0 or prior >= 1.0:
            return float(prior >= 1.0)
        log_los = _log_normal(nu, var)
        log_nlos = self.log_bias_likelihood(nu, var)
        x = math.log1p(-prior) + log_los - math.log(prior) - log_nlos
        return 1.0 / (1.0 + math.exp(x)) if x < 700.0 else 0.0

    def classify(self, nu: float, var: float, reject_probability: float = 0.5,
                 prior: float | None = None) -> bool:
        """Whether a range with innovation ``nu`` [m] of variance ``var`` [m²] (see
        :meth:`posterior`) is more probably NLOS than ``reject_probability``: reject it.

        An NLOS bias only lengthens a range, and a range that starts a link can already carry
        one (no jump for :class:`RangeRateGate` to see). The prior is the chain's steady share,
        not the link's history: successive innovations share the vehicles' persistent position
        errors, and chaining them as independent evidence ratchets a link to "NLOS" on an
        error well inside the position σ. A range that is kept carries the bias's prior mean
        square p₀ E[b²] as dependent noise (``FilterSettings.uwb_nlos_sigma``), not the
        posterior's p · E[b² | ν, NLOS]: that trusts an innovation whose state part is itself
        misestimated, and a vehicle metres off keeps a wrong bias and refuses the clean ranges
        after it (evidence: docs/decisions/0002-evidence-for-the-defaults.md).

        ``prior`` replaces the steady share by the link's NLOS probability from its own range
        series (:class:`NlosLinkTracker`): evidence that does not share the position errors.
        A kept range then carries that probability's p · E[b²] as dependent noise.
        """
        return self.posterior(self.steady if prior is None else prior, nu, var) > reject_probability


@dataclass(frozen=True)
class LinkBelief:
    """What a link's range series says about its current range.

    Attributes
    ----------
    p_nlos : float
        Probability that the range carries an NLOS bias.
    bias_mean_square : float
        E[b² | NLOS] of that bias [m²].
    outlier : bool
        The range is more probably a gross outlier than anything else (the track ignored it).
    """

    p_nlos: float
    bias_mean_square: float
    outlier: bool = False

    @property
    def bias_variance(self) -> float:
        """The bias's contribution to the range's error variance, P(NLOS) E[b² | NLOS] [m²]."""
        return self.p_nlos * self.bias_mean_square


@dataclass
class _Link:
    t: float
    r: float  # range level as measured (any bias included) [m]
    rd: float  # its rate [m/s]
    p11: float
    p12: float
    p22: float
    p: float  # P(NLOS)
    b: float  # E[b | NLOS] [m]
    b2: float  # E[b² | NLOS] [m²]


@dataclass
class NlosLinkTracker:
    """The NLOS state of each UWB link, followed from the link's own range series.

    An NLOS episode adds one bias for its whole duration (:class:`NlosModel`): the range steps
    up by 0.3-3 m when it starts and back down when it ends, both far beyond the UWB noise
    between two ranges 0.1 s apart. A constant-velocity Kalman filter follows the range level
    (process noise: the relative acceleration); each new range is scored against four
    transitions of the two-state chain (LOS or NLOS staying, an episode starting with a fresh
    bias, an episode ending with the link's bias) and, if the model has one, a gross outlier,
    and the link's NLOS probability and bias moments are updated (a Gaussian-sum filter
    collapsed at every range). A step, once the next range confirms it, resets the level.

    The evidence is the range's difference from the link's own recent ranges, so it does not
    share the two vehicles' persistent position errors, which a range's innovation against
    the two estimates does (:meth:`NlosModel.classify`). Only a link that starts inside an
    episode has no step to see; its probability starts at the chain's steady share and decays
    with every range that shows no step down.

    Attributes
    ----------
    model : NlosModel
    sigma : float
        UWB range noise [m].
    accel_psd : float
        Power spectral density of the relative range acceleration [m²/s³] while either
        vehicle moves (braking, turning: the part straight relative motion does not explain).
    accel_psd_standing : float
        The same while both stand (a ZUPT-held estimate, the car rocking on its springs).
    rate_sigma : float
        Least uncertainty of the range rate a link starts with [m/s].
    max_gap : float
        A link silent for longer than this [s] restarts (its NLOS probability carried over by
        the chain).
    """

    model: NlosModel
    sigma: float
    accel_psd: float = 10.0
    accel_psd_standing: float = 0.01
    rate_sigma: float = 1.0
    max_gap: float = 10.0
    _links: dict[str, _Link] = field(default_factory=dict)
    #: the last range off the track until the next one confirms or refutes it: (t, range,
    #: its hypotheses' weights or None for an outlier, its innovation)
    _pending: dict[str, tuple] = field(default_factory=dict)

    def belief(self, link: str, t: float, measured: float, rate: float, rel_speed2: float = 0.0,
               standing: bool = False, rate_var: float | None = None) -> LinkBelief:
        """Score the range ``measured`` [m] of ``link`` at time ``t`` [s] and update the link.

        Parameters
        ----------
        link : str
            The neighbour at the other end.
        t : float
            Sensor time of the range [s]. A range older than the link's last one is scored
            on the link's current state without changing it.
        measured : float
            The range [m].
        rate : float
            Range rate predicted from the two estimates [m/s]: it starts a link, and with
            ``rate_var`` it also updates the level's rate at every range (two cars braking
            towards each other change their range rate by 16 m/s within a second, which the
            inertial velocities see at once and a range series only after the fact).
        rel_speed2 : float
            Squared horizontal relative speed from the two estimates [m²/s²]: the level's
            prediction assumes straight relative motion, exact for two cars passing each
            other, whose range rate reverses within a fraction of a second (a
            constant-velocity range model misses that by metres).
        standing : bool
            Both vehicles stand (``accel_psd_standing``).
        rate_var : float, optional
            Variance of ``rate`` [m²/s²]; without it, ``rate`` only starts a link, with the
            relative speed squared as its variance.

        A range off the track (a step or a gross outlier) is judged but not followed until
        the next range agrees with it (within the UWB noise and the level's prediction): an
        isolated error leaves the track as it was, a step moves the level there, and two
        agreeing ranges too far off for any step restart the link (a change the track could
        not follow).
        """
        m = self.model
        lk = self._links.get(link)
        start_var = rel_speed2 if rate_var is None else rate_var  # of the rate a restart takes
        if lk is None or t - lk.t > self.max_gap:
            return self._restart(link, t, measured, rate, lk, start_var)
        dt = max(t - lk.t, 0.0)
        q = self.accel_psd_standing if standing else self.accel_psd
        r_p, rd_p, p11, p12, p22 = _predict_level(lk, dt, q, rel_speed2, rate, rate_var)
        var = p11 + self.sigma**2
        nu = measured - r_p
        logs = _hypotheses(m, lk, dt, nu, var)
        top = max(logs.values())
        w = {k: math.exp(v - top) for k, v in logs.items()}
        total = w["LL"] + w["NN"] + w["LN"] + w["NL"]
        outlier = w.get("out", 0.0) >= max(w["LL"], w["NN"], w["LN"], w["NL"])
        step = outlier or w["LN"] + w["NL"] > w["LL"] + w["NN"]
        if t < lk.t:  # out of order: scored, not kept
            return LinkBelief(lk.p, lk.b2, outlier=True) if outlier else LinkBelief((w["LN"] + w["NN"]) / total, lk.b2)
        pending = self._pending.pop(link, None)
        if pending is not None and self._agrees(pending[0], pending[1], t, measured, rate):
            if pending[2] is None:  # an outlier confirmed: a change the level's prediction missed
                return self._restart(link, t, measured, rate, lk, start_var)
            # the step judged on the first range off the track, confirmed by this one
            step, w, nu = True, pending[2], pending[3]
            total = w["LL"] + w["NN"] + w["LN"] + w["NL"]
        elif step:  # the first range off the track: judged, not yet followed
            self._pending[link] = (t, measured, None if outlier else w, nu)
            if outlier:
                return LinkBelief(lk.p, lk.b2, outlier=True)
            b_on = min(max(nu, m.bias_min), m.bias_max)
            return LinkBelief((w["LN"] + w["NN"]) / total, b_on * b_on + var if w["LN"] > w["NN"] else lk.b2)
        if step:  # the level restarts at this range
            lk.r, lk.rd, lk.p11, lk.p12, lk.p22 = measured, rd_p, self.sigma**2, 0.0, p22
        else:
            k1, k2 = p11 / var, p12 / var
            lk.r, lk.rd = r_p + k1 * nu, rd_p + k2 * nu
            lk.p11, lk.p12, lk.p22 = p11 - k1 * p11, p12 - k1 * p12, p22 - k2 * p12
        _update_bias(m, lk, w, nu, var, total)
        lk.t = t
        return LinkBelief(lk.p, lk.b2)

    def _agrees(self, t0: float, r0: float, t: float, measured: float, rate: float) -> bool:
        """Whether ``measured`` at ``t`` continues the range ``r0`` at ``t0`` with ``rate``."""
        dt = t - t0
        return dt > 0.0 and abs(measured - r0 - rate * dt) <= \
            3.0 * math.sqrt(2.0 * self.sigma**2 + self.accel_psd * dt**3 / 3.0) + self.rate_sigma * dt

    def _restart(self, link: str, t: float, measured: float, rate: float, old: _Link | None,
                 rate_var: float) -> LinkBelief:
        """Start ``link``'s track at this range; its NLOS probability carried over by the chain."""
        m = self.model
        pi = m.steady
        p = pi if old is None else pi + (old.p - pi) * math.exp(-(m.enter + m.exit) * max(t - old.t, 0.0))
        b, b2 = (m.bias_mean, m.bias_mean_square) if old is None else (old.b, old.b2)
        # the estimates' rate is only as good as their line of sight: at a few metres with
        # metres of position error it can have the wrong sign; without its variance, take the
        # relative speed squared
        self._links[link] = _Link(t, measured, rate, self.sigma**2, 0.0, max(self.rate_sigma**2, rate_var),
                                  p, b, b2)
        self._pending.pop(link, None)
        return LinkBelief(p, b2)

    def forget(self, link: str) -> None:
        self._links.pop(link, None)
        self._pending.pop(link, None)


def _safe_log(x: float) -> float:
    return math.log(x) if x > 0.0 else -math.inf


def _predict_level(lk, dt: float, q: float, rel_speed2: float, rate: float,
                   rate_var: float | None) -> tuple[float, float, float, float, float]:
    """A link's level predicted over ``dt`` [s] (constant velocity, white relative acceleration
    of PSD ``q``), then updated with the estimates' range rate when ``rate_var`` is given:
    (range, rate, and the covariance p11, p12, p22)."""
    # straight relative motion: the line-of-sight part of the relative velocity is the
    # rate, the rest (w) is across it
    w2 = max(rel_speed2 - lk.rd * lk.rd, 0.0)
    along, across = lk.r + lk.rd * dt, math.sqrt(w2) * dt
    r_p = math.hypot(along, across)
    rd_p = (along * lk.rd + w2 * dt) / max(r_p, 1e-6)
    p11 = lk.p11 + dt * (2.0 * lk.p12 + dt * lk.p22) + q * dt**3 / 3.0
    p12 = lk.p12 + dt * lk.p22 + q * dt * dt / 2.0
    p22 = lk.p22 + q * dt
    if rate_var is not None:  # the estimates' range rate now
        s_rate = p22 + rate_var
        k1, k2 = p12 / s_rate, p22 / s_rate
        innov = rate - rd_p
        r_p, rd_p = r_p + k1 * innov, rd_p + k2 * innov
        p11, p12, p22 = p11 - k1 * p12, p12 - k1 * p22, p22 - k2 * p22
    return r_p, rd_p, p11, p12, p22


def _hypotheses(m: NlosModel, lk, dt: float, nu: float, var: float) -> dict[str, float]:
    """Log-likelihoods of the link's transitions over ``dt`` given the innovation ``nu`` of
    variance ``var``: LOS stays LOS (LL), NLOS stays (NN), an episode starts (LN) or ends (NL),
    and with outliers modelled, an outlier ("out")."""
    # the two-state chain over dt
    pi = m.steady
    e = math.exp(-(m.enter + m.exit) * dt)
    p_nn = pi + (1.0 - pi) * e
    p_ln = pi * (1.0 - e)
    p_los = 1.0 - lk.p
    stay = _log_normal(nu, var)
    logs = {
        "LL": _safe_log(p_los * (1.0 - p_ln)) + stay,
        "NN": _safe_log(lk.p * p_nn) + stay,
        "LN": _safe_log(p_los * p_ln) + m.log_bias_likelihood(nu, var),
        # an episode's end shortens the range by its bias, at least bias_min
        "NL": (_safe_log(lk.p * (1.0 - p_nn)) + _log_normal(nu + lk.b, var + max(lk.b2 - lk.b**2, 0.0))
               if nu < 3.0 * math.sqrt(var) - m.bias_min else -math.inf),
    }
    if m.outlier_prob > 0.0:
        for k in logs:
            logs[k] += math.log1p(-m.outlier_prob)
        sd = math.sqrt(var)
        z = _cdf_between((m.outlier_min - abs(nu)) / sd, (m.outlier_max - abs(nu)) / sd)
        logs["out"] = _safe_log(m.outlier_prob * z / (2.0 * (m.outlier_max - m.outlier_min)))
    return logs


def _update_bias(m: NlosModel, lk, w: dict[str, float], nu: float, var: float, total: float) -> None:
    """The link's NLOS probability and bias moments given NLOS: a fresh bias near the step, or
    the link's own (``w`` the hypotheses' weights, ``total`` their sum without an outlier)."""
    nlos = w["LN"] + w["NN"]
    if nlos > 0.0:
        b_on = min(max(nu, m.bias_min), m.bias_max)
        lk.b = (w["LN"] * b_on + w["NN"] * lk.b) / nlos
        lk.b2 = (w["LN"] * (b_on * b_on + min(var, m.bias_mean_square)) + w["NN"] * lk.b2) / nlos
    else:
        lk.b, lk.b2 = m.bias_mean, m.bias_mean_square
    lk.p = nlos / total
