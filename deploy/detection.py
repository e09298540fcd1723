"""Scoring first-stopped decisions against the emulator's truth.

A claim at time t is *correct* when the vehicle is truly the first stopped vehicle of its lane
at some time within ``t ± tolerance``, or is within centimetres of where it stands first stopped
(``zone``, :attr:`hw_emulation.truth.VehicleTruth.first_stop_zone`): the truth labels a vehicle
stopped below 0.05 m/s, and a filter may declare a stop earlier or later while the vehicle
creeps the last centimetres to its stop position (a few hundredths of a second in slcp's
traffic model, seconds in SUMO's).

- precision: correct claimed time / claimed time;
- recall: truly-first time covered by a claim / truly-first time;
- latency: per truly-first interval, first claim minus the interval's start [s];
- SL RMSE: the stop-line method's horizontal error over the whole truly-first time (detection
  latency included) and over the claimed part only.
"""

from __future__ import annotations

import numpy as np


def _dilate(flags: np.ndarray, t: np.ndarray, tolerance: float) -> np.ndarray:
    """True where ``flags`` is true at some sample within ± tolerance [s]."""
    idx = np.flatnonzero(flags)
    if idx.size == 0:
        return np.zeros_like(flags)
    tt = t[idx]
    k = np.searchsorted(tt, t - tolerance)
    return (k < tt.size) & (tt[np.minimum(k, tt.size - 1)] <= t + tolerance)


def score_first_stopped(t: np.ndarray, truth_first: np.ndarray, claimed: np.ndarray,
                        err_h: np.ndarray | None = None, tolerance: float = 0.3,
                        zone: np.ndarray | None = None) -> dict:
    """Scores of one vehicle's claims.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Sample times [s], increasing and roughly evenly spaced.
    truth_first, claimed : ndarray of bool, shape (n,)
        Truth label and the filter's claim at each sample.
    err_h : ndarray, shape (n,), optional
        Horizontal error [m] of the stop-line method at each sample.
    tolerance : float
        Timing tolerance [s] of a claim.
    zone : ndarray of bool, shape (n,), optional
        Where the vehicle is within centimetres of a first-stopped stance (a claim is correct there).
    """
    t = np.asarray(t, float)
    truth_first = np.asarray(truth_first, bool)
    claimed = np.asarray(claimed, bool)
    steps = np.diff(t)
    steps = steps[steps > 0]
    dt = float(np.median(steps)) if steps.size else 0.0
    near_truth = _dilate(truth_first, t, tolerance)
    if zone is not None:
        near_truth |= np.asarray(zone, bool)
    out: dict = {
        "truth_s": float(truth_first.sum() * dt),
        "claimed_s": float(claimed.sum() * dt),
        "wrong_s": float((claimed & ~near_truth).sum() * dt),
        "covered_s": float((claimed & truth_first).sum() * dt),
    }
    out["precision"] = 1.0 - out["wrong_s"] / out["claimed_s"] if out["claimed_s"] > 0 else None
    out["recall"] = out["covered_s"] / out["truth_s"] if out["truth_s"] > 0 else None
    starts = np.flatnonzero(truth_first & ~np.r_[False, truth_first[:-1]])
    ends = np.flatnonzero(truth_first & ~np.r_[truth_first[1:], False])
    n_tol = int(round(tolerance / dt)) if dt > 0 else 0
    lat = []
    for a, b in zip(starts, ends):
        lo = max(a - n_tol, 0)
        hit = np.flatnonzero(claimed[lo: b + 1])
        lat.append(float(t[lo + hit[0]] - t[a]) if hit.size else None)  # negative: claimed early
    out["latency_s"] = lat
    if err_h is not None:
        e = np.asarray(err_h, float)
        out["sl_rmse_truth_first_m"] = float(np.sqrt(np.mean(e[truth_first] ** 2))) if truth_first.any() else None
        both = truth_first & claimed
        out["sl_rmse_claimed_m"] = float(np.sqrt(np.mean(e[both] ** 2))) if both.any() else None
    return out
