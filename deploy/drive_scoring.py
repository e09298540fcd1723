"""Scoring a recorded drive's estimates against its GNSS fixes, the one way both the offline
replay (:mod:`deploy.replay`) and ``slcp replay --publish`` (:mod:`deploy.replay_publish`) do.

The file's fixes (RTK) stand as truth for the GNSS antenna; each estimate is moved to the
antenna by its attitude and the lever arm, then interpolated to the fixes' epochs. Epochs whose
fix was withheld (an outage of the protocol) give the outage metrics.
"""

from __future__ import annotations

import numpy as np
import pymap3d

from slcp.agent.nav.rotation import euler_to_dcm
from slcp.geo import earth
from slcp.transport.messages import Estimate


def antenna_positions(est: list[Estimate], lever_arm: tuple[float, float, float]) -> np.ndarray:
    """Where each estimate puts the GNSS antenna (lat, lon [rad], h [m]), (n, 3)."""
    lever = np.asarray(lever_arm, float)
    if not lever.any():
        return np.array([e.llh for e in est]).reshape(-1, 3)
    return np.array([earth.offset_llh(e.llh, euler_to_dcm(*e.rpy) @ lever) for e in est]).reshape(-1, 3)


def errors_at_epochs(fix_t: np.ndarray, fix_llh: np.ndarray, est_t: np.ndarray,
                     est_llh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal error [m] of estimates against reference fixes at the fixes' epochs.

    The estimates (times (k,), llh (k, 3) in rad, rad, m) are interpolated linearly in local
    NED to each epoch of ``fix_t`` (n,) inside their time span. Returns ``(inside (n,) bool,
    error (inside.sum(),))``.
    """
    order = np.argsort(est_t)
    t, llh = np.asarray(est_t, float)[order], np.asarray(est_llh, float)[order]
    inside = (fix_t >= t[0]) & (fix_t <= t[-1]) if len(t) > 1 else np.zeros(len(fix_t), bool)
    if not inside.any():
        return inside, np.zeros(0)
    origin = fix_llh[0]
    ref = np.column_stack(pymap3d.geodetic2ned(*fix_llh[inside].T, *origin, deg=False)[:2])
    ne = np.column_stack(pymap3d.geodetic2ned(*llh.T, *origin, deg=False)[:2])
    est = np.column_stack([np.interp(fix_t[inside], t, ne[:, i]) for i in (0, 1)])
    return inside, np.hypot(*(est - ref).T)


def _rms(x: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x * x))) if len(x) else None


def outage_metrics(err: np.ndarray, withheld: np.ndarray) -> dict:
    """The outage figures of errors ``err`` [m] at epochs whose fix was ``withheld`` or not: RMS
    over the withheld epochs, the error at the last withheld epoch of every outage (a run of
    withheld epochs; mean and max), the largest, and the RMS with GNSS on. None where empty."""
    last = np.flatnonzero(withheld & ~np.r_[withheld[1:], False])
    ends = [float(err[i]) for i in last]
    return {"outage_h_rms_m": _rms(err[withheld]),
            "outage_h_end_mean_m": float(np.mean(ends)) if ends else None,
            "outage_h_end_max_m": float(np.max(ends)) if ends else None,
            "outage_h_max_m": float(err[withheld].max()) if withheld.any() else None,
            "gnss_on_h_rms_m": _rms(err[~withheld]),
            "n_outages": len(ends), "n_withheld_fixes": int(withheld.sum()), "outage_end_errors_m": ends}


def score_estimates(fix_t: np.ndarray, fix_llh: np.ndarray, withheld: np.ndarray, est: list[Estimate],
                    lever_arm: tuple[float, float, float]) -> tuple[dict, np.ndarray, np.ndarray]:
    """One method's estimates against the fixes: its figures (:func:`outage_metrics`, with
    ``n_estimates``, ``epochs`` scored and the first and last of them, ``first_epoch_t`` and
    ``last_epoch_t`` [s], ``h_rms_m`` and ``h_max_m``), and the scored epochs' mask and errors
    (:func:`errors_at_epochs`)."""
    inside, err = errors_at_epochs(fix_t, fix_llh, np.array([e.t for e in est]), antenna_positions(est, lever_arm))
    wh = withheld[inside]
    scored = np.asarray(fix_t, float)[inside]
    m = {"n_estimates": len(est), "epochs": int(inside.sum()),
         "first_epoch_t": float(scored[0]) if len(scored) else None,
         "last_epoch_t": float(scored[-1]) if len(scored) else None, "h_rms_m": _rms(err),
         "h_max_m": float(err.max()) if len(err) else None, **outage_metrics(err, wh)}
    return m, inside, err
