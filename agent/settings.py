"""What a method fuses (:class:`MethodSpec`) and the tuning the methods share
(:class:`FilterSettings`, SI units): the one place a vehicle's filter configuration lands, from a
scenario, an agent file or a vehicle profile."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .nav.error_model import ImuNoise
from .range_gate import NlosModel

METHODS = ("SP", "SL-SP", "CP", "SL-CP")
#: how CP methods fuse a range with a neighbour's beacon (see :mod:`agent.nav.fusion`)
FUSION_RULES = ("paper", "source-ci", "split-ci", "ci")
#: the rule the CP methods use unless told otherwise
DEFAULT_FUSION = "source-ci"


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
    #: must outlast NLOS episodes, which last up to a minute and may follow each other:
    #: re-anchoring on one keeps its error to the end of the run
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
    #: overconfident approach it can let through
    consider_constants: bool = True
    #: source CI chooses its weights to minimise the horizontal position variance plus τ² times
    #: the horizontal velocity variance, τ this horizon [s]; 0 minimises the position alone,
    #: which lets a range that the position gains little from inflate the velocity it does not
    #: observe by 1/ω, range after range, until the velocity σ is metres per second and the
    #: position error follows
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
    #: yaw-rate term widens the lateral σ and pitch-rate term the vertical σ; with fixes it
    #: rides on their updates, without, it is applied on its own once no fix came for
    #: ``nhc_coast_after`` s
    nhc_sigma: float | None = None
    nhc_vertical_sigma: float = 0.1
    nhc_lever_uncertainty: float = 1.0
    nhc_coast_after: float = 1.0
    #: zero angular rate with every zero-velocity update: σ of the mean rate [rad/s] (None: off)
    zaru_sigma: float | None = None
    #: the covariance is propagated over this interval of IMU samples [s] (and before every
    #: update); a step of the GNSS fix period costs least and changes little
    cov_interval: float = 0.1
    #: what a road vehicle may do while its IMU data are missing (a frozen process, a sensor
    #: outage): σ of an unknown constant acceleration, horizontal and vertical [m/s²], and of
    #: its turn rate, roll/pitch and yaw [rad/s]
    gap_accel_sigma: tuple[float, float] = (3.0, 0.5)
    gap_rate_sigma: tuple[float, float] = (0.05, 0.3)
    #: the IMU-GNSS time offset as a state: its initial σ [s] and random walk [s/√s] (None: not
    #: estimated; the offset known is applied to the IMU time stamps by the sensor driver)
    time_offset: tuple[float, float] | None = None
    #: the estimated offset stays within this distance of the sensor driver's prior [s]: a
    #: wrong model (a mount, a lever arm) must not make it run away by seconds
    time_offset_bound: float = 1.0
