"""Random processes shared by the sensor models (vectorised where the recursion allows)."""

from __future__ import annotations

import math

import numpy as np


def gauss_markov(n: int, dt: float, sigma: float, tau: float, rng: np.random.Generator,
                 dims: int = 1, x0: np.ndarray | None = None) -> np.ndarray:
    """Stationary first-order Gauss-Markov samples, exact discretisation.

    ``x[k+1] = φ x[k] + sqrt(1-φ²) σ w[k]`` with ``φ = exp(-dt/τ)``; ``x[0] ~ N(0, σ²)`` unless
    given. Returns shape (n, dims). ``tau = inf`` gives a constant ``x0``; ``sigma = 0`` zeros.
    """
    if n <= 0:
        return np.zeros((0, dims))
    x0 = rng.normal(0.0, sigma, dims) if x0 is None else np.asarray(x0, float)
    if sigma == 0.0 or math.isinf(tau):
        return np.broadcast_to(x0, (n, dims)).copy()
    phi = math.exp(-dt / tau)
    w = rng.normal(0.0, sigma * math.sqrt(1.0 - phi * phi), (n, dims))
    w[0] = x0
    return ar1_filter(w, phi)


def ar1_filter(w: np.ndarray, phi: float) -> np.ndarray:
    """``x[k] = phi x[k-1] + w[k]``, ``x[0] = w[0]``, along axis 0 of ``w`` (n, dims).

    The same floating-point operations as ``scipy.signal.lfilter([1], [1, -phi], w, axis=0)``, so
    the same bits, without importing ``scipy.signal`` (about a second of every emulator's start)."""
    x = np.array(w, dtype=float, copy=True)
    if len(x) == 0:
        return x
    for d in range(x.shape[1]):
        col = x[:, d].tolist()
        acc = col[0]
        for k in range(1, len(col)):
            acc = phi * acc + col[k]
            col[k] = acc
        x[:, d] = col
    return x


def gauss_markov_varying(dt: np.ndarray, sigma: float, tau: np.ndarray, rng: np.random.Generator,
                         dims: int = 1) -> np.ndarray:
    """Gauss-Markov samples whose correlation time changes per step (e.g. moving vs static).

    ``dt[k]`` and ``tau[k]`` apply to the step from sample ``k-1`` to ``k`` (``dt[0]`` unused).
    Returns shape (len(dt), dims); the marginal standard deviation stays ``sigma``.
    """
    n = len(dt)
    phi = np.exp(-np.asarray(dt, float) / np.asarray(tau, float))
    drive = rng.normal(0.0, 1.0, (n, dims)) * (sigma * np.sqrt(1.0 - phi * phi))[:, None]
    x = np.empty((n, dims))
    x[0] = rng.normal(0.0, sigma, dims)
    for k in range(1, n):
        x[k] = phi[k] * x[k - 1] + drive[k]
    return x


def two_state_markov(n: int, p_enter: float, p_exit: float, rng: np.random.Generator,
                     start: bool | None = None) -> np.ndarray:
    """Boolean Markov chain per step: P(False→True) = p_enter, P(True→False) = p_exit.

    Vectorised by drawing geometric sojourn times. ``start=None`` draws the initial state from
    the stationary distribution ``p_enter / (p_enter + p_exit)``.
    """
    if n <= 0:
        return np.zeros(0, bool)
    for name, p in (("p_enter", p_enter), ("p_exit", p_exit)):
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"{name} must be a probability, got {p}")
    if p_enter == 0.0 and p_exit == 0.0:
        return np.full(n, bool(start))
    if start is None:
        start = bool(rng.random() < p_enter / (p_enter + p_exit))
    out = np.empty(n, bool)
    k, state = 0, start
    while k < n:
        p = p_exit if state else p_enter
        if p == 0.0:
            out[k:] = state
            break
        m = int(rng.geometric(p))
        out[k:k + m] = state
        k += m
        state = not state
    return out
