"""Cooperative integrity: solution separation between a cooperative filter and its own-sensor twin.

A cooperative method (CP, SL-CP) fuses everything its own-sensor twin (SP, SL-SP) fuses, plus
the neighbours' beacons and the UWB ranges. Under no fault both estimates are consistent, so
their horizontal difference ``d`` is bounded by their covariances; the cooperative information
is *faulty* when ``d`` is far larger than they allow. This is the solution-separation test of
GNSS integrity monitoring (ARAIM: the full-set solution against the subset that excludes the
suspect measurements; Brenner 1996, Blanch et al. 2012), with the cooperative measurements as
the excluded set.

What it catches here: a persistent UWB NLOS bias (0.3-3 m) that no innovation test could see
(the link was already NLOS at its first range, while both positions were uncertain to metres),
fused range after range and amplified by the geometry (a range nearly across a vehicle's track
moves it along the track by the innovation over the small direction cosine), until the
cooperative estimate stands metres off at a decimetre σ. Its χ² gates then refuse the very
measurements that could correct it (the lane rows, and the first-stopped claim whose gate is
its own σ), while its own-sensor twin, standing on its stop line, is right.

The test: ``dᵀ (P_coop + P_own)⁻¹ d`` over the horizontal position, against the χ² quantile
(2 degrees of freedom) of ``1 - p`` for a false-alarm probability ``p`` per test. The two
estimates share the own sensors' errors, so the variance of ``d`` is at most ``P_coop + P_own``
for positively correlated errors: the test is conservative (false alarms fewer than ``p``).
When it fires, the cooperative filter's horizontal position is widened by the separation
(:meth:`~agent.methods.MethodFilter.widen_position`: ``d²`` per axis on the position, and as much
along position and GNSS error state together, which the fixes cannot see), an uncertainty of its
own kind, as when a GNSS fix long refused re-anchors it. Its own measurements (GNSS, lane rows,
the stop line) are then accepted again and pull it back; nothing of the own-sensor estimate is
copied into it (that would count the own sensors twice).

Pure numpy (no I/O, and no scipy, which an agent process does not import): the runtime and
the in-process evaluation call :func:`check_separation` at the decision rate.
"""

from __future__ import annotations

import math

import numpy as np

from slcp.geo import earth

from .methods import MethodFilter

#: the own-sensor twin of each cooperative method
OWN_TWIN = {"CP": "SP", "SL-CP": "SL-SP"}


def separation(coop_llh: np.ndarray, coop_cov: np.ndarray, own_llh: np.ndarray,
               own_cov: np.ndarray) -> tuple[np.ndarray, float]:
    """Horizontal solution separation and its normalised square.

    Parameters
    ----------
    coop_llh, own_llh : ndarray, shape (3,)
        Geodetic positions (latitude, longitude [rad], ellipsoidal height [m]).
    coop_cov, own_cov : ndarray, shape (3, 3) or (2, 2)
        NED position error covariances [m²] (the horizontal block is used).

    Returns
    -------
    d : ndarray, shape (2,)
        North and east of the cooperative estimate relative to the own one [m].
    nis : float
        ``dᵀ (P_coop + P_own)⁻¹ d`` over the horizontal block (χ² with 2 degrees of freedom
        for independent consistent estimates; smaller for positively correlated ones).
    """
    n, e, _ = earth.ned_offset(float(coop_llh[0]), float(coop_llh[1]), float(coop_llh[2]),
                               float(own_llh[0]), float(own_llh[1]), float(own_llh[2]))
    d = np.array([n, e])
    s = np.asarray(coop_cov, float)[:2, :2] + np.asarray(own_cov, float)[:2, :2]
    try:
        nis = float(d @ np.linalg.solve(s, d))
    except np.linalg.LinAlgError:
        return d, math.inf
    return d, nis


def separation_threshold(false_alarm: float) -> float:
    """χ² quantile (2 degrees of freedom) for a false-alarm probability per test: the χ²(2)
    survival function is exp(-x/2), so the quantile is -2 ln p (no scipy in an agent)."""
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f"false-alarm probability must lie in (0, 1), got {false_alarm!r}")
    return -2.0 * math.log(false_alarm)


def check_separation(coop: MethodFilter, own: MethodFilter) -> bool:
    """Test ``coop`` against its own-sensor twin ``own``; on a fault, widen ``coop``'s position.

    The false-alarm probability is ``coop.settings.separation_false_alarm`` (None: no test).
    The test also fires when the *twin* is the faulty one (its GNSS locked on an NLOS fix, a
    wrong first-stopped claim); so a disagreement widens ``coop`` once, and while the two keep
    disagreeing after that, ``coop`` is left to its own measurements (``integrity_held``) until
    they agree again: without the latch a faulty twin would have ``coop`` widened at every
    test and drag it off too. Counts ``integrity_tests``, ``integrity_resets`` and ``integrity_held`` in
    ``coop.counters``. Returns whether ``coop`` was widened.
    """
    p = coop.settings.separation_false_alarm
    if p is None:
        return False
    coop.counters["integrity_tests"] += 1
    d, nis = separation(coop.filter.state.llh, coop.position_cov, own.filter.state.llh, own.position_cov)
    if not nis > separation_threshold(p):
        coop.separation_fault = False
        return False
    if coop.separation_fault:  # widened once for this disagreement: it may be the twin's fault
        coop.counters["integrity_held"] += 1
        return False
    coop.widen_position(d)
    coop.separation_fault = True
    coop.counters["integrity_resets"] += 1
    return True
