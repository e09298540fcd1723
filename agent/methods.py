"""The four estimation methods of the paper, as pure filters driven by sensor-time events.

============  =====================================================================
method        fuses
============  =====================================================================
``SP``        own IMU + GNSS (loosely coupled)
``SL-SP``     SP + the stop-line fix while this vehicle is the first stopped one
``CP``        SP + UWB ranges to neighbours, with their beacons' positions (eq. 26-28)
``SL-CP``     all of the above
============  =====================================================================

No I/O here: the agent runtime (asyncio shell) feeds measurements in sensor-time order.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import pymap3d

from geo import earth
from geo.lane_markings import UNSEEN, MarkingWindow

from .first_stopped import ApproachLane, Decision, StopTracker
from .lane_map import LaneMap
from .nav.error_model import ImuNoise
from .nav.ins_filter import InsFilter, level_from_accel
from .nav.kalman import Measurement, UpdateResult, chi2_gate
from .nav.measurements.lane_line import lane_line_measurement
from .nav.measurements.stop_line import Line2D, StopGapModel, StopLineApproach, stop_line_fix, stop_line_measurement
from .nav.measurements.v2v_range import quadratic_rows, range_measurement, relative_position
from .nav.rotation import euler_to_quat, quat_to_euler
from .nav.source_fusion import ANY, CONSTANT_MARK, SourcePart
from .nav.state import POS, VEL, NavState
from .neighbours import NeighbourState, NeighbourTable
from .own_sensors import OwnSensors
from .range_gate import NlosLinkTracker, NlosModel, RangeRateGate

METHODS = ("SP", "SL-SP", "CP", "SL-CP")
#: residual error of a stop-line fix beyond the stop gap's spread: map and model [m]
STOP_LINE_MAP_SIGMA = 0.03
#: classified camera reports a side needs before its class names a lane for the lane row (2 s
#: at 5 Hz): a lane row holds the vehicle in the lane it names, so a 1 s camera error at the
#: start, which settled five frames, put rush-hour E2 (seed 6) a lane off for the whole run
LANE_MARKING_FRAMES = 10
#: longest wait [s] of the GNSS updates of a vehicle that drives off with its heading unknown
HEADING_WAIT = 1.0
#: how CP methods fuse a range with a neighbour's beacon (see :mod:`agent.nav.fusion`)
FUSION_RULES = ("paper", "source-ci", "split-ci", "ci")
#: the rule the CP methods use unless told otherwise
DEFAULT_FUSION = "source-ci"
#: below this horizontal speed [m/s] (own estimate, the neighbour's beacon) a vehicle counts as
#: standing for the UWB link's range track
STANDING_SPEED = 0.3
#: σ [m/s] of a relative velocity from two inertial estimates along a known line of sight
RATE_VELOCITY_SIGMA = 0.3
#: the UWB antenna at the IMU (the agents' range model; read only)
_NO_LEVER_ARM = np.zeros(3)
_NO_LEVER_ARM.flags.writeable = False


def lane_row_markings(window: MarkingWindow, t: float) -> tuple[int, int]:
    """The camera's (left, right) classes at sensor time ``t`` [s] that may name a lane for the
    lane row: both sides settled over :data:`LANE_MARKING_FRAMES` reports, or nothing. One
    side is not enough: a side's error episode can outlast the window, and then the other
    side's gaps let the wrong side name the neighbouring lane alone (in the fleet, rush-hour
    E2, seed 6: the left side read divider for 2.6 s, the right side had too few reports to
    settle, and the lane row moved E2 3.6 m into the next lane for the whole run)."""
    marks = window.settled(t, LANE_MARKING_FRAMES)
    return (UNSEEN, UNSEEN) if UNSEEN in marks else marks


@dataclass(frozen=True)
class MethodSpec:
    """What a method fuses."""

    name: str
    stop_line: bool
    ranges: bool

    @classmethod
    def of(cls, name: str) -> MethodSpec:
        if name not in METHODS:
            raise ValueError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
        return cls(name, name.startswith("SL-"), name.endswith("CP"))


@dataclass(frozen=True)
class FilterSettings:
    """Tuning shared by the methods (SI units)."""

    noise: ImuNoise
    sigma_uwb: float = 0.1
    range_gate: float = 0.999  #: chi-square probability of the NIS gate for ranges
    second_order_ranges: bool = True
    #: σ [m] of the height difference of two vehicles' UWB antennas, taken as zero (same mounting
    #: height on a locally flat road); the range model then acts on the horizontal position only.
    #: None takes the difference of the two estimated heights (a 3-D range).
    range_height_sigma: float | None = 0.3
    #: χ² probability of the NIS gate on GNSS positions (NLOS jumps of metres to tens of metres,
    #: while the GNSS velocity keeps the INS honest); None accepts every fix
    gnss_gate: float | None = 0.999
    #: after this long [s] with every fix rejected, the position is re-anchored on the fix
    #: (its covariance widened by the innovation): a wrong solution is not kept for ever. It
    #: must outlast NLOS episodes (two may follow each other): re-anchoring after 20 s followed
    #: 5-60 s jumps and made rush-hour's SP worse than no gate (6.06 -> 7.49 m, seed 1); after
    #: 60 s it re-anchored on the last seconds of 4 long episodes in 8 fleet seeds (errors of
    #: 14-45 m to the end of the run)
    gnss_reset_after: float = 120.0
    init_att_sigma: tuple[float, float, float] = (math.radians(2.0), math.radians(2.0), math.radians(5.0))
    init_vel_sigma: float = 0.3
    #: initial bias uncertainty (the IMU's turn-on bias repeatability) [rad/s], [m/s²];
    #: None uses the in-run bias sigma of ``noise``
    init_gyro_bias_sigma: float | None = None
    init_accel_bias_sigma: float | None = None
    stop_line_interval: float = 1.0  #: apply the stop-line fix at most this often [s]
    #: SL methods also keep to their lane: the distance right of the lane's left lane line is
    #: d_l ~ N(m_yb, σ_yb²) (the stop-line fix's lateral part) wherever the lane is certain
    #: (:mod:`agent.lane_map`), applied at most every ``lane_interval`` s; the driver's offset
    #: is a state, constant while the vehicle stays in a lane and redrawn in the next one (or
    #: after ``lane_memory`` s without a lane)
    lane_constraint: bool = True
    lane_interval: float = 1.0
    lane_memory: float = 2.0
    #: ``paper``: R = σ² + uᵀP_j u, both estimates independent (the paper's eq. 26-28);
    #: ``source-ci``: covariance intersection by information source (each source's part of
    #: both estimates paired, different sources independent; :mod:`agent.nav.source_fusion`);
    #: ``split-ci``: split covariance intersection (what came from own sensors and the UWB
    #: noise independent; the neighbour's estimate and what came from it dependent);
    #: ``ci``: covariance intersection (both estimates wholly dependent, UWB noise independent)
    fusion: str = DEFAULT_FUSION
    #: zero-velocity updates while the IMU shows rest and GNSS is absent (all methods alike) [m/s];
    #: None switches them off
    zupt_sigma: float | None = 0.02
    #: source CI tracks the random constants of the SL methods (this stop's gap, this lane's
    #: offset) exactly: their sensitivities travel in the beacons and the parts of two
    #: vehicles' errors that come from one such constant are correlated as they are, not by CI
    #: (:mod:`agent.nav.source_fusion`); False leaves them in the own component
    exact_constants: bool = True
    #: with ``exact_constants``, the stop-gap and lane-offset states are *consider* states
    #: (Schmidt-Kalman): never estimated, their errors stay the constants themselves, wholly in
    #: the exact part, so that covariance intersection has nothing of theirs to inflate. On by
    #: default since the cooperative integrity test (``separation_false_alarm``) catches the
    #: overconfident approach it let through (paper-1 seed 2: V0 6.4 m off at σ 0.96 m)
    consider_constants: bool = True
    #: source CI chooses its weights to minimise the horizontal position variance plus τ² times
    #: the horizontal velocity variance, τ this horizon [s]; 0 minimises the position alone,
    #: which lets a range that the position gains little from inflate the velocity it does not
    #: observe by 1/ω, range after range (paper-1 seed 0 with ``consider_constants``: V0's
    #: velocity σ 0.12 -> 23 m/s in 3 s, its position error following)
    ci_velocity_horizon: float = 1.0
    #: node selection for the CI rules: fuse a range only if it is expected to reduce the
    #: horizontal position variance (source CI: the sum its weights minimise, with
    #: ``ci_velocity_horizon``) by at least this fraction
    min_gain: float = 1e-4
    #: a neighbour whose range node selection declined is not weighed again for this long [s],
    #: unless something the decision rests on moved: the own horizontal position variance grew,
    #: or the neighbour's shrank, by more than ``selection_hold_change`` (relative), or the line
    #: of sight turned by more than ``selection_hold_turn`` [rad]. Its ranges in between are
    #: declined (counted in ``ranges_skipped`` and ``ranges_skipped_held``) after the gates, which
    #: still see every range. Weighing a range costs a source-CI agent about 140 µs; in a busy
    #: queue nearly all of its 60 ranges a second are declined. 0 weighs every range.
    selection_hold: float = 0.5
    selection_hold_change: float = 0.05
    selection_hold_turn: float = math.radians(8.0)
    #: a range is fused only if the predicted horizontal distance is at least this many σ of
    #: the two positions' combined uncertainty across the line of sight: closer, the estimated
    #: direction is wrong by tens of degrees and the update pushes the wrong way (a vehicle
    #: crossing 3.5 m in front of another with σ 1 m pushed it 2.5 m off); 0 fuses all
    range_min_sigmas: float = 4.0
    max_range: float = 150.0  #: physical gate on UWB ranges [m]
    #: RMS of the UWB NLOS bias (persistent over an episode, so fused as dependent noise by the
    #: CI rules) [m]
    uwb_nlos_sigma: float = 0.0
    #: the UWB NLOS model: the CI rules then classify every range (:meth:`NlosModel.classify`)
    #: and reject those more probably NLOS than ``nlos_reject_probability``
    uwb_nlos: NlosModel | None = None
    nlos_reject_probability: float = 0.5
    #: the CI rules follow each link's NLOS episodes from its range series
    #: (:class:`~agent.range_gate.NlosLinkTracker`): the link's NLOS probability is the
    #: classifier's prior, and its bias variance replaces ``uwb_nlos_sigma``² as the range's
    #: dependent noise
    nlos_link_tracking: bool = True
    #: cooperative integrity (:mod:`agent.integrity`): CP and SL-CP are tested against their
    #: own-sensor twins (SP, SL-SP, when the agent runs them) at the decision rate; a horizontal
    #: separation beyond the χ² quantile of this false-alarm probability per test widens the
    #: cooperative position so that its own measurements pull it back. None: no test
    separation_false_alarm: float | None = 1e-4
    #: GNSS receiver characteristics: correlated (multipath) error carried as three
    #: Gauss-Markov states, so that correlated fixes are not averaged as if independent;
    #: None treats the reported sigma as white noise (the paper's filter)
    gnss_multipath_sigma: float | None = 3.0
    gnss_multipath_tau: float = 60.0  #: while moving [s]
    gnss_multipath_tau_static: float | None = None  #: while standing [s]; None: as moving
    gnss_white_sigma: float = 0.5
    #: a slower error shared by nearby receivers (atmosphere, orbits), as three more
    #: Gauss-Markov states; 0 leaves it out
    gnss_common_sigma: float = 0.0
    gnss_common_tau: float = 600.0
    #: the GNSS antenna's position in the body frame (forward, right, down) [m]
    gnss_lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: the receiver's reported σ is widened by these factors for a fixed RTK, a float RTK and
    #: any other solution: receivers report the σ of float and code solutions optimistically
    gnss_quality_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    #: floors of the reported GNSS σ (position [m], velocity [m/s]): a receiver's millimetres
    #: are not the error of the antenna's position on the vehicle
    gnss_min_sigma: float = 0.0
    gnss_min_sigma_v: float = 0.0
    #: non-holonomic constraint (no sideways or vertical velocity of the body): its lateral σ
    #: [m/s] (None: off), vertical σ, and the unknown IMU-to-rear-axle distance [m] whose
    #: yaw-rate term widens the lateral σ; with fixes it rides on their updates, without, it is
    #: applied on its own once no fix came for ``nhc_coast_after`` s
    nhc_sigma: float | None = None
    nhc_vertical_sigma: float = 0.1
    nhc_lever_uncertainty: float = 1.0
    nhc_coast_after: float = 1.0
    #: zero angular rate with every zero-velocity update: σ of the mean rate [rad/s] (None: off)
    zaru_sigma: float | None = None
    #: the covariance is propagated over this interval of IMU samples [s] (and before every
    #: update); a step of the GNSS fix period costs least and changes little
    cov_interval: float = 0.1
    #: the IMU-GNSS time offset as a state: its initial σ [s] and random walk [s/√s] (None: not
    #: estimated; the offset known is applied to the IMU time stamps by the sensor driver)
    time_offset: tuple[float, float] | None = None


def initial_state(llh: np.ndarray, v_ned: np.ndarray, f_b_mean: np.ndarray) -> NavState:
    """Initial nominal state from a GNSS fix and the mean specific force (level, heading from
    the GNSS course; a standing vehicle starts with heading 0 and a large yaw variance)."""
    roll, pitch = level_from_accel(f_b_mean)
    yaw = math.atan2(v_ned[1], v_ned[0]) if math.hypot(v_ned[0], v_ned[1]) > 1.0 else 0.0
    return NavState(float(llh[0]), float(llh[1]), float(llh[2]), np.asarray(v_ned, float).copy(),
                    euler_to_quat(roll, pitch, yaw))


class MethodFilter:
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
                    # through the ranges as news (paper-1 V1's σ went 1 % below the joint
                    # bound); they are reset when the vehicle drives off (:meth:`end_stop`),
                    # so nothing inflates them between stops
                    shared_h |= {off + k for k in range(self._sl.start, self._sl.stop)}
                if self._lane is not None:  # the same, for the lane offset (reset between lanes)
                    shared_h.add(off + self._lane.start)
                unshared = tuple(i for i in range(self.filter.n) if i not in shared_h)
            if s.fusion == "split-ci":
                self.filter.track_independent(self._common_mode_part(), shared=cm, unshared=unshared)
            else:
                self.filter.track_sources(vehicle, self._common_mode_part(), shared=cm, unshared=unshared)
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
        stands (paper-1 seed 2: σ 6.6 -> 1.4 m with the error still 6 m)."""
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
             quality: int = 1, moving: bool | None = None, applied_offset: float = 0.0) -> None:
        """A GNSS fix (:meth:`OwnSensors.gnss`); ``moving`` (default: the fix's speed is over
        0.5 m/s) says whether the vehicle moves, for the multipath time constant and the
        non-holonomic rows; ``applied_offset`` is the time offset by which the fix was moved
        to filter time. While the heading is unknown, the fix may first have to wait for the
        course (:meth:`_await_heading`)."""
        if not self.heading_known and self._await_heading(v_ned, sigma_v):
            return
        if moving is None:
            moving = math.hypot(v_ned[0], v_ned[1]) >= 0.5
        self.own.gnss(llh, v_ned, sigma_ned, sigma_v, quality, moving, self.heading_known, applied_offset)

    def coast(self, moving: bool) -> None:
        """Between fixes (:meth:`OwnSensors.coast`)."""
        self.own.coast(moving, self.heading_known)

    def _await_heading(self, v_ned: np.ndarray, sigma_v: float) -> bool:
        """Heading unknown: take it (and the velocity) from the GNSS course as soon as the course
        is good to 5° (0.6 m/s); until then the INS turns the first metres of travel the wrong
        way and the filter explains it with tilt and gyro biases (1500 °/h and 1.5° of pitch
        from a start at 1.5 m/s, rush-hour E4, seed 1). A vehicle that backs off is taken as
        driving ahead. Returns whether this fix must wait: moving, the course not yet good,
        the fixes' innovations would go to tilt and gyro biases (0.4 s of them put the gyro
        bias 7 σ off); they wait at most HEADING_WAIT s (a car creeping off for seconds drifted
        2.8 m without them)."""
        speed = math.hypot(v_ned[0], v_ned[1])
        sv = max(sigma_v, 0.05)  # a receiver's σ of millimetres per second is not its course's
        if speed > 0.0 and sv / speed < math.radians(5.0):
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

    def stop_line(self, approach: StopLineApproach, along_only: bool = False,
                  stop_id: float | None = None, lane: str | None = None) -> UpdateResult | None:
        """Apply the stop-line fix (only for SL methods, at most once per interval).

        ``stop_id`` identifies the physical stop (e.g. the time it began): a new one resets the
        stop-gap error states to their prior, since each stop draws its own d_s and d_l.
        ``lane`` names the approach lane: with the lane-keeping constraint on, a full fix's
        lateral row acts on that lane's offset state (the driver's d_l in it).
        """
        if not self.spec.stop_line or self.gap is None or self.origin is None or self._sl is None:
            return None
        f = self.filter
        if stop_id != self._stop_id:
            self._stop_id = stop_id
            self.last_stop_line = -math.inf
            self._reset_stop_gap()
        if self.t - self.last_stop_line < self.settings.stop_line_interval:
            return None
        self.last_stop_line = self.t
        m = stop_line_measurement(f.state, approach, self.gap, self.origin, along_only=along_only)
        # predicted fix = p - J ê, with J = ∂p/∂(d_e, d_l): the gap error is a state, not noise
        _, J = stop_line_fix(approach, self.gap.m_xb + self.gap.l0, self.gap.m_yb)
        hx = np.zeros((m.dim, len(f.extra)))
        if along_only:
            hx[:, self._sl] = -(approach.stop_line_normal() @ J)[None, :]
        elif self._lane is not None and lane is not None:
            self._enter_lane(lane)
            hx[:, self._sl.start] = -J[:, 0]
            hx[:, self._lane.start] = -J[:, 1]
        else:
            hx[:, self._sl] = -J
        self._sl_full = not along_only
        m = Measurement(m.z + hx @ f.extra, f.full_jacobian(m.H, hx), np.eye(m.dim) * STOP_LINE_MAP_SIGMA**2, m.name)
        res = f.update(m)
        self.counters["stop_line"] += int(res.accepted)
        return res

    def range(self, neighbour: NeighbourState, measured: float, t: float | None = None) -> str | None:
        """Fuse a UWB range [m] to a neighbour, measured at sensor time ``t`` [s] (default: now;
        earlier for a range deferred until the neighbour's beacon of that time arrived).

        Returns the outcome: ``"fused"``; ``"skipped"`` (node selection: too little expected
        gain); ``"skipped_near"`` (too near for the linearisation: ``range_min_sigmas``);
        ``"gate_physical"`` (outside (0, max_range)); ``"gate_rate"`` (a jump the
        vehicles' motion cannot explain); ``"gate_nlos"`` (more probably NLOS than not, CI
        rules with an NLOS model); ``"gate_nis"`` (χ² innovation gate); None for methods
        without ranges.
        """
        if not self.spec.ranges:
            return None
        s = self.settings
        t_meas = self.t if t is None else t
        if not 0.0 < measured < s.max_range:
            return self._count_range("gate_physical")
        nb_llh = neighbour.llh
        if t_meas < self.t:
            # a delayed range: move the neighbour by my displacement since t, which keeps the
            # relative geometry of time t while the Jacobian acts on my current error
            nb_llh = earth.offset_llh(nb_llh, self.displacement_since(t_meas))
        d = relative_position(self.filter.state, _NO_LEVER_ARM, nb_llh)
        # the line of sight as the range model takes it: horizontal unless the 3-D model is
        # chosen (Python floats: a dozen numpy calls on 3-vectors cost more than the arithmetic)
        d0, d1, d2 = d.tolist()
        l2 = 0.0 if s.range_height_sigma is not None else d2
        norm = max(math.sqrt(d0 * d0 + d1 * d1 + l2 * l2), 1e-3)
        u = (d0 / norm, d1 / norm, l2 / norm)
        vi, vj = self.filter.state.v.tolist(), neighbour.v_ned.tolist()
        v_rel = (vi[0] - vj[0], vi[1] - vj[1], vi[2] - vj[2])
        rate = u[0] * v_rel[0] + u[1] * v_rel[1] + u[2] * v_rel[2]
        if not self.rate_gate.check(neighbour.vehicle, t_meas, measured, rate):
            return self._count_range("gate_rate")
        own_cov = self.filter.position_cov
        own_rows, nb_rows = own_cov.tolist(), neighbour.cov_ned.tolist()
        link = None
        if self.nlos_tracker is not None:
            speed2 = v_rel[0] ** 2 + v_rel[1] ** 2
            link = self.nlos_tracker.belief(
                neighbour.vehicle, t_meas, measured, rate, speed2,
                standing=vi[0] ** 2 + vi[1] ** 2 < STANDING_SPEED**2 and vj[0] ** 2 + vj[1] ** 2 < STANDING_SPEED**2,
                rate_var=_rate_variance(u, (d0, d1, d2), own_rows, nb_rows, speed2))
            if link.outlier:
                return self._count_range("gate_rate")
        if s.range_min_sigmas > 0.0 and _too_near((d0, d1, d2), own_rows, nb_rows, s.range_min_sigmas):
            return self._count_range("skipped_near")
        m = range_measurement(self.filter.state, measured, s.sigma_uwb, nb_llh, neighbour.cov_ned,
                              own_cov_ned=own_cov, second_order=s.second_order_ranges,
                              relative=d, height_offset=None if s.range_height_sigma is None
                              else (0.0, s.range_height_sigma))
        if s.fusion == "paper":
            res = self.filter.update(m, s.range_gate)
        else:
            # innovation and its variance HPHᵀ + R: the model's row acts on the position only
            nu = -float(m.z[0])
            hp = m.H[0, POS].tolist()
            var = quadratic_rows(own_rows, hp) + float(m.R[0, 0])
            if s.uwb_nlos is not None and s.uwb_nlos.classify(nu, var, s.nlos_reject_probability,
                                                              None if link is None else link.p_nlos):
                return self._count_range("gate_nlos")
            r_bias = s.uwb_nlos_sigma**2 if link is None else link.bias_variance
            # the NIS gate on the whole spread, uninflated: the split-CI update gates on its
            # inflated covariances, P/ω and R_dep/(1-ω), and when most of P is shared with the
            # neighbours ω is small and a gross outlier passes (rush-hour seed 7 in the fleet:
            # after two rate-gate rejections W1 fused a range that moved it 23 m at an
            # along-track σ of 2.2 m, and W2 followed through W1's beacons)
            if self._range_gate_nis is not None and nu * nu / max(var + r_bias, 1e-12) > self._range_gate_nis:
                return self._count_range("gate_nis")
            own_var, nb_var = own_rows[0][0] + own_rows[1][1], nb_rows[0][0] + nb_rows[1][1]
            if self._decline_held(neighbour.vehicle, t_meas, own_var, nb_var, u):
                self.counters["ranges_skipped_held"] += 1
                return self._count_range("skipped")
            # the neighbour's estimate is wholly dependent: it may contain our information, and
            # its own-sensor errors (multipath) persist from one range to the next; so does an
            # NLOS bias. The UWB white noise (and the second-order term) is independent.
            h = m.H[0, POS]  # the line of sight as the model uses it (horizontal or 3-D)
            r_nb = max(quadratic_rows(nb_rows, hp), 0.0)
            m_ind = Measurement(m.z, m.H, m.R - r_nb, m.name)
            if s.fusion == "source-ci":
                res = self._range_source_ci(m_ind, h, neighbour, r_nb, r_bias)
            else:
                r_dep = np.array([[r_nb + r_bias]])
                res = self.filter.update_split_ci(m_ind, r_dep, own_independent=s.fusion == "split-ci",
                                                  gate_probability=s.range_gate, min_gain=s.min_gain)
            if res.skipped and s.selection_hold > 0.0:
                horiz = max(math.hypot(u[0], u[1]), 1e-9)
                self._declined[neighbour.vehicle] = (t_meas, own_var, nb_var, u[0] / horiz, u[1] / horiz)
            else:
                self._declined.pop(neighbour.vehicle, None)
        return self._count_range("skipped" if res.skipped else "fused" if res.accepted else "gate_nis")

    def _decline_held(self, vehicle: str, t: float, own_var: float, nb_var: float,
                      u: tuple[float, float, float]) -> bool:
        """Whether node selection's last decline of ``vehicle`` still holds for a range at sensor
        time ``t`` [s] (``selection_hold``): recent enough, and neither the own (``own_var``) nor
        the neighbour's (``nb_var``) horizontal position variance [m²] nor the line of sight
        ``u`` (unit, NED; its horizontal direction) moved by more than the settings allow."""
        last = self._declined.get(vehicle)
        if last is None:
            return False
        s = self.settings
        t0, own0, nb0, e0, n0 = last
        if not 0.0 <= t - t0 < s.selection_hold:
            return False
        if own_var > own0 * (1.0 + s.selection_hold_change) or nb_var < nb0 * (1.0 - s.selection_hold_change):
            return False
        # the turn of the horizontal line of sight: cos of the angle between the two directions
        horiz = math.hypot(u[0], u[1])
        return horiz > 0.0 and (u[0] * e0 + u[1] * n0) / horiz >= math.cos(s.selection_hold_turn)

    def _range_source_ci(self, m: Measurement, h: np.ndarray, neighbour: NeighbourState,
                         r_nb: float, r_bias: float) -> UpdateResult:
        """A range's source-CI update (:mod:`agent.nav.source_fusion`). ``m`` carries the range's
        white noise; the neighbour's estimate enters by source (its beacon's breakdown, projected
        on the line of sight ``h`` (3,); ``r_nb`` [m²] the whole of it projected, used when the
        beacon has no breakdown), and the link's NLOS bias ``r_bias`` [m²] under the
        link's name. Both ends of a link receive the same range, so its noise is a source of its
        own, named after the link (``"V0|V1"``) at both ends. A beacon no older than the range may
        already hold this very range: its white noise then counts with the link's source too."""
        link = frozenset({"|".join(sorted((self.vehicle, neighbour.vehicle)))})
        if neighbour.source_labels:
            var = np.maximum((neighbour.source_cov @ h) @ h, 0.0).tolist()
            parts = [SourcePart(lab, v) for lab, v in zip(neighbour.source_labels, var)]
        else:  # no breakdown: the neighbour's estimate may hold anything
            parts = [SourcePart(frozenset({ANY}), r_nb)]
        if r_bias > 0.0:
            parts.append(SourcePart(link, r_bias, correlated=True))
        if neighbour.age <= 0.0:
            white = float(m.R[0, 0])
            parts.append(SourcePart(link, white, correlated=True))
            m = Measurement(m.z, m.H, np.zeros((1, 1)), m.name)
        s = self.settings
        # the neighbour's position error enters the range opposite to mine: -h
        constants = [(lab, -float(g @ h)) for lab, g in neighbour.constants]
        return self.filter.update_source_ci(m, parts, link, s.range_gate, s.min_gain, constants,
                                            s.ci_velocity_horizon)

    def lane_due(self) -> bool:
        """Whether :meth:`lane_line` wants a lane now (``lane_interval`` after its last call)."""
        return (self._lane is not None and self.origin is not None
                and self.t - self._lane_checked >= self.settings.lane_interval)

    def lane_line(self, lane: str | None, left_line: Line2D | None = None) -> UpdateResult | None:
        """Keep to the lane: ``lane`` (and its ``left_line`` where the vehicle is, map frame) is
        the lane the vehicle drives in, None if no lane is certain now. Skipped while the stop
        line's full fix holds the lateral position (the same d_l). Only for SL methods with the
        lane-keeping constraint; the caller paces it (:meth:`lane_due`)."""
        if self._lane is None or self.origin is None:
            return None
        t = self.t
        self._lane_checked = t
        if lane is None:
            if t - self._lane_seen > self.settings.lane_memory:
                self._leave_lane()
            return None
        self._enter_lane(lane)
        if self._stop_id is not None and self._sl_full:
            return None
        f = self.filter
        m = lane_line_measurement(f.state, left_line, self.gap.m_yb, STOP_LINE_MAP_SIGMA, self.origin)
        hx = np.zeros((1, len(f.extra)))
        hx[0, self._lane.start] = -1.0  # predicted distance = d_l - (offset error)
        m = Measurement(m.z + hx @ f.extra, f.full_jacobian(m.H, hx), m.R, m.name)
        res = f.update(m, self.settings.range_gate)
        self.counters["lane_line" if res.accepted else "lane_line_rejected"] += 1
        if not res.accepted:  # the estimate and the lane disagree: the lane is not kept
            self._leave_lane()
        return res

    @property
    def lane(self) -> str | None:
        """The lane whose offset state the vehicle keeps now (lane keeping), or None."""
        return self._lane_id

    def _enter_lane(self, lane: str) -> None:
        if lane != self._lane_id or self.t - self._lane_seen > self.settings.lane_memory:
            self._leave_lane()
            self._lane_id = lane
        self._lane_seen = self.t

    def _leave_lane(self) -> None:
        """The lane is over: its offset state back to its prior (the next lane draws its own)."""
        if self._lane_id is not None:
            self._lane_id = None
            self._reset_extra(self._lane, np.array([self.gap.sigma_yb]))

    def end_stop(self) -> None:
        """The vehicle moves: a stop whose line it fixed on is over. Its stop-gap states go back
        to their prior, uncorrelated with the rest: nothing observes them until the next stop,
        which draws its own d_s and d_l, and left correlated, each split-CI range would inflate
        their dependent part by 1/ω with nothing to shrink it. No-op outside such a stop (a
        claim that ends while the vehicle stands keeps them: a new claim in the same stop
        shares their error)."""
        if self._sl is not None and self._stop_id is not None:
            self._stop_id = None
            self._reset_stop_gap()

    def _reset_stop_gap(self) -> None:
        self._sl_full = False
        self._reset_extra(self._sl, np.array([self.gap.sigma_xb, self.gap.sigma_yb]))

    def _reset_extra(self, states: slice, sigma: np.ndarray) -> None:
        """Extra ``states`` back to their prior σ ``sigma`` [(k,)], uncorrelated with the rest."""
        f = self.filter
        f.flush_covariance()
        k = np.arange(f.extra_offset + states.start, f.extra_offset + states.stop)
        for P in (f.P, f.P_ind):
            if P is not None:
                P[k, :] = 0.0
                P[:, k] = 0.0
                P[k, k] = sigma**2
        if f.sources is not None:
            f.sources.clear_states(k)
        f.extra[states] = 0.0
        self._track_constant(states, sigma)

    def _track_constant(self, states: slice, sigma: np.ndarray) -> None:
        """Extra ``states``, just at their prior σ ``sigma`` [(k,)], are new random constants:
        under source CI with ``exact_constants``, tracked exactly (one name per state, unique
        to this vehicle, also across restarts: the sensor time is in it)."""
        f = self.filter
        if f.sources is None or not self.settings.exact_constants:
            return
        k = np.arange(f.extra_offset + states.start, f.extra_offset + states.stop)
        names = []
        for _ in k:
            self._n_constants += 1
            names.append(f"{self.vehicle}{CONSTANT_MARK}{self._n_constants}.{self.t:.3f}")
        f.sources.new_constants(names, k, sigma)

    def _count_range(self, outcome: str) -> str:
        self.counters["ranges" if outcome == "fused" else f"ranges_{outcome}"] += 1
        if outcome.startswith("gate"):
            self.counters["ranges_rejected"] += 1
        return outcome

    @property
    def time_offset(self) -> float:
        """The estimated IMU-GNSS time offset [s]: filter time + offset = GNSS time (0 when not
        estimated)."""
        return float(self.filter.extra[self._dtau]) if self._dtau is not None else 0.0

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


def _rate_variance(u: tuple[float, ...], d: tuple[float, ...], own_cov: list, nb_cov: list, speed2: float) -> float:
    """Variance [m²/s²] of the range rate u·(v_i − v_j) from two estimates: the velocities'
    (``RATE_VELOCITY_SIGMA``) and the line of sight's, whose direction is off by the two
    positions' combined σ across it over the distance (``u`` horizontal unit (3,), ``d`` the
    relative position (3,) [m], ``own_cov``/``nb_cov`` (3, 3) [m²] as rows of floats,
    ``speed2`` the squared horizontal relative speed)."""
    r2 = max(d[0] ** 2 + d[1] ** 2, 1.0)
    return RATE_VELOCITY_SIGMA**2 + speed2 * min(_across(u[0], u[1], own_cov, nb_cov) / r2, 1.0)


def _across(u0: float, u1: float, own_cov: list, nb_cov: list) -> float:
    """The two horizontal covariances' sum (3x3 rows of floats [m²]) across the horizontal
    direction (u0, u1): a·(P_i + P_j)·a with a = (-u1, u0)."""
    c00 = own_cov[0][0] + nb_cov[0][0]
    c01 = own_cov[0][1] + nb_cov[0][1]
    c11 = own_cov[1][1] + nb_cov[1][1]
    return c00 * u1 * u1 - 2.0 * c01 * u0 * u1 + c11 * u0 * u0


def _too_near(d: tuple[float, ...], own_cov: list, nb_cov: list, k: float) -> bool:
    """Whether the horizontal distance ``d[:2]`` [m] is below ``k`` σ of the horizontal position
    uncertainty across the line of sight (own plus the neighbour's covariance, (3, 3) m² as rows
    of floats)."""
    rho = math.hypot(d[0], d[1])
    if rho <= 0.0:
        return True
    return rho * rho < k * k * _across(d[0] / rho, d[1] / rho, own_cov, nb_cov)


def first_stopped_step(tracker: StopTracker, f: MethodFilter, table: NeighbourTable,
                       lanes: dict[str, ApproachLane], origin_llh: tuple[float, float, float],
                       t: float, ghosts: dict | None = None,
                       lane_map: LaneMap | None = None) -> tuple[Decision, bool]:
    """One first-stopped decision for filter ``f`` at sensor time ``t`` [s] from its own estimate,
    the map (``lanes``, frame at ``origin_llh``) and the neighbours' beacons in ``table``; a claim
    applies the stop-line fix (a new claim at once). Returns the decision and whether it changed.
    With ``lane_map`` (every lane of the site), it also applies the lane-keeping row when due.

    ``ghosts`` maps neighbours lost recently (silent, or their process gone) to their last known
    (llh (3,), NED covariance (3, 3) [m²]): they count as standing there, so that a vehicle that
    cannot hear the queue ahead of it does not take the stop line."""
    st = f.filter.state
    known = {o: (table.entries[o].llh, table.entries[o].cov) for o in table.vehicles()}
    for o, (llh, cov) in (ghosts or {}).items():
        if o not in known:
            known[o] = (llh, cov)
            # standing there: since it was last seen coming to rest, since now if it was last
            # seen moving, or "forever" if it was never seen (observe_neighbour's rules)
            tracker.observe_neighbour(o, t, 0.0, False)
    speed = float(np.hypot(st.v[0], st.v[1]))
    # driving: "moving" needs no geometry (the same decision, for a fraction of the cost)
    quick = tracker.moving_decision(t, speed)
    if quick is not None:
        dec, changed = quick
    else:
        ne = np.array(pymap3d.geodetic2ned(st.lat, st.lon, st.h, *origin_llh, deg=False)[:2])
        nb_ne = {}
        if known:  # one vectorised conversion for all neighbours
            llh = np.array([v[0] for v in known.values()])
            n, e, _ = pymap3d.geodetic2ned(llh[:, 0], llh[:, 1], llh[:, 2], *origin_llh, deg=False)
            nb_ne = {o: np.array([n[i], e[i]]) for i, o in enumerate(known)}
        nb_cov = {o: cov[:2, :2] for o, (_, cov) in known.items()}
        dec, changed = tracker.decide(t, ne, f.position_cov[:2, :2], float(quat_to_euler(st.q)[2]),
                                      speed, nb_ne, nb_cov)
    if changed:
        f.last_stop_line = -math.inf
    if tracker.since is None:  # moving: the stop is over
        f.end_stop()
    if dec.first:
        f.stop_line(lanes[dec.lane].approach, along_only=dec.along_only, stop_id=tracker.since, lane=dec.lane)
    if lane_map is not None and f.lane_due():
        st = f.filter.state
        ne_now = np.array(pymap3d.geodetic2ned(st.lat, st.lon, st.h, *origin_llh, deg=False)[:2])
        hit = lane_map.locate(ne_now, f.position_cov[:2, :2], float(quat_to_euler(st.q)[2]),
                              lane_row_markings(tracker.markings, t), f.yaw_sigma, current=f.lane)
        f.lane_line(hit.lane if hit else None, hit.left_line if hit else None)
    return dec, changed
