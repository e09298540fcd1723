"""Closed-loop GNSS/INS error-state EKF: nominal-state mechanisation plus 15-state covariance.

The nominal state is integrated at the IMU rate; the covariance may be propagated at a lower
rate (``cov_interval``), using the mean specific force over the accumulated interval, and is
always brought to the current time before an update. After each update the estimated error is
fed back into the nominal state and reset to zero (closed loop).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import cast

import numpy as np

from slcp.geo.earth import offset_llh

from .error_model import (
    ImuNoise,
    discretize_density,
    gap_transition,
    process_noise_density,
    system_matrix,
    unknown_heading_noise,
)
from .fusion import split_ci_update
from .kalman import FilterStats, Measurement, UpdateResult, joseph, kalman_update, stack
from .mechanization import mechanize_run
from .rotation import euler_to_quat, quat_to_euler, wrap_angle
from .source_fusion import COMMON_MODE, SourcePart, SourceSplit
from .state import ATT, N_STATES, POS, VEL, NavState, remove_error


class InsFilter:
    """Error-state EKF of one vehicle.

    Parameters
    ----------
    state : NavState
        Initial nominal state.
    P : ndarray, shape (15, 15)
        Initial error covariance.
    noise : ImuNoise
        IMU stochastic model (SI units).
    t : float
        Time of ``state`` [s] (sensor time).
    cov_interval : float
        Covariance propagation interval [s]; 0 propagates at every IMU sample.
    discretization : {"series", "van_loan"}
    extra_states : sequence of (initial value, initial sigma, PSD[, tau]), optional
        Additional states appended after the 15 navigation errors: random walks (no ``tau``,
        e.g. the IMU-GNSS time offset) or first-order Gauss-Markov processes with correlation
        time ``tau`` [s] and driving PSD ``2 σ²/τ`` (e.g. GNSS multipath per axis). Their
        nominal values live in :attr:`extra` (GM means decay with ``exp(-dt/τ)``); measurements
        give their Jacobian columns after the 15th. ``P`` may be 15x15 (the extra variances are
        then appended) or full size.
    scale_factors : (accel sigma, gyro sigma, tau), optional
        Estimate IMU scale-factor errors (dimensionless, per axis) as six Gauss-Markov states
        placed between the 15 navigation errors and ``extra_states``: measured increments are
        modelled as ``(1 + s) * true + bias``. Nominal values in :attr:`scale` (accel xyz, gyro xyz).
    """

    def __init__(
        self,
        state: NavState,
        P: np.ndarray,
        noise: ImuNoise,
        t: float = 0.0,
        cov_interval: float = 0.0,
        discretization: str = "series",
        extra_states: tuple[tuple[float, ...], ...] = (),
        scale_factors: tuple[float, float, float] | None = None,
    ) -> None:
        P = np.array(P, float)
        specs: list[tuple[float, ...]] = []
        if scale_factors is not None:
            sa, sg, tau = scale_factors
            specs += [(0.0, sa, 2 * sa * sa / tau, tau)] * 3 + [(0.0, sg, 2 * sg * sg / tau, tau)] * 3
        self.n_scale = len(specs)
        specs += [tuple(e) for e in extra_states]
        n = N_STATES + len(specs)
        if P.shape == (N_STATES, N_STATES) and specs:
            P = np.pad(P, (0, len(specs)))
            for i, spec in enumerate(specs):
                P[N_STATES + i, N_STATES + i] = spec[1] ** 2
        if P.shape != (n, n):
            raise ValueError(f"P must be {n}x{n}, got {P.shape}")
        self.n = n
        #: column of the first ``extra_states`` entry in P and in measurement Jacobians
        self.extra_offset = N_STATES + self.n_scale
        self.scale = np.zeros(self.n_scale)
        self.extra = np.array([e[0] for e in specs[self.n_scale:]], float)
        self._aug_psd = np.array([e[2] for e in specs], float)
        self._aug_tau = np.array([e[3] if len(e) > 3 else math.inf for e in specs], float)
        self.state = state
        self.P = 0.5 * (P + P.T)
        self.noise = noise
        self.t = float(t)
        self.cov_interval = float(cov_interval)
        self.discretization = discretization
        self.stats = FilterStats()
        self._gqg = process_noise_density(noise)
        self._prev_dtheta: tuple[float, float, float] | None = None
        self._prev_dvel: tuple[float, float, float] | None = None
        self._acc_dt = 0.0
        self._acc_dv_b = (0.0, 0.0, 0.0)
        self._acc_dth_b = (0.0, 0.0, 0.0)
        self._cov_state: NavState | None = None
        #: independent part of P for split covariance intersection (None: not tracked); see
        #: :meth:`track_independent`
        self.P_ind: np.ndarray | None = None
        #: P split by information source for source CI (None: not tracked); see
        #: :meth:`track_sources`
        self.sources: SourceSplit | None = None
        #: the heading is unknown (a vehicle that starts standing): yaw takes no part in updates
        self.yaw_free = False
        self._shared = np.zeros(0, int)
        self._unshared = np.zeros(0, int)
        #: *consider* states (Schmidt-Kalman): updates never change their estimates, and their
        #: covariances follow exactly (:func:`agent.nav.kalman.kalman_update`)
        self.consider = np.zeros(0, int)

    def set_gauss_markov(self, k: int, sigma: float, tau: float) -> None:
        """Change the steady-state σ and correlation time τ [s] of Gauss-Markov extra state ``k``
        (index within ``extra_states``) from now on, e.g. a multipath τ that depends on motion."""
        self.flush_covariance()
        i = self.n_scale + k
        self._aug_tau[i] = tau
        self._aug_psd[i] = 2.0 * sigma * sigma / tau

    def track_independent(self, dependent: np.ndarray | None = None, shared: tuple[int, ...] = (),
                          unshared: tuple[int, ...] = ()) -> None:
        """Start tracking the independent part of P.

        Parameters
        ----------
        dependent : ndarray, shape (n, n), optional
            The part of the current P that is *not* independent of other vehicles' estimates
            (default: none of it).
        shared : tuple of int
            Indices (within ``extra_states``) of states whose error other vehicles share, e.g. a
            common-mode GNSS error: their process noise counts as dependent from now on.
        unshared : tuple of int
            Indices (within the whole state) of states that no cooperative measurement observes
            and that count as independent at every split-CI update, whatever their history (e.g.
            the vertical channel under a horizontal range model). Otherwise every update inflates
            their dependent part by 1/ω and nothing shrinks it again: the vertical σ of a vehicle
            fusing ranges at 10 Hz grew from 2.5 m to hundreds of metres in 30 s.
        """
        self.flush_covariance()
        self.P_ind = self.P - (dependent if dependent is not None else 0.0)
        self._shared = np.array([self.n_scale + N_STATES + k for k in shared], int)
        self._unshared = np.array(unshared, int)

    def track_sources(self, me: str, common_mode: np.ndarray | None = None, shared: tuple[int, ...] = (),
                      unshared: tuple[int, ...] = ()) -> None:
        """Start splitting P by information source (:mod:`agent.nav.source_fusion`).

        Parameters
        ----------
        me : str
            This vehicle's id, the name of its own source.
        common_mode : ndarray, shape (n, n), optional
            The part of the current P that comes from the GNSS error all vehicles share.
        shared, unshared : tuple of int
            As :meth:`track_independent`: extra states whose process noise is the shared GNSS
            error's, and states no cooperative measurement observes.
        """
        self.flush_covariance()
        self.sources = SourceSplit(me, self.n, unshared,
                                   [self.n_scale + N_STATES + k for k in shared])
        if common_mode is not None:
            self.sources.add(frozenset({COMMON_MODE}), np.array(common_mode, float))

    # ------------------------------------------------------------------ propagation
    def propagate(self, dtheta: np.ndarray | Sequence[float], dvel: np.ndarray | Sequence[float], dt: float) -> None:
        """Integrate one IMU interval of raw increments lasting ``dt`` s.

        ``dtheta`` [rad] and ``dvel`` [m/s] are 3-sequences (body FRD): arrays, lists or tuples.
        """
        th = dtheta.tolist() if isinstance(dtheta, np.ndarray) else dtheta
        dv = dvel.tolist() if isinstance(dvel, np.ndarray) else dvel
        self.propagate_run((th,), (dv,), (float(dt),))

    def propagate_run(self, dtheta: Sequence[Sequence[float]], dvel: Sequence[Sequence[float]],
                      dt: Sequence[float], velocities: list[tuple[float, float, float]] | None = None) -> None:
        """Integrate ``n`` consecutive IMU intervals: the same as ``n`` calls of
        :meth:`propagate` (the same arithmetic in the same order), at a fraction of the cost.

        ``dtheta`` [rad] and ``dvel`` [m/s] are sequences of ``n`` 3-sequences (body FRD) and
        ``dt`` of ``n`` interval lengths [s]: plain lists (or tuples) of floats. ``velocities``
        (optional) gets each interval's NED velocity at its start appended.
        """
        n = len(dt)
        i = 0
        while i < n:
            # up to the next covariance step, as propagate() would take it
            if self._acc_dt == 0.0:
                self._cov_state = self.state
            acc, j = self._acc_dt, i
            while j < n:
                d = dt[j]
                if not d > 0.0:
                    raise ValueError(f"IMU interval must be positive, got {d}")
                acc += d
                j += 1
                if acc >= self.cov_interval:
                    break
            th, dv = dtheta[i:j], dvel[i:j]
            if self.n_scale:
                sa0, sa1, sa2, sg0, sg1, sg2 = self.scale.tolist()
                dv = [(x[0] * (1 - sa0), x[1] * (1 - sa1), x[2] * (1 - sa2)) for x in dv]
                th = [(x[0] * (1 - sg0), x[1] * (1 - sg1), x[2] * (1 - sg2)) for x in th]
            # the interval's sums continue sample by sample (as one call per sample adds them)
            new, pth, pdv, sth, sdv = mechanize_run(self.state, th, dv, dt[i:j], self._prev_dtheta, self._prev_dvel,
                                                    (self._acc_dth_b, self._acc_dv_b), velocities)
            self._prev_dtheta, self._prev_dvel = pth, pdv
            self._acc_dv_b = sdv
            if self.n_scale:
                self._acc_dth_b = sth
            self.state = new
            for k in range(i, j):  # the clock as propagate() advances it (same rounding)
                self.t += dt[k]
            self._acc_dt = acc
            self.stats.imu_samples += j - i
            i = j
            if self._acc_dt >= self.cov_interval:
                self.flush_covariance()

    def flush_covariance(self) -> None:
        """Propagate P over the IMU samples integrated since the last covariance step."""
        dt = self._acc_dt
        if dt <= 0.0:
            return
        lin = self._cov_state if self._cov_state is not None else self.state
        c_bn = lin.dcm
        f_b = np.array(self._acc_dv_b) / dt
        F = system_matrix(lin, c_bn @ f_b, self.noise)
        if self.n > N_STATES:
            # augmented model: scale factors couple into velocity/attitude errors,
            # every augmented state is a random walk or first-order Gauss-Markov process
            n = self.n
            Fa = np.zeros((n, n))
            Fa[:N_STATES, :N_STATES] = F
            if self.n_scale:
                w_b = np.array(self._acc_dth_b) / dt
                Fa[VEL, 15:18] = -c_bn * f_b[None, :]
                Fa[ATT, 18:21] = c_bn * w_b[None, :]
            idx = np.arange(N_STATES, n)
            Fa[idx, idx] = -1.0 / self._aug_tau
            F = Fa
            q = np.concatenate([self._gqg, self._aug_psd])
            decay = np.exp(-dt / self._aug_tau)
            self.scale = self.scale * decay[: self.n_scale]
            self.extra = self.extra * decay[self.n_scale:]
        else:
            q = self._gqg
        phi, qd = discretize_density(F, q, dt, self.discretization)
        if self.yaw_free:
            qd[VEL, VEL] += unknown_heading_noise(c_bn @ f_b, dt)
        self._transition(phi, qd)
        self._acc_dt = 0.0
        self._acc_dv_b = (0.0, 0.0, 0.0)
        self._acc_dth_b = (0.0, 0.0, 0.0)
        self._cov_state = None
        self.stats.cov_steps += 1

    def _transition(self, phi: np.ndarray, qd: np.ndarray) -> None:
        """P ← Φ P Φᵀ + Q_d, and the same for the independent part and the sources."""
        P = phi @ self.P @ phi.T + qd
        self.P = 0.5 * (P + P.T)
        if self.P_ind is not None:  # process noise is independent information loss...
            if self._shared.size:  # ...except that of errors other vehicles share
                qd = qd.copy()
                qd[self._shared, :] = 0.0
                qd[:, self._shared] = 0.0
            Pi = phi @ self.P_ind @ phi.T + qd
            self.P_ind = 0.5 * (Pi + Pi.T)
        if self.sources is not None:
            self.sources.propagate(phi, qd)

    # ------------------------------------------------------------------ updates
    def full_jacobian(self, H_nav: np.ndarray, H_extra: np.ndarray | None = None) -> np.ndarray:
        """Measurement Jacobian over the whole (augmented) state from its navigation part,
        shape (m, 15), and optionally its ``extra_states`` part, shape (m, len(extra))."""
        H = np.zeros((H_nav.shape[0], self.n))
        H[:, :N_STATES] = H_nav
        if H_extra is not None:
            H[:, self.extra_offset:] = H_extra
        return H

    def _prepare(self, meas: Measurement) -> Measurement:
        """Before an update: the covariance brought to now, the heading isolated while unknown,
        and ``meas.H`` widened to the whole state (a navigation-only H has 15 columns)."""
        self.flush_covariance()
        self._isolate_yaw()
        if meas.H.shape[1] < self.n:
            H = np.zeros((meas.H.shape[0], self.n))
            H[:, : meas.H.shape[1]] = meas.H
            meas = Measurement(meas.z, H, meas.R, meas.name)
        return meas

    def update(self, meas: Measurement, gate_probability: float | None = None) -> UpdateResult:
        """Kalman update with one measurement, closed-loop feedback, and reset."""
        meas = self._prepare(meas)
        dx, P, result = kalman_update(self.P, meas, gate_probability, self.consider)
        if result.accepted:
            gain = cast(np.ndarray, result.gain)  # an accepted update carries its gain
            if self.P_ind is not None:  # an own-sensor measurement: independent information
                self.P_ind = joseph(self.P_ind, gain, meas.H, meas.R)
            if self.sources is not None:  # the same: its noise is the own component's
                self.sources.transform(gain, meas.H)
            self._feedback(dx)
            self.P = P
        self.stats.count(result)
        return result

    def update_split_ci(self, meas: Measurement, R_dep: np.ndarray, own_independent: bool = True,
                        gate_probability: float | None = None, min_gain: float = 0.0) -> UpdateResult:
        """Split covariance-intersection update (:mod:`agent.nav.fusion`) with closed-loop feedback.

        ``meas.R`` is the independent measurement noise and ``R_dep`` the part that may be
        correlated with this filter's estimate (e.g. a neighbour's cooperative information).
        With ``own_independent`` False (plain CI) the whole prior counts as dependent.
        ω minimises the horizontal position variance; ``min_gain`` skips updates expected to
        reduce it by less than that fraction (node selection).
        """
        meas = self._prepare(meas)
        Pi = self.P_ind if (own_independent and self.P_ind is not None) else np.zeros_like(self.P)
        if self._unshared.size:  # their rows and columns of the dependent part are zero
            Pi = Pi.copy()
            Pi[self._unshared, :] = self.P[self._unshared, :]
            Pi[:, self._unshared] = self.P[:, self._unshared]
        dx, P, Pi_post, result = split_ci_update(self.P, Pi, meas, np.atleast_2d(R_dep), _HORIZONTAL,
                                                 gate_probability, min_gain)
        if result.accepted:
            self._feedback(dx)
            self.P = P
            if self.P_ind is not None:
                self.P_ind = Pi_post
        if not result.skipped:
            self.stats.count(result)
        return result

    def update_source_ci(self, meas: Measurement, parts: list[SourcePart], noise_labels: frozenset[str],
                         gate_probability: float | None = None, min_gain: float = 0.0,
                         constants: Sequence[tuple[str, float]] = (),
                         velocity_horizon: float = 0.0) -> UpdateResult:
        """Source-CI update (:mod:`agent.nav.source_fusion`) with closed-loop feedback.

        ``meas.R`` is the measurement's white noise, kept under ``noise_labels``; ``parts`` the
        rest of its error by source (e.g. the neighbour's components), ``constants`` its
        sensitivity to exactly tracked random constants. The weights minimise the horizontal
        position variance, plus τ² times the horizontal velocity variance for a
        ``velocity_horizon`` τ > 0 [s] (the position variance τ seconds on, less the
        covariance term); ``min_gain`` as :meth:`update_split_ci`, on the same sum.
        """
        if self.sources is None:
            raise RuntimeError("source CI needs track_sources() first")
        meas = self._prepare(meas)
        if velocity_horizon > 0.0:
            idx, weight = _HORIZONTAL_PV, np.array([1.0, 1.0, velocity_horizon**2, velocity_horizon**2])
        else:
            idx, weight = _HORIZONTAL, None
        dx, P, result = self.sources.update(self.P, meas, parts, idx, noise_labels,
                                            gate_probability, min_gain, constants, self.consider, weight)
        if result.accepted:
            self._feedback(dx)
            self.P = P
        if not result.skipped:
            self.stats.count(result)
        return result

    def _feedback(self, dx: np.ndarray) -> None:
        """Remove the estimated error from the nominal state (closed loop)."""
        self.state = remove_error(self.state, dx[:N_STATES])
        if self.n_scale:
            self.scale = self.scale - dx[N_STATES:self.extra_offset]
        if self.n > self.extra_offset:
            self.extra = self.extra - dx[self.extra_offset:]

    def update_stacked(
        self, measurements: list[Measurement], gate_probability: float | None = None
    ) -> UpdateResult:
        """One update with several independent measurements stacked (paper eq. 29)."""
        if not measurements:
            raise ValueError("no measurements to stack")
        name = "+".join(m.name for m in measurements)
        return self.update(stack(measurements, name), gate_probability)

    # ------------------------------------------------------------------ helpers
    def _isolate_yaw(self) -> None:
        """While ``yaw_free``: the heading takes no part in an update (its correlations with
        the other states are dropped). A vehicle that starts standing has no heading; linearised
        about a heading 60° σ off, the updates turned its yaw by over 100° in 6 s through the
        estimated accelerometer bias and learned gyro biases of 10 σ, which sent the yaw tens
        of degrees off for a minute after it drove off."""
        if not self.yaw_free:
            return
        for P in (self.P, self.P_ind):
            if P is not None:
                d = P[2, 2]
                P[2, :] = 0.0
                P[:, 2] = 0.0
                P[2, 2] = d
        if self.sources is not None:
            self.sources.decorrelate(2)

    def reset_yaw(self, yaw: float, sigma: float) -> None:
        """Replace the heading by ``yaw`` [rad] (e.g. from the GNSS course) with std ``sigma``.

        Roll and pitch are kept; the yaw row/column of P is decorrelated from the rest, and
        ``yaw_free`` ends. The bias estimates stay: the INS turns its own attitude by the body
        rates, so a standing vehicle learns its gyro (and accelerometer) biases in the body
        frame, whatever its heading.
        """
        roll, pitch, _ = quat_to_euler(self.state.q)
        self.state.q = euler_to_quat(roll, pitch, float(wrap_angle(yaw)))
        self.flush_covariance()
        self.yaw_free = False
        self.P[2, :] = 0.0
        self.P[:, 2] = 0.0
        self.P[2, 2] = sigma**2  # (works for augmented P too)
        if self.P_ind is not None:
            self.P_ind[2, :] = 0.0
            self.P_ind[:, 2] = 0.0
            self.P_ind[2, 2] = sigma**2
        if self.sources is not None:
            self.sources.clear_states([2])

    def reset_velocity(self, v_ned: np.ndarray, sigma: float) -> None:
        """Replace the velocity by ``v_ned`` (3,) [m/s] (e.g. a GNSS velocity) with std ``sigma``
        [m/s] per axis, decorrelated from the rest: with the heading from the GNSS course, the
        velocity integrated under the heading it replaces is void."""
        self.flush_covariance()
        self.state.v = np.asarray(v_ned, float).copy()
        for P in (self.P, self.P_ind):
            if P is not None:
                P[VEL, :] = 0.0
                P[:, VEL] = 0.0
                P[VEL, VEL] = np.eye(3) * sigma**2
        if self.sources is not None:
            self.sources.clear_states(np.arange(VEL.start, VEL.stop))

    def inflate_position(self, variance: np.ndarray) -> None:
        """Add ``variance`` (3,) [m²] to the NED position error variances: uncertainty of the
        vehicle's own (independent) kind, e.g. before re-anchoring on a fix long rejected."""
        delta = np.zeros((self.n, self.n))
        idx = np.arange(POS.start, POS.stop)
        delta[idx, idx] = variance
        self.inflate(delta)

    def coast(self, gap: float, sigma_accel: tuple[float, float], sigma_rate: tuple[float, float]) -> None:
        """No IMU data for ``gap`` s (a frozen process, a sensor outage): the state moves on at
        its velocity, and the covariance grows by what the vehicle may have done meanwhile
        (:func:`error_model.gap_transition`)."""
        if not gap > 0.0:
            return
        self.flush_covariance()
        st = self.state
        lat, lon, h = offset_llh(st.llh, st.v * gap)
        self.state = NavState(float(lat), float(lon), float(h), st.v.copy(), st.q.copy(), st.bg.copy(), st.ba.copy())
        phi, qd = gap_transition(self.n, gap, sigma_accel, sigma_rate, self._gqg, self._aug_tau, self._aug_psd)
        if self.n > N_STATES:
            decay = np.diag(phi)[N_STATES:]
            self.scale = self.scale * decay[: self.n_scale]
            self.extra = self.extra * decay[self.n_scale:]
        self._transition(phi, qd)
        self.t += gap

    def inflate(self, delta: np.ndarray) -> None:
        """Add ``delta`` (n, n), symmetric positive semi-definite, to P: uncertainty of the
        vehicle's own (independent) kind, e.g. after a fault has been detected."""
        self.flush_covariance()
        delta = np.asarray(delta, float)
        if delta.shape != (self.n, self.n):
            raise ValueError(f"delta must be {self.n}x{self.n}, got {delta.shape}")
        self.P += delta
        if self.P_ind is not None:
            self.P_ind += delta

    @property
    def position_cov(self) -> np.ndarray:
        """NED position error covariance, shape (3, 3) [m²]."""
        self.flush_covariance()
        cov: np.ndarray = self.P[POS, POS].copy()
        return cov

    @property
    def velocity_cov(self) -> np.ndarray:
        """NED velocity error covariance, shape (3, 3) [m²/s²]."""
        self.flush_covariance()
        cov: np.ndarray = self.P[VEL, VEL].copy()
        return cov


_HORIZONTAL = np.array([POS.start, POS.start + 1])
_HORIZONTAL_PV = np.array([POS.start, POS.start + 1, VEL.start, VEL.start + 1])

