"""The four estimation methods of the paper, as pure filters driven by sensor-time events.

============  =====================================================================
method        fuses
============  =====================================================================
``SP``        own IMU + GNSS (loosely coupled)
``SL-SP``     SP + the stop-line fix while this vehicle is the first stopped one
``CP``        SP + UWB ranges to neighbours, with their beacons' positions (eq. 26-28)
``SL-CP``     all of the above
============  =====================================================================

No I/O here: the vehicle engine (:mod:`agent.engine`) feeds measurements in sensor-time order.
A method's filter is :class:`MethodFilter`: its own sensors (:mod:`agent.own_sensors`), its
ranges (:mod:`agent.range_updates`) and its site updates (:mod:`agent.site_updates`).
"""

from __future__ import annotations

import bisect
import math
from collections import deque

import numpy as np

from .nav.error_model import level_from_accel
from .nav.ins_filter import InsFilter
from .nav.kalman import UpdateResult, chi2_gate
from .nav.measurements.stop_line import StopGapModel
from .nav.rotation import euler_to_quat
from .nav.state import POS, VEL, NavState
from .own_sensors import OwnSensors
from .range_gate import NlosLinkTracker, RangeRateGate
from .range_updates import RangeUpdates
from .settings import DEFAULT_FUSION, FUSION_RULES, METHODS, FilterSettings, MethodSpec
from .site_updates import STOP_LINE_MAP_SIGMA, SiteUpdates

__all__ = ["DEFAULT_FUSION", "FUSION_RULES", "HEADING_WAIT", "METHODS", "STOP_LINE_MAP_SIGMA", "FilterSettings",
           "MethodFilter", "MethodSpec", "initial_state"]

#: longest wait [s] of the GNSS updates of a vehicle that drives off with its heading unknown
HEADING_WAIT = 1.0
#: a heading more uncertain than this [rad] (after a gap in the IMU data) is taken as unknown
HEADING_LOST = math.radians(30.0)
#: the GNSS course gives the heading once its σ is below this [rad]: the heading is then set
#: with twice that σ, within the linear range of the filter, which refines it. A code receiver's
#: velocity (σ 0.5 m/s) gives a course good to 10° above 2.9 m/s; at 5° it needed 5.7 m/s, and
#: a car creeping through town kept its heading unknown, and isolated, for many seconds
COURSE_SIGMA_MAX = math.radians(10.0)


def initial_state(llh: np.ndarray, v_ned: np.ndarray, f_b_mean: np.ndarray) -> NavState:
    """Initial nominal state from a GNSS fix and the mean specific force (level, heading from
    the GNSS course; a standing vehicle starts with heading 0 and a large yaw variance)."""
    roll, pitch = level_from_accel(f_b_mean)
    yaw = math.atan2(v_ned[1], v_ned[0]) if math.hypot(v_ned[0], v_ned[1]) > 1.0 else 0.0
    return NavState(float(llh[0]), float(llh[1]), float(llh[2]), np.asarray(v_ned, float).copy(),
                    euler_to_quat(roll, pitch, yaw))


class MethodFilter(RangeUpdates, SiteUpdates):
    """One method's filter for one vehicle."""

    def __init__(self, spec: MethodSpec, state: NavState, sigma_pos: np.ndarray, settings: FilterSettings,
                 t: float, gap: StopGapModel | None = None, origin_llh: tuple[float, float, float] | None = None,
                 heading_known: bool = True, vehicle: str = "self") -> None:
        s = settings
        self.vehicle = vehicle
        self.spec = spec
        self.settings = settings
        extra = self._extra_states(spec, s, gap)
        p0 = self._initial_variances(s, sigma_pos, heading_known)
        n = s.noise
        self._lane_id: str | None = None
        self._lane_seen = -math.inf  #: sensor time the current lane was last confirmed [s]
        self._lane_checked = -math.inf  #: sensor time of the last call of :meth:`lane_line` [s]
        self._sl_full = False  #: the current stop's fix has its lateral row
        self.filter = InsFilter(state, np.diag(p0), n, t=t, cov_interval=s.cov_interval, extra_states=extra)
        self.filter.yaw_free = not heading_known
        self._stop_id: float | None = None
        if self._mp.stop:
            self._init_from_fix_errors()
        if s.fusion not in FUSION_RULES:
            raise ValueError(f"unknown fusion rule {s.fusion!r}; choose from {', '.join(FUSION_RULES)}")
        if spec.ranges and s.fusion in ("split-ci", "source-ci"):
            self._track_fusion(s, vehicle)
        self.gap = gap
        self.origin = origin_llh
        self.heading_known = heading_known
        self._heading_wait_since: float | None = None  #: sensor time GNSS began waiting for the course
        self.last_stop_line = -math.inf
        self.counters = {"gnss": 0, "gnss_rejected": 0, "gnss_reanchored": 0,
                         "ranges": 0, "ranges_rejected": 0, "ranges_skipped": 0, "ranges_gate_physical": 0,
                         "ranges_gate_rate": 0, "ranges_gate_nis": 0, "ranges_gate_nlos": 0, "ranges_skipped_near": 0,
                         "ranges_skipped_held": 0, "stop_line": 0,
                         "lane_line": 0, "lane_line_rejected": 0,
                         "integrity_tests": 0, "integrity_resets": 0, "integrity_held": 0}
        self.own = OwnSensors(self.filter, s, self._mp, self._dtau, self.counters)
        #: the own-sensor models need the IMU rates (lever arm, time offset, ZARU, NHC)
        self._own_imu = bool(any(s.gnss_lever_arm) or s.time_offset or s.zaru_sigma or s.nhc_sigma)
        #: the cooperative integrity test has widened this filter for the current disagreement
        #: with its own-sensor twin (:func:`agent.integrity.check_separation`)
        self.separation_fault = False
        self.rate_gate = RangeRateGate()
        self.nlos_tracker = (NlosLinkTracker(s.uwb_nlos, s.sigma_uwb)
                             if s.uwb_nlos is not None and s.nlos_link_tracking and s.fusion != "paper" else None)
        self._range_gate_nis = chi2_gate(1, s.range_gate) if s.range_gate is not None else None
        #: per neighbour, its last declined range: (sensor time [s], own and neighbour's
        #: horizontal position variance [m²], line of sight (east, north)) (``selection_hold``)
        self._declined: dict[str, tuple[float, float, float, float, float]] = {}
        # INS displacement (NED, m) integrated from the nominal velocity, unaffected by updates:
        # places a delayed range at its own time (p(t) = p(now) - (D(now) - D(t)))
        self._disp = [0.0, 0.0, 0.0]
        self._disp_hist: deque[tuple[float, float, float, float]] = deque(maxlen=64)
        self._disp_hist.append((t, 0.0, 0.0, 0.0))
        self._n_constants = 0  #: constants named so far (:meth:`_track_constant`)
        if s.consider_constants and self.filter.sources is not None and s.exact_constants:
            k = [self.filter.extra_offset + i for sl in (self._sl, self._lane) if sl is not None
                 for i in range(sl.start, sl.stop)]
            self.filter.consider = np.array(k, int)
        if self._sl is not None:
            self._track_constant(self._sl, np.array([gap.sigma_xb, gap.sigma_yb]))
        if self._lane is not None:
            self._track_constant(self._lane, np.array([gap.sigma_yb]))

    def _track_fusion(self, s: FilterSettings, vehicle: str) -> None:
        """Split or source CI: track what of the covariance came from where."""
        # the common-mode GNSS error is shared with the neighbours: what we know of it is
        # not independent of their estimates
        cm = tuple(range(3, self._mp.stop)) if self._mp.stop > 3 else ()
        # a horizontal range observes the horizontal position (and, through the dynamics, the
        # horizontal velocity and the shared GNSS error); every other state (attitude, IMU
        # biases, the vertical channel, the stop-gap states) stays out of the CI inflation,
        # which otherwise compounds there with nothing to shrink it: a vehicle standing in a
        # queue for 30 s reached a yaw σ of 30° and diverged when it drove off
        unshared = ()
        if s.range_height_sigma is not None:
            off = self.filter.extra_offset
            shared_h = {VEL.start, VEL.start + 1, POS.start, POS.start + 1}
            shared_h |= {off + k for k in range(self._mp.stop) if k % 3 != 2}
            if self._sl is not None:
                # the stop-gap states carry my stop-line fix, which reaches my neighbours'
                # estimates through my beacons: counted as independent, the fix came back
                # through the ranges as news (a σ below the joint bound); they are reset when
                # the vehicle drives off (:meth:`end_stop`),
                # so nothing inflates them between stops
                shared_h |= {off + k for k in range(self._sl.start, self._sl.stop)}
            if self._lane is not None:  # the same, for the lane offset (reset between lanes)
                shared_h.add(off + self._lane.start)
            unshared = tuple(i for i in range(self.filter.n) if i not in shared_h)
        if s.fusion == "split-ci":
            self.filter.track_independent(self._common_mode_part(), shared=cm, unshared=unshared)
        else:
            self.filter.track_sources(vehicle, self._common_mode_part(), shared=cm, unshared=unshared)

    @staticmethod
    def _initial_variances(s: FilterSettings, sigma_pos: np.ndarray, heading_known: bool) -> np.ndarray:
        """The navigation states' initial variances: attitude (yaw 60° until the course gives
        it), velocity, position from the fix, and the biases (in-run and turn-on together)."""
        n = s.noise
        att = np.array(s.init_att_sigma)
        if not heading_known:
            att[2] = math.radians(60.0)
        bg0 = math.hypot(n.gyro_bias_sigma, s.init_gyro_bias_sigma or 0.0)
        ba0 = math.hypot(n.accel_bias_sigma, s.init_accel_bias_sigma or 0.0)
        return np.concatenate([att, [s.init_vel_sigma] * 3, np.maximum(sigma_pos, 0.1),
                               [max(bg0, 1e-6)] * 3, [max(ba0, 1e-4)] * 3]) ** 2

    def _extra_states(self, spec: MethodSpec, s: FilterSettings, gap: StopGapModel | None) -> tuple:
        """The filter's states beyond the navigation errors, their places kept in ``_mp``,
        ``_sl``, ``_lane`` and ``_dtau``: GNSS multipath and common mode (Gauss-Markov), this
        stop's gap deviations and this lane's offset (random constants), the time offset."""
        extra: tuple = ()
        if s.gnss_multipath_sigma:
            sm, tau = s.gnss_multipath_sigma, s.gnss_multipath_tau
            extra = tuple((0.0, sm, 2 * sm * sm / tau, tau) for _ in range(3))
            if s.gnss_common_sigma > 0.0:
                sc, tc = s.gnss_common_sigma, s.gnss_common_tau
                extra += tuple((0.0, sc, 2 * sc * sc / tc, tc) for _ in range(3))
        #: GNSS error states within ``filter.extra``: multipath (3), then common mode (3)
        self._mp = slice(0, len(extra))
        #: this stop's deviation of (d_s, d_l) from their means: random constants, reset at every
        #: new stop, so that repeated stop-line fixes share their error instead of averaging it
        self._sl: slice | None = None
        if spec.stop_line and gap is not None:
            self._sl = slice(len(extra), len(extra) + 2)
            extra += ((0.0, gap.sigma_xb, 0.0), (0.0, gap.sigma_yb, 0.0))
        #: the driver's lateral offset from m_yb in the current lane: a random constant, redrawn
        #: in each lane; with it, the stop-line fix's lateral row acts on it too (the same d_l)
        self._lane: slice | None = None
        if spec.stop_line and gap is not None and s.lane_constraint:
            self._lane = slice(len(extra), len(extra) + 1)
            extra += ((0.0, gap.sigma_yb, 0.0),)
        #: the IMU-GNSS time offset (a random walk) within ``filter.extra``
        self._dtau: int | None = None
        if s.time_offset is not None:
            self._dtau = len(extra)
            extra += ((0.0, s.time_offset[0], s.time_offset[1] ** 2),)
        return extra

    def _init_from_fix_errors(self) -> None:
        """The initial position comes from a GNSS fix, so its error *is* that fix's error:
        δp = m + c + w with the multipath m and common-mode c states at -m, -c (estimate minus
        truth). Give position the whole GNSS error budget and the matching correlations;
        treating them as independent makes the filter overconfident from its first update."""
        f, P = self.filter, self.filter.P  # still diagonal here
        for i in range(3):
            p = 6 + i
            err = [f.extra_offset + k for k in range(i, self._mp.stop, 3)]  # this axis' error states
            P[p, p] = self.settings.gnss_white_sigma**2 + sum(P[j, j] for j in err)
            for j in err:
                P[p, j] = P[j, p] = -P[j, j]

    def widen_position(self, d_ne: np.ndarray) -> None:
        """A fault has moved the horizontal position by up to ``d_ne`` (north, east) [m]: add
        ``d²`` per axis to its variance, and as much along each GNSS error state of that axis
        taken with the opposite sign. The fixes see position plus GNSS error, and a fault that
        pulled the position away while the fixes kept agreeing has put its error into the GNSS
        error states too: widened alone, the position is pinned again by the next fix, where it
        stands."""
        f = self.filter
        delta = np.zeros((f.n, f.n))
        for i in range(2):
            var = float(d_ne[i]) ** 2
            p = POS.start + i
            delta[p, p] += var
            for k in range(i, self._mp.stop, 3):  # this axis' multipath (and common-mode) state
                v = np.zeros(f.n)
                v[p], v[f.extra_offset + k] = 1.0, -1.0
                delta += var * np.outer(v, v)
        f.inflate(delta)

    def _common_mode_part(self) -> np.ndarray | None:
        """The initial covariance's common-mode share: δp = m + c + w puts +σ_c² on position,
        −σ_c² between position and the c states, σ_c² on c."""
        f = self.filter
        if self._mp.stop <= 3:
            return None
        D = np.zeros_like(f.P)
        for i in range(3):
            p, c = 6 + i, f.extra_offset + 3 + i
            var = f.P[c, c]
            D[p, p], D[c, c], D[p, c], D[c, p] = var, var, -var, -var
        return D

    @property
    def t(self) -> float:
        return self.filter.t

    def propagate(self, dtheta, dvel, dt: float) -> None:
        v = self.filter.state.v
        d = self._disp
        d[0] += float(v[0]) * dt
        d[1] += float(v[1]) * dt
        d[2] += float(v[2]) * dt
        self.filter.propagate(dtheta, dvel, dt)
        if self._own_imu:
            self.own.imu(dtheta, dvel, dt)
        if self.filter.t - self._disp_hist[-1][0] >= 0.05:
            self._disp_hist.append((self.filter.t, d[0], d[1], d[2]))

    def propagate_run(self, dtheta: list, dvel: list, dt: list[float]) -> None:
        """``n`` consecutive IMU intervals (lists of 3-lists and of lengths [s]): the same as
        ``n`` calls of :meth:`propagate`, with one mechanisation call for the run."""
        vel: list[tuple[float, float, float]] = []
        t = self.filter.t
        self.filter.propagate_run(dtheta, dvel, dt, vel)
        d, hist = self._disp, self._disp_hist
        d0, d1, d2 = d
        last = hist[-1][0]
        for k in range(len(dt)):
            v, dt_k = vel[k], dt[k]
            d0 += v[0] * dt_k
            d1 += v[1] * dt_k
            d2 += v[2] * dt_k
            t += dt_k  # the filter's clock, added as it adds it
            if t - last >= 0.05:
                hist.append((t, d0, d1, d2))
                last = t
        d[0], d[1], d[2] = d0, d1, d2
        if self._own_imu:
            for k in range(len(dt)):
                self.own.imu(dtheta[k], dvel[k], dt[k])

    def displacement_since(self, t: float) -> np.ndarray:
        """INS displacement [m] (NED, (3,)) from time ``t`` to the filter time (0 if ``t`` is
        not in the recent history, which spans about 3 s)."""
        h = self._disp_hist
        if t >= self.filter.t or t < h[0][0]:
            return np.zeros(3)
        i = bisect.bisect_right(h, t, key=lambda x: x[0])  # h[i-1][0] <= t < h[i][0]
        d = self._disp
        if i >= len(h):  # after the newest entry: its value (as np.interp would clamp)
            p = h[-1]
            return np.array([d[0] - p[1], d[1] - p[2], d[2] - p[3]])
        p0, p1 = h[i - 1], h[i]
        a = (t - p0[0]) / (p1[0] - p0[0])
        return np.array([d[k - 1] - (p0[k] + a * (p1[k] - p0[k])) for k in (1, 2, 3)])

    def gnss(self, llh: np.ndarray, v_ned: np.ndarray, sigma_ned: np.ndarray, sigma_v: float,
             quality: int = 1, moving: bool | None = None, applied_offset: float = 0.0,
             velocity: bool = True) -> None:
        """A GNSS fix (:meth:`OwnSensors.gnss`); ``moving`` (default: the fix's speed is over
        0.5 m/s) says whether the vehicle moves, for the multipath time constant and the
        non-holonomic rows; ``applied_offset`` is the time offset by which the fix was moved
        to filter time; without ``velocity`` the velocity is one derived from positions
        (:mod:`agent.position_course`), used for these decisions and the course, not as a
        measurement. While the heading is unknown, the fix may first have to wait for the course
        (:meth:`_await_heading`)."""
        if not self.heading_known and self._await_heading(v_ned, sigma_v):
            return
        if moving is None:
            moving = math.hypot(v_ned[0], v_ned[1]) >= 0.5
        self.own.gnss(llh, v_ned, sigma_ned, sigma_v, quality, moving, self.heading_known, applied_offset,
                      velocity)
        self._bound_time_offset()

    def _bound_time_offset(self) -> None:
        """Hold the time-offset estimate within ``time_offset_bound`` of the prior."""
        if self._dtau is None:
            return
        x, b = self.filter.extra, self.settings.time_offset_bound
        if abs(x[self._dtau]) > b:
            x[self._dtau] = math.copysign(b, x[self._dtau])
            self.counters["time_offset_bounded"] = self.counters.get("time_offset_bounded", 0) + 1

    def coast_gap(self, gap: float) -> None:
        """No IMU data for ``gap`` s: the state moves on and its covariance covers what the
        vehicle may have done (:meth:`InsFilter.coast`); a heading that uncertain is unknown
        again, until the GNSS course gives it."""
        s = self.settings
        self.filter.coast(gap, s.gap_accel_sigma, s.gap_rate_sigma)
        if self.heading_known and self.yaw_sigma > HEADING_LOST:
            self.heading_known = False
            self.filter.yaw_free = True
            self.counters["heading_lost"] = self.counters.get("heading_lost", 0) + 1

    def coast(self, moving: bool) -> None:
        """Between fixes (:meth:`OwnSensors.coast`)."""
        self.own.coast(moving, self.heading_known)

    def _await_heading(self, v_ned: np.ndarray, sigma_v: float) -> bool:
        """Heading unknown: take it (and the velocity) from the GNSS course as soon as the course
        is good to :data:`COURSE_SIGMA_MAX` (above 0.3 m/s for a σ of 0.05 m/s); until then the
        INS turns the first metres of travel the wrong way (its velocity variance grows by the
        specific force, :meth:`InsFilter.flush_covariance`). A vehicle that backs off is taken as
        driving ahead. Returns whether this fix must wait: moving, the course not yet good,
        the fixes' innovations would go to tilt and gyro biases (0.4 s of them put the gyro
        bias 7 σ off); they wait at most HEADING_WAIT s (a car creeping off for seconds drifted
        2.8 m without them)."""
        speed = math.hypot(v_ned[0], v_ned[1])
        sv = max(sigma_v, 0.05)  # a receiver's σ of millimetres per second is not its course's
        if speed > 0.0 and sv / speed < COURSE_SIGMA_MAX:
            course_sigma = math.atan2(sv, speed)
            self.filter.reset_yaw(math.atan2(v_ned[1], v_ned[0]), max(2.0 * course_sigma, math.radians(3.0)))
            self.filter.reset_velocity(v_ned, sigma_v)
            self.heading_known = True
            return False
        if speed <= 3.0 * sv:
            self._heading_wait_since = None
            return False
        if self._heading_wait_since is None:
            self._heading_wait_since = self.t
        if self.t - self._heading_wait_since < HEADING_WAIT:
            self.counters["gnss_heading_wait"] = self.counters.get("gnss_heading_wait", 0) + 1
            return True
        return False

    def zupt(self) -> UpdateResult | None:
        """Zero-velocity update (the caller decides that the vehicle is at rest)."""
        return self.own.zupt()

    @property
    def time_offset(self) -> float:
        """The estimated IMU-GNSS time offset [s]: filter time + offset = GNSS time (0 when not
        estimated), within ``time_offset_bound``."""
        if self._dtau is None:
            return 0.0
        b = self.settings.time_offset_bound
        return min(b, max(-b, float(self.filter.extra[self._dtau])))

    @property
    def position_cov(self) -> np.ndarray:
        """Position error covariance [m²] (3, 3)."""
        return self.filter.position_cov

    @property
    def yaw_sigma(self) -> float:
        """σ of the heading [rad]."""
        self.filter.flush_covariance()
        return math.sqrt(max(float(self.filter.P[2, 2]), 0.0))

    def beacon(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(llh, v_ned, cov_pos)`` to broadcast."""
        st = self.filter.state
        return st.llh.copy(), st.v.copy(), self.filter.position_cov

    def beacon_sources(self) -> tuple[tuple[tuple[str, ...], np.ndarray], ...]:
        """The broadcast position covariance by information source: ``(labels, (3, 3) [m²])``
        pairs, own first; with :meth:`beacon_constants`' outer products they sum to
        :meth:`beacon`'s; empty unless the rule is source CI."""
        f = self.filter
        if f.sources is None:
            return ()
        f.flush_covariance()
        return tuple(f.sources.blocks(f.P, POS))

    def beacon_constants(self) -> tuple[tuple[str, np.ndarray], ...]:
        """The position error's sensitivity to each exactly tracked constant: ``(name, (3,)
        [m per σ])`` pairs; empty unless the rule is source CI with ``exact_constants``."""
        f = self.filter
        if f.sources is None:
            return ()
        return tuple(f.sources.constant_rows(POS))
