"""A vehicle's own-sensor updates of one filter: GNSS fixes, zero velocity, zero angular rate
and the non-holonomic constraint, with the vehicle's installation (antenna lever arm, the
receiver's quality-dependent σ, the IMU-GNSS time offset).

Every method's filter takes these the same way; the cooperative parts (ranges, stop lines,
lanes) are :mod:`agent.methods`'. Pure numpy on top of :mod:`agent.nav`.
"""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from slcp.geo import earth

from .nav.ins_filter import InsFilter
from .nav.kalman import Measurement, UpdateResult
from .nav.measurements.gnss import gnss_position, gnss_velocity
from .nav.measurements.vehicle import non_holonomic, zero_angular_rate, zero_velocity

if TYPE_CHECKING:
    from .methods import FilterSettings

#: IMU samples averaged for the specific force of the time-offset column and the rate of ZARU
IMU_MEMORY = 10


class OwnSensors:
    """The own-sensor measurement models of one filter (``filter``, configured by ``settings``).

    ``mp`` are the GNSS error (multipath, common-mode) states and ``dtau`` the IMU-GNSS time
    offset state within ``filter.extra`` (None: not estimated). :meth:`imu` must see every IMU
    interval the filter integrates (the angular rate for the lever arm, the specific force for
    the time offset, the mean rate for ZARU).
    """

    def __init__(self, filt: InsFilter, settings: FilterSettings, mp: slice, dtau: int | None,
                 counters: dict[str, int]) -> None:
        self.filter = filt
        self.settings = settings
        self.mp = mp
        self.dtau = dtau
        self.counters = counters
        self.lever = np.array(settings.gnss_lever_arm, float)
        self._w_last: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._w: deque[tuple[float, float, float]] = deque(maxlen=IMU_MEMORY)
        self._f: deque[tuple[float, float, float]] = deque(maxlen=IMU_MEMORY)
        self._static: bool | None = None
        self._rejected_since: float | None = None  #: sensor time of the first fix rejected in a row
        self.last_fix_t = -math.inf  #: sensor time of the last fix applied [s]
        self._applied = 0.0  #: the time offset by which the fix being applied was moved [s]

    def imu(self, dtheta, dvel, dt: float) -> None:
        """One IMU interval: increments [rad], [m/s] over ``dt`` [s]."""
        if dt > 0.0:
            w = (dtheta[0] / dt, dtheta[1] / dt, dtheta[2] / dt)
            self._w_last = w
            self._w.append(w)
            self._f.append((dvel[0] / dt, dvel[1] / dt, dvel[2] / dt))

    @property
    def w_b(self) -> np.ndarray:
        """The latest raw angular rate [rad/s] (3,)."""
        return np.array(self._w_last)

    def mean_rate(self) -> np.ndarray:
        """The mean raw angular rate of the latest samples [rad/s] (3,)."""
        return np.mean(np.array(self._w), axis=0) if self._w else np.zeros(3)

    # ----------------------------------------------------------------- GNSS
    def sigma_scale(self, quality: int) -> float:
        """How much the receiver's reported σ is widened for a solution of ``quality`` (1 fixed
        RTK, 2 float RTK, anything else a code solution)."""
        fixed, floating, other = self.settings.gnss_quality_scale
        return fixed if quality == 1 else floating if quality == 2 else other

    def gnss(self, llh: np.ndarray, v_ned: np.ndarray, sigma_ned: np.ndarray, sigma_v: float,
             quality: int = 1, moving: bool = True, heading_known: bool = True,
             applied_offset: float = 0.0, velocity: bool = True) -> UpdateResult:
        """A GNSS fix: the position through the χ² gate (re-anchored after
        ``gnss_reset_after`` s of rejections), then the velocity, and with the non-holonomic
        constraint on, its rows while moving. The fix is applied at the filter time of its
        GNSS time by the time offset ``applied_offset`` [s]. Without ``velocity`` (a receiver
        that reports positions only) there is no velocity row."""
        self._applied = applied_offset
        s, f = self.settings, self.filter
        k = self.sigma_scale(quality)
        m = self._position(llh, np.asarray(sigma_ned, float) * k, moving)
        res = f.update(m, s.gnss_gate)
        if res.accepted:
            self._rejected_since = None
        else:
            self.counters["gnss_rejected"] += 1
            if self._rejected_since is None:
                self._rejected_since = f.t
            elif f.t - self._rejected_since >= s.gnss_reset_after:
                f.inflate_position(np.square(m.z))
                res = f.update(m)
                self._rejected_since = None
                self.counters["gnss_reanchored"] += 1
        if velocity:
            sv = max(sigma_v * k, s.gnss_min_sigma_v)
            mv = gnss_velocity(f.state, v_ned, np.eye(3) * sv**2, self.w_b, self.lever)
            f.update(self._delayed(mv, "velocity"))
        if s.nhc_sigma is not None and moving and heading_known:
            f.update(self.nhc())
        self.last_fix_t = f.t
        self.counters["gnss"] += int(res.accepted)
        return res

    def _position(self, llh: np.ndarray, sigma_ned: np.ndarray, moving: bool) -> Measurement:
        """The position row: plus the GNSS error states when modelled (the white part is what
        remains), else at the reported σ."""
        s, f = self.settings, self.filter
        if not s.gnss_multipath_sigma:
            m = gnss_position(f.state, llh, np.diag(np.square(np.maximum(sigma_ned, s.gnss_min_sigma))), self.lever)
            return self._delayed(m, "position")
        static = not moving
        if s.gnss_multipath_tau_static and static != self._static:
            # a standing receiver sees the same reflections: its multipath decorrelates slowly
            self._static = static
            tau = s.gnss_multipath_tau_static if static else s.gnss_multipath_tau
            for i in range(3):
                f.set_gauss_markov(i, s.gnss_multipath_sigma, tau)
        m = gnss_position(f.state, llh, np.eye(3) * s.gnss_white_sigma**2, self.lever)
        hx = np.zeros((3, len(f.extra)))
        hx[:, self.mp] = np.tile(np.eye(3), (1, self.mp.stop // 3))
        m = Measurement(m.z + hx @ f.extra, f.full_jacobian(m.H, hx), m.R, m.name)
        return self._delayed(m, "position")

    def _delayed(self, m: Measurement, kind: str) -> Measurement:
        """With the time offset δτ estimated, the fix of time t is the truth at t − δτ in
        filter time: position rows see −v δτ, velocity rows −a δτ (to first order in δτ,
        which the sensor driver's offset keeps to a fraction of a second)."""
        if self.dtau is None:
            return m
        f = self.filter
        st = f.state
        if kind == "position":
            col = -st.v
        else:
            f_b = np.mean(np.array(self._f), axis=0) if self._f else np.zeros(3)
            col = -(st.dcm @ (f_b - st.ba))
            col[2] -= earth.gravity(st.lat, st.h)  # specific force + gravity: the NED acceleration
        n_nav = f.extra_offset
        H = m.H if m.H.shape[1] == f.n else f.full_jacobian(m.H[:, :n_nav])
        H = H.copy()
        H[:, n_nav + self.dtau] = col
        # predicted at the estimated offset: the fix was applied where the offset then put it,
        # h(x) ≈ value(t) + col (δτ − that offset)
        return Measurement(m.z + col * (float(f.extra[self.dtau]) - self._applied), H, m.R, m.name)

    # ----------------------------------------------------------------- motion
    def zupt(self) -> UpdateResult | None:
        """Zero velocity (the caller decided the vehicle is at rest), and zero angular rate
        with ``zaru_sigma``."""
        s, f = self.settings, self.filter
        if s.zupt_sigma is None:
            return None
        res = f.update(zero_velocity(f.state, s.zupt_sigma))
        self.counters["zupt"] = self.counters.get("zupt", 0) + int(res.accepted)
        self.zaru()
        return res

    def zaru(self) -> None:
        """Zero angular rate at rest, with ``zaru_sigma`` (it observes the gyro biases, which
        GNSS does not while the vehicle stands)."""
        s, f = self.settings, self.filter
        if s.zaru_sigma is not None and len(self._w) == self._w.maxlen:
            f.update(zero_angular_rate(f.state, self.mean_rate(), s.zaru_sigma))
            self.counters["zaru"] = self.counters.get("zaru", 0) + 1

    def nhc(self) -> Measurement:
        """No sideways or vertical body velocity at the rear axle. The IMU sits an unknown
        distance l ahead of or behind it, where the body's rotation adds ω × (l, 0, 0) =
        (0, ω_z l, −ω_y l): the lateral σ grows with the yaw rate and the vertical σ with the
        pitch rate (braking, bumps, crests), each times that unknown distance."""
        s = self.settings
        w = self._w_last
        sig = math.hypot(s.nhc_sigma or 0.0, abs(w[2]) * s.nhc_lever_uncertainty)
        sig_v = math.hypot(s.nhc_vertical_sigma, abs(w[1]) * s.nhc_lever_uncertainty)
        return non_holonomic(self.filter.state, sig, sig_v)

    def coast(self, moving: bool, heading_known: bool) -> None:
        """Between fixes: the non-holonomic constraint on its own once no fix came for
        ``nhc_coast_after`` s (with fixes it rides on their updates)."""
        s, f = self.settings, self.filter
        if (s.nhc_sigma is not None and moving and heading_known
                and f.t - self.last_fix_t > s.nhc_coast_after):
            f.update(self.nhc())
            self.counters["nhc"] = self.counters.get("nhc", 0) + 1
