"""Linear Kalman update on the error state (Joseph form), NIS, gating and stacking.

Measurement convention used by every model in :mod:`agent.nav.measurements`: the innovation
``z`` is *predicted minus measured*, so that ``z ≈ H dx + v`` with ``dx`` the estimate-minus-truth
error state (the paper's eq. 9); the estimated error ``K z`` is then removed from the nominal
state (closed loop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class Measurement:
    """One linearised measurement.

    Attributes
    ----------
    z : ndarray, shape (m,)
        Innovation, predicted minus measured, in the measurement's units.
    H : ndarray, shape (m, n)
        Jacobian of the prediction w.r.t. the error state.
    R : ndarray, shape (m, m)
        Measurement noise covariance.
    name : str
        Model name for diagnostics (``"gnss_pos"``, ``"stop_line"``, ...).
    """

    z: np.ndarray
    H: np.ndarray
    R: np.ndarray
    name: str = ""

    @property
    def dim(self) -> int:
        return int(self.z.shape[0])


@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one update: estimated error, NIS and whether it was applied."""

    dx: np.ndarray
    nis: float
    dof: int
    accepted: bool
    name: str = ""
    gain: np.ndarray | None = None  #: Kalman gain K, shape (n, m), when applied
    omega: float | None = None  #: covariance-intersection weight, for CI updates
    skipped: bool = False  #: not applied because its expected gain was too small (node selection)


def chi2_survival(x: float, dof: int) -> float:
    """``P(chi2_dof > x)`` for an integer ``dof`` >= 1, in closed form (Abramowitz & Stegun
    26.4.4-5): with ``m = dof // 2``, ``exp(-x/2) Σ_{i<m} (x/2)^i / i!`` for even ``dof``, and
    ``erfc(sqrt(x/2)) + sqrt(2x/π) exp(-x/2) Σ_{i<m} x^i / (3·5···(2i+1))`` for odd ``dof``."""
    if x <= 0.0:
        return 1.0
    e = math.exp(-0.5 * x)
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= 0.5 * x / i
            total += term
        return e * total
    term, total = 1.0, 0.0
    for i in range(dof // 2):
        total += term
        term *= x / (2 * i + 3)
    return math.erfc(math.sqrt(0.5 * x)) + math.sqrt(2.0 * x / math.pi) * e * total


@lru_cache(maxsize=256)
def chi2_gate(dof: int, probability: float) -> float:
    """Chi-square quantile ``P(chi2_dof <= gate) = probability`` (bisection on
    :func:`chi2_survival` to 1e-12 relative; agrees with ``scipy.stats.chi2.ppf``, which an agent
    does not import: ``scipy.stats`` alone would add about 50 MB to its resident memory)."""
    if not (isinstance(dof, int) and dof >= 1) or not 0.0 < probability < 1.0:
        raise ValueError(f"chi2_gate needs an integer dof >= 1 and 0 < probability < 1, got {dof}, {probability}")
    tail = 1.0 - probability
    lo, hi = 0.0, max(1.0, float(dof))
    while chi2_survival(hi, dof) > tail:
        lo, hi = hi, 2.0 * hi
    while hi - lo > 1e-12 * hi:
        mid = 0.5 * (lo + hi)
        if chi2_survival(mid, dof) > tail:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def stack(measurements: list[Measurement], name: str = "stacked") -> Measurement:
    """Stack independent measurements into one (the paper's eq. 29): block-diagonal R."""
    dims = [m.dim for m in measurements]
    R = np.zeros((sum(dims), sum(dims)))
    k = 0
    for m, d in zip(measurements, dims):
        R[k:k + d, k:k + d] = m.R
        k += d
    return Measurement(
        z=np.concatenate([m.z for m in measurements]),
        H=np.vstack([m.H for m in measurements]),
        R=R,
        name=name,
    )


def kalman_update(
    P: np.ndarray, meas: Measurement, gate_probability: float | None = None, consider: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, UpdateResult]:
    """Joseph-form Kalman update of the error covariance.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        Prior error covariance ``P(k|k-1)``.
    meas : Measurement
        Linearised measurement; prior error mean is zero (closed loop).
    gate_probability : float, optional
        If given, reject the update when NIS exceeds the chi-square quantile of this
        probability (e.g. 0.999).
    consider : ndarray of int, optional
        *Consider* states (Schmidt-Kalman): their rows of the gain are zero, so their
        estimates never change while their covariances with the rest stay exact (the Joseph
        form holds for any gain).

    Returns
    -------
    dx : ndarray, shape (n,)
        Estimated error (zeros if rejected).
    P_post : ndarray, shape (n, n)
        Posterior covariance (the prior if rejected).
    result : UpdateResult
    """
    H, R, z = meas.H, meas.R, meas.z
    n = P.shape[0]
    PHt = P @ H.T
    S = H @ PHt + R
    # small S (<= a few rows): an explicit inverse is cheaper than a factorisation call
    try:
        if not (np.isfinite(S).all() and np.isfinite(z).all()):
            raise np.linalg.LinAlgError("non-finite innovation")
        Sinv = np.linalg.inv(S)
        nis = float(z @ Sinv @ z)
        if not nis >= 0.0:  # S not positive definite (or NaN)
            raise np.linalg.LinAlgError("innovation covariance not positive definite")
    except np.linalg.LinAlgError:
        return np.zeros(n), P, UpdateResult(np.zeros(n), float("inf"), meas.dim, False, meas.name)
    if gate_probability is not None and nis > chi2_gate(meas.dim, gate_probability):
        return np.zeros(n), P, UpdateResult(np.zeros(n), nis, meas.dim, False, meas.name)
    K = PHt @ Sinv
    if consider is not None and consider.size:
        K[consider] = 0.0
    dx = K @ z
    return dx, joseph(P, K, H, R), UpdateResult(dx, nis, meas.dim, True, meas.name, K)


def joseph(P: np.ndarray, K: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Joseph-form posterior ``(I - K H) P (I - K H)ᵀ + K R Kᵀ``, symmetrised: prior ``P`` (n, n),
    gain ``K`` (n, m), Jacobian ``H`` (m, n), noise ``R`` (m, m). Valid for any gain, so it also
    carries a covariance part (e.g. split CI's independent part) through another update's gain."""
    IKH = -(K @ H)
    IKH.flat[:: P.shape[0] + 1] += 1.0
    P_post = IKH @ P @ IKH.T + K @ R @ K.T
    P_sym: np.ndarray = 0.5 * (P_post + P_post.T)
    return P_sym


@dataclass
class FilterStats:
    """Counters a filter keeps for diagnostics."""

    imu_samples: int = 0
    cov_steps: int = 0
    updates: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)

    def count(self, result: UpdateResult) -> None:
        table = self.updates if result.accepted else self.rejected
        table[result.name] = table.get(result.name, 0) + 1
