"""Fusing information of unknown correlation: split covariance intersection (split CI).

A vehicle's estimate and its neighbour's beacon are not independent once they have exchanged
information: the neighbour's estimate already contains ranges to us, and both ends fuse the same
range. Treating them as independent (the paper's rule) double counts and makes the filter
overconfident. Split CI (Julier & Uhlmann 2001; Li & Nashashibi 2013 for cooperative vehicle
localisation) splits every covariance into an *independent* part (from the vehicle's own sensors
and from white measurement noise) and a *dependent* part (anything that may be correlated), and
inflates only the dependent parts:

    P1(ω) = P_d / ω + P_i,        R1(ω) = R_d / (1 - ω) + R_i,        0 < ω < 1

followed by an ordinary Kalman update with P1, R1. The result is consistent for *any*
correlation between the dependent parts. ω is chosen to minimise the posterior variance of the
horizontal position. The independent part after the update is
``(I - KH) P_i (I - KH)ᵀ + K R_i Kᵀ``.

Plain covariance intersection is the special case P_i = 0, R_d = all of the neighbour's
covariance (every part of both estimates may be correlated); only the sensor noise of the
measurement (UWB) stays independent.

Pure numpy/scipy; no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import cast

import numpy as np

from .kalman import Measurement, UpdateResult, joseph, kalman_update

OMEGA_MIN, OMEGA_MAX = 1e-3, 1.0 - 1e-3


def _scalar_terms(Pd: np.ndarray, Pi: np.ndarray, H: np.ndarray, Rd: np.ndarray, Ri: np.ndarray,
                  idx: np.ndarray) -> tuple[float, ...]:
    """For a scalar measurement (``H`` of shape (1, n)): ``(tr_d, tr_i, aa, ab, bb, ha, hb, rd, ri)``.

    With a = P_d Hᵀ and b = P_i Hᵀ restricted to ``idx``: aa = a·a, ab = a·b, bb = b·b;
    ha = H a, hb = H b (over all states); tr_d, tr_i the traces of the ``idx`` blocks.
    """
    a, b = Pd @ H[0], Pi @ H[0]
    h = H[0]
    ai, bi = a[idx], b[idx]
    return (float(Pd[idx, idx].sum()), float(Pi[idx, idx].sum()),  # traces (np.ix_ is slow)
            float(ai @ ai), float(ai @ bi), float(bi @ bi), float(h @ a), float(h @ b),
            float(Rd[0, 0]), float(Ri[0, 0]))


def _scalar_trace_fn(terms: tuple[float, ...]) -> Callable[[float], float]:
    """The posterior ``idx`` variance as a function of ω for a scalar measurement (see
    :func:`_trace_fn`), from :func:`_scalar_terms`."""
    tr_d, tr_i, aa, ab, bb, ha, hb, rd, ri = terms

    def f(w: float) -> float:
        s = ha / w + hb + rd / (1.0 - w) + ri
        return tr_d / w + tr_i - (aa / (w * w) + 2.0 * ab / w + bb) / s
    return f


def _trace_fn(Pd: np.ndarray, Pi: np.ndarray, H: np.ndarray, Rd: np.ndarray, Ri: np.ndarray,
              idx: np.ndarray) -> Callable[[float], float]:
    """The posterior variance over the states ``idx`` as a function of ω, precomputed.

    With a = P_d Hᵀ and b = P_i Hᵀ: P₁Hᵀ = a/ω + b, H P₁ Hᵀ = H a/ω + H b, and the posterior
    trace is tr(P₁[idx]) − tr(A S⁻¹ Aᵀ) with A = (a/ω + b)[idx], S = H P₁ Hᵀ + R₁(ω).
    """
    if H.shape[0] == 1:  # scalar measurement: plain floats
        return _scalar_trace_fn(_scalar_terms(Pd, Pi, H, Rd, Ri, idx))
    a, b = Pd @ H.T, Pi @ H.T
    Ha, Hb = H @ a, H @ b
    tr_d = float(Pd[idx, idx].sum())
    tr_i = float(Pi[idx, idx].sum())
    ai, bi = a[idx], b[idx]

    def g(w: float) -> float:
        A = ai / w + bi
        S = Ha / w + Hb + Rd / (1.0 - w) + Ri
        return tr_d / w + tr_i - float(np.trace(A @ np.linalg.solve(S, A.T)))
    return g


def scalar_gain_exceeds(terms: tuple[float, ...], threshold: float,
                        lo: float = OMEGA_MIN, hi: float = OMEGA_MAX) -> bool:
    """Whether some ω in [lo, hi] reduces the ``idx`` variance by more than ``threshold``
    (a scalar measurement; ``terms`` from :func:`_scalar_terms`), decided exactly without a search.

    With x = 1/ω the gain is G(x) = N(x)/s(x) − tr_d (x − 1), N(x) = aa x² + 2ab x + bb and
    s(x) = D(x)/(x − 1), D(x) = (ha x + hb + ri)(x − 1) + rd x > 0. So G(x) > T exactly where the
    cubic p(x) = N(x)(x − 1) − (tr_d (x − 1) + T) D(x) is positive, and the maximum of a cubic on
    an interval lies at an end or where its derivative (a quadratic) vanishes. A small relative
    margin against rounding errs towards True (the caller then runs the search).
    """
    tr_d, _, aa, ab, bb, ha, hb, rd, ri = terms
    c = hb + ri
    d1 = c - ha + rd
    e = threshold - tr_d
    # p(x) = A x³ + B x² + C x + (e c − bb); only its derivative's coefficients are needed
    A = aa - tr_d * ha
    B = 2.0 * ab - aa - tr_d * d1 - e * ha
    C = bb - 2.0 * ab + tr_d * c - e * d1
    x_lo, x_hi = 1.0 / hi, 1.0 / lo
    xs = [x_lo, x_hi]
    # p'(x) = 3A x² + 2B x + C
    qa, qb, qc = 3.0 * A, 2.0 * B, C
    if qa != 0.0:
        disc = qb * qb - 4.0 * qa * qc
        if disc >= 0.0:
            r = math.sqrt(disc)
            q = -0.5 * (qb + math.copysign(r, qb))  # numerically stable roots
            xs += [q / qa] + ([qc / q] if q != 0.0 else [])
    elif qb != 0.0:
        xs.append(-qc / qb)
    for x in xs:
        if x_lo <= x <= x_hi:
            w = x - 1.0
            plus = (aa * x * x + 2.0 * ab * x + bb) * w
            minus = (tr_d * w + threshold) * ((ha * x + c) * w + rd * x)
            if plus - minus > -1e-9 * (abs(plus) + abs(minus)):
                return True
    return False


def _posterior_trace(Pd: np.ndarray, Pi: np.ndarray, H: np.ndarray, Rd: np.ndarray, Ri: np.ndarray,
                     idx: np.ndarray, omega: float) -> float:
    """Trace of the posterior covariance over the states ``idx`` for a given ω."""
    return _trace_fn(Pd, Pi, H, Rd, Ri, idx)(omega)


def best_omega(Pd: np.ndarray, Pi: np.ndarray, H: np.ndarray, Rd: np.ndarray, Ri: np.ndarray,
               idx: np.ndarray) -> float:
    """ω in (0, 1) minimising the posterior variance of the states ``idx``.

    Parameters
    ----------
    Pd, Pi : ndarray, shape (n, n)
        Dependent and independent parts of the prior covariance.
    H : ndarray, shape (m, n)
    Rd, Ri : ndarray, shape (m, m)
        Dependent and independent parts of the measurement noise.
    idx : ndarray of int
        States whose variance is minimised (e.g. north and east position).
    """
    return _best(Pd, Rd, _trace_fn(Pd, Pi, H, Rd, Ri, idx))


def fminbound(f: Callable[[float], float], lo: float, hi: float, xatol: float = 1e-5, maxfun: int = 500) -> float:
    """Minimiser of a scalar function on ``[lo, hi]`` by Brent's method (golden section with
    parabolic interpolation), step for step as ``scipy.optimize.minimize_scalar(method="bounded")``
    (the tests check both agree). Written out so that an agent does not import
    ``scipy.optimize``, about 40 MB of resident memory."""
    sqrt_eps = math.sqrt(2.2e-16)
    golden_mean = 0.5 * (3.0 - math.sqrt(5.0))
    a, b = lo, hi
    fulc = a + golden_mean * (b - a)
    nfc = xf = fulc
    rat = e = 0.0
    fx = f(xf)
    num = 1
    ffulc = fnfc = fx
    xm = 0.5 * (a + b)
    tol1 = sqrt_eps * abs(xf) + xatol / 3.0
    tol2 = 2.0 * tol1
    while abs(xf - xm) > tol2 - 0.5 * (b - a):
        golden = True
        if abs(e) > tol1:  # try a parabolic step
            golden = False
            r = (xf - nfc) * (fx - ffulc)
            q = (xf - fulc) * (fx - fnfc)
            p = (xf - fulc) * q - (xf - nfc) * r
            q = 2.0 * (q - r)
            if q > 0.0:
                p = -p
            q = abs(q)
            r, e = e, rat
            if abs(p) < abs(0.5 * q * r) and q * (a - xf) < p < q * (b - xf):
                rat = p / q
                x = xf + rat
                if x - a < tol2 or b - x < tol2:
                    rat = tol1 * (1.0 if xm - xf >= 0 else -1.0)
            else:
                golden = True
        if golden:
            e = a - xf if xf >= xm else b - xf
            rat = golden_mean * e
        x = xf + (1.0 if rat >= 0 else -1.0) * max(abs(rat), tol1)
        fu = f(x)
        num += 1
        if fu <= fx:
            if x >= xf:
                a = xf
            else:
                b = xf
            fulc, ffulc = nfc, fnfc
            nfc, fnfc = xf, fx
            xf, fx = x, fu
        else:
            if x < xf:
                a = x
            else:
                b = x
            if fu <= fnfc or nfc == xf:
                fulc, ffulc = nfc, fnfc
                nfc, fnfc = x, fu
            elif fu <= ffulc or fulc == xf or fulc == nfc:
                fulc, ffulc = x, fu
        xm = 0.5 * (a + b)
        tol1 = sqrt_eps * abs(xf) + xatol / 3.0
        tol2 = 2.0 * tol1
        if num >= maxfun:
            break
    return xf


def _best(Pd: np.ndarray, Rd: np.ndarray, f: Callable[[float], float]) -> float:
    if not np.any(Rd):
        return OMEGA_MAX  # nothing dependent on the measurement side: keep the prior whole
    if not np.any(Pd):
        return OMEGA_MIN  # nothing dependent on our side: keep the measurement whole
    return float(fminbound(f, OMEGA_MIN, OMEGA_MAX, xatol=1e-3))


def naive_gain(P: np.ndarray, H: np.ndarray, R: np.ndarray, idx: np.ndarray) -> float:
    """Reduction of the variance of the states ``idx`` [their unit²] by a plain Kalman update
    with prior ``P`` (n, n), Jacobian ``H`` (m, n) and noise ``R`` (m, m): ``tr(A S⁻¹ Aᵀ)`` with
    ``A = (P Hᵀ)[idx]``, ``S = H P Hᵀ + R``. An upper bound on what split CI can gain."""
    PHt = P @ H.T
    S = H @ PHt + R
    A = PHt[idx]
    if H.shape[0] == 1:
        s = float(S[0, 0])
        return float(A[:, 0] @ A[:, 0]) / s if s > 0.0 else 0.0
    try:
        return float(np.trace(A @ np.linalg.solve(S, A.T)))
    except np.linalg.LinAlgError:
        return 0.0


def split_ci_update(P: np.ndarray, P_ind: np.ndarray, meas: Measurement, R_dep: np.ndarray, idx: np.ndarray,
                    gate_probability: float | None = None, min_gain: float = 0.0,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, UpdateResult]:
    """One split-CI update of an error state.

    Parameters
    ----------
    P : ndarray, shape (n, n)
        Prior covariance; ``P - P_ind`` is its dependent part.
    P_ind : ndarray, shape (n, n)
        Independent part of ``P`` (zeros for plain CI).
    meas : Measurement
        ``z``, ``H`` and the *independent* noise ``R`` (e.g. UWB noise plus the neighbour's
        independent covariance projected on the measurement).
    R_dep : ndarray, shape (m, m)
        Dependent part of the measurement noise (the neighbour's dependent covariance projected).
    idx : ndarray of int
        States whose posterior variance chooses ω.
    gate_probability : float, optional
        χ² gate on the NIS computed with the inflated covariances.
    min_gain : float
        Node selection: skip the update (``result.skipped``) unless it is expected to reduce the
        variance of the states ``idx`` by at least this fraction.

    Returns
    -------
    dx, P_post, P_ind_post, result
        As :func:`agent.nav.kalman.kalman_update`, plus the posterior independent part;
        ``result.omega`` is the chosen ω. A rejected update returns the priors.
    """
    n = P.shape[0]
    Pd = P - P_ind
    Pd = 0.5 * (Pd + Pd.T)
    scalar = meas.dim == 1
    terms = _scalar_terms(Pd, P_ind, meas.H, R_dep, meas.R, idx) if scalar else ()
    if min_gain > 0.0:
        prior = float(P[idx, idx].sum())
        # screen first, so that an update no ω makes worth it is skipped without the ω search
        # (the decision is the same as after it): for a scalar measurement exactly (the best
        # gain over all ω exceeds the threshold or not); otherwise by the plain Kalman gain, an
        # upper bound over all ω (P1(ω) ≥ P, R1(ω) ≥ R, and the posterior grows with both)
        if (not scalar_gain_exceeds(terms, min_gain * prior) if scalar
                else naive_gain(P, meas.H, R_dep + meas.R, idx) < min_gain * prior):
            return np.zeros(n), P, P_ind, UpdateResult(np.zeros(n), float("nan"), meas.dim, False, meas.name,
                                                       None, float("nan"), skipped=True)
    f = _scalar_trace_fn(terms) if scalar else _trace_fn(Pd, P_ind, meas.H, R_dep, meas.R, idx)
    omega = _best(Pd, R_dep, f)
    if min_gain > 0.0 and prior - f(omega) < min_gain * prior:
        return np.zeros(n), P, P_ind, UpdateResult(np.zeros(n), float("nan"), meas.dim, False, meas.name,
                                                   None, omega, skipped=True)
    P1 = Pd / omega + P_ind
    R1 = R_dep / (1.0 - omega) + meas.R
    dx, P_post, res = kalman_update(P1, Measurement(meas.z, meas.H, R1, meas.name), gate_probability)
    if not res.accepted:
        return dx, P, P_ind, UpdateResult(dx, res.nis, res.dof, False, res.name, None, omega)
    K = cast(np.ndarray, res.gain)  # an accepted update carries its gain
    P_ind_post = joseph(P_ind, K, meas.H, meas.R)
    return dx, P_post, P_ind_post, UpdateResult(dx, res.nis, res.dof, True, res.name, K, omega)
