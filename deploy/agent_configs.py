"""Agent configurations derived from a scenario (the map and each vehicle's sensor specs)."""

from __future__ import annotations

import dataclasses
import math

from slcp.agent.engine import AgentConfig
from slcp.agent.first_stopped import ApproachLane
from slcp.agent.lane_map import LaneMap
from slcp.agent.methods import DEFAULT_FUSION, METHODS, FilterSettings
from slcp.agent.nav.error_model import ImuNoise
from slcp.agent.nav.measurements.stop_line import Line2D, StopGapModel, StopLineApproach
from slcp.agent.own_sensors import IMU_MEMORY
from slcp.agent.range_gate import NlosModel
from slcp.geo.site import Site
from slcp.hw_emulation.scenario import Scenario
from slcp.hw_emulation.sensors import params
from slcp.hw_emulation.sensors.imu import ImuModel
from slcp.hw_emulation.sensors.uwb import UwbModel
from slcp.vehicles.profile import VehicleProfile


def _triple(obj, name: str, positive_entries: bool = False) -> None:
    v = getattr(obj, name)
    if (not isinstance(v, (list, tuple)) or len(v) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        raise ValueError(f"{type(obj).__name__}.{name} must be three finite numbers, got {v!r}")
    if positive_entries and not all(x > 0 for x in v):
        raise ValueError(f"{type(obj).__name__}.{name} must be three numbers > 0, got {v!r}")
    object.__setattr__(obj, name, tuple(float(x) for x in v))


@dataclasses.dataclass(frozen=True)
class FilterOptions:
    """The ``[filter]`` section of an agent configuration: the vehicle's installation and the
    own-sensor options of its filters (the units are in the names). The defaults are the
    emulated vehicles'."""

    #: the GNSS antenna's position in the body frame: forward, right, down [m]
    gnss_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: factors on the receiver's reported σ for a fixed RTK, a float RTK and any other solution
    gnss_quality_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    #: floor of the reported position σ [m]
    gnss_min_sigma_m: float = 0.0
    #: floor of the reported velocity σ [m/s]
    gnss_min_sigma_mps: float = 0.0
    #: non-holonomic constraint: lateral σ [m/s] (0: off)
    nhc_sigma_mps: float = 0.0
    #: non-holonomic constraint: vertical σ [m/s]
    nhc_vertical_sigma_mps: float = 0.1
    #: the unknown distance from the IMU to the rear axle, which widens the lateral σ by the yaw rate
    #: and the vertical σ by the pitch rate [m]
    nhc_lever_uncertainty_m: float = 1.0
    #: without a fix for this long, the non-holonomic constraint is applied on its own [s]
    nhc_coast_after_s: float = 1.0
    #: zero-velocity update σ [m/s] (0: off)
    zupt_sigma_mps: float = 0.02
    #: zero angular rate at rest: σ of the mean rate of the last 10 IMU samples [deg/s] (0: off)
    zaru_sigma_dps: float = 0.0
    #: the IMU-GNSS time offset as a filter state: its initial σ [s] (0: not estimated)
    time_offset_sigma_s: float = 0.0
    #: the time offset's random walk [s/√s]
    time_offset_rw: float = 1e-3
    #: covariance propagation interval [s]
    cov_interval_s: float = 0.1
    #: initial attitude σ: roll, pitch, yaw [deg] (the yaw's is 60° when the vehicle starts standing)
    init_att_sigma_deg: tuple[float, float, float] = (2.0, 2.0, 5.0)
    #: initial velocity σ [m/s]
    init_vel_sigma_mps: float = 0.3

    def __post_init__(self) -> None:
        _triple(self, "gnss_lever_arm_m")
        _triple(self, "gnss_quality_scale", positive_entries=True)
        _triple(self, "init_att_sigma_deg", positive_entries=True)
        params.non_negative(self, "gnss_min_sigma_m", "gnss_min_sigma_mps", "nhc_sigma_mps", "zupt_sigma_mps",
                            "zaru_sigma_dps", "time_offset_sigma_s", "time_offset_rw")
        params.positive(self, "nhc_vertical_sigma_mps", "nhc_lever_uncertainty_m", "nhc_coast_after_s",
                        "cov_interval_s", "init_vel_sigma_mps")

    def settings(self) -> dict:
        """The :class:`FilterSettings` fields these set (SI units, radians)."""
        return {
            "gnss_lever_arm": self.gnss_lever_arm_m, "gnss_quality_scale": self.gnss_quality_scale,
            "gnss_min_sigma": self.gnss_min_sigma_m, "gnss_min_sigma_v": self.gnss_min_sigma_mps,
            "nhc_sigma": self.nhc_sigma_mps or None, "nhc_vertical_sigma": self.nhc_vertical_sigma_mps,
            "nhc_lever_uncertainty": self.nhc_lever_uncertainty_m, "nhc_coast_after": self.nhc_coast_after_s,
            "zupt_sigma": self.zupt_sigma_mps or None,
            "zaru_sigma": math.radians(self.zaru_sigma_dps) or None,
            "time_offset": (self.time_offset_sigma_s, self.time_offset_rw) if self.time_offset_sigma_s else None,
            "cov_interval": self.cov_interval_s,
            "init_att_sigma": tuple(math.radians(x) for x in self.init_att_sigma_deg),
            "init_vel_sigma": self.init_vel_sigma_mps,
        }


def with_filter(cfg: AgentConfig, options: FilterOptions) -> AgentConfig:
    """``cfg`` with the ``[filter]`` section's options."""
    return dataclasses.replace(cfg, settings=dataclasses.replace(cfg.settings, **options.settings()))


def with_profile(cfg: AgentConfig, profile: VehicleProfile) -> AgentConfig:
    """``cfg`` with a vehicle profile's IMU model, installation and own-sensor options (what
    the sensor driver does with the profile, the mount and the time-offset prior, is not the
    engine's)."""
    imu, g, c, t, i = profile.imu, profile.gnss, profile.constraints, profile.time, profile.initial
    noise = ImuNoise(arw=imu.arw, vrw=imu.vrw, gyro_bias_sigma=imu.gyro_bias, gyro_bias_tau=imu.bias_correlation_s,
                     accel_bias_sigma=imu.accel_bias, accel_bias_tau=imu.bias_correlation_s)
    # ZARU weighs the mean rate of the engine's last IMU_MEMORY samples: white rate noise
    # averages to ARW/√T, doubled for the vibration of a vehicle at rest with its engine on
    zaru_dps = c.zaru_sigma_dps or math.degrees(2.0 * noise.arw / math.sqrt(IMU_MEMORY / imu.rate_hz))
    options = FilterOptions(  # the agent file's [filter] section, as the profile sets it (0: off)
        gnss_lever_arm_m=g.lever_arm_m, gnss_quality_scale=g.quality_scale, gnss_min_sigma_m=g.min_sigma_m,
        gnss_min_sigma_mps=g.min_sigma_mps, nhc_sigma_mps=c.nhc_sigma_mps if c.nhc else 0.0,
        nhc_vertical_sigma_mps=c.nhc_vertical_sigma_mps, nhc_lever_uncertainty_m=c.nhc_lever_uncertainty_m,
        nhc_coast_after_s=c.nhc_coast_after_s, zupt_sigma_mps=c.zupt_sigma_mps if c.zupt else 0.0,
        zaru_sigma_dps=zaru_dps if c.zupt and c.zaru else 0.0,
        time_offset_sigma_s=t.sigma_s if t.estimate else 0.0, time_offset_rw=t.random_walk,
        # one covariance step per fix period costs least and changes little
        cov_interval_s=1.0 / g.rate_hz, init_att_sigma_deg=i.att_sigma_deg, init_vel_sigma_mps=i.vel_sigma_mps)
    s = dataclasses.replace(cfg.settings, noise=noise, init_gyro_bias_sigma=imu.gyro_turn_on,
                            init_accel_bias_sigma=imu.accel_turn_on, time_offset_bound=t.bound_s)
    return with_filter(dataclasses.replace(cfg, settings=s), options)


def imu_noise_of(model: ImuModel) -> ImuNoise:
    """Filter IMU model matching an emulated IMU (in-run biases as Gauss-Markov)."""
    return ImuNoise(arw=model.arw, vrw=model.vrw, gyro_bias_sigma=model.gyro_in_run, gyro_bias_tau=model.bias_tau,
                    accel_bias_sigma=model.accel_in_run, accel_bias_tau=model.bias_tau)


def approach_lanes(site: Site | Scenario) -> dict[str, ApproachLane]:
    """Stop line (at the centre-line end, at right angles to the lane or along its slant) and left
    lane line of every approach."""
    out = {}
    for lane in site.lanes.values():
        if not lane.stop_line:
            continue
        left, d = lane.end_left_line()
        across = lane.stop_slant if lane.stop_slant is not None else (-d[1], d[0])
        approach = StopLineApproach(Line2D(tuple(lane.centerline[-1]), tuple(across)), Line2D(tuple(left), tuple(d)))
        out[lane.id] = ApproachLane(lane.id, approach, lane.width)
    return out


def lane_map(site: Site | Scenario) -> LaneMap:
    """Every lane of the site (centre lines and widths) for the lane-keeping row."""
    return LaneMap({lane.id: (lane.centerline, lane.width) for lane in site.lanes.values()})


def with_site(cfg: AgentConfig, site: Site) -> AgentConfig:
    """``cfg`` at ``site`` (e.g. a Lanelet2 map's, :mod:`geo.lanelet2_site`): its stop lines, its
    lanes for the lane constraint, and its origin."""
    return dataclasses.replace(cfg, lanes=approach_lanes(site), origin_llh=site.origin_llh,
                               lane_map=lane_map(site))


def agent_config(scn: Scenario, vehicle: str, methods: tuple[str, ...] = METHODS,
                 fusion: str = DEFAULT_FUSION, lane_constraint: bool = True) -> AgentConfig:
    """The configuration a vehicle computer would carry for this scenario's site and sensors
    (``lane_constraint``: the SL methods also keep to the map's lanes)."""
    specs = {v.id: v for v in scn.vehicles}
    if vehicle not in specs:
        raise ValueError(f"vehicle {vehicle!r} not in scenario {scn.name!r}")
    sp = specs[vehicle]
    gm = sp.gnss
    settings = FilterSettings(imu_noise_of(sp.imu), init_gyro_bias_sigma=sp.imu.gyro_turn_on,
                              init_accel_bias_sigma=sp.imu.accel_turn_on,
                              gnss_multipath_sigma=gm.multipath_h, gnss_multipath_tau=gm.multipath_tau_moving,
                              gnss_multipath_tau_static=gm.multipath_tau_static,
                              gnss_common_sigma=scn.common_mode_sigma, gnss_common_tau=scn.common_mode_tau,
                              gnss_white_sigma=max(gm.white_h, 0.1),
                              fusion=fusion, lane_constraint=lane_constraint)
    gap = StopGapModel(sp.stop_gap[0], sp.stop_gap[1], sp.lateral[0], sp.lateral[1], sp.l0)
    return with_uwb(AgentConfig(vehicle, tuple(methods), settings, gap, approach_lanes(scn), scn.origin_llh,
                                lane_map=lane_map(scn)), scn.uwb)


def with_uwb(cfg: AgentConfig, u: UwbModel) -> AgentConfig:
    """``cfg`` with the range model of UWB radios that behave as ``u`` (the emulator's model):
    the line-of-sight σ (at least 5 cm), the NLOS bias as an extra σ and as the range gate's
    two-state model, and the largest range."""
    nlos = (NlosModel(u.nlos_enter, u.nlos_exit, u.nlos_bias_min, u.nlos_bias_max,
                      u.outlier_prob, u.outlier_min, u.outlier_max)
            if u.nlos_enter > 0 and u.nlos_exit > 0 and u.nlos_bias_max > u.nlos_bias_min else None)
    p_nlos = u.nlos_enter / (u.nlos_enter + u.nlos_exit) if u.nlos_enter > 0 else 0.0
    nlos_ms = (u.nlos_bias_min**2 + u.nlos_bias_min * u.nlos_bias_max + u.nlos_bias_max**2) / 3.0
    settings = dataclasses.replace(cfg.settings, sigma_uwb=max(u.sigma_los, 0.05),
                                   uwb_nlos_sigma=math.sqrt(p_nlos * nlos_ms), uwb_nlos=nlos, max_range=u.max_range)
    return dataclasses.replace(cfg, settings=settings, nlos_bias_max=u.nlos_bias_max)


#: ``[gnss]`` fields of an agent configuration -> :class:`FilterSettings` fields
GNSS_FIELDS = {"multipath_sigma": "gnss_multipath_sigma", "multipath_tau": "gnss_multipath_tau",
               "multipath_tau_static": "gnss_multipath_tau_static", "white_sigma": "gnss_white_sigma",
               "common_sigma": "gnss_common_sigma", "common_tau": "gnss_common_tau",
               "gate": "gnss_gate", "reset_after": "gnss_reset_after"}


def siteless_agent_config(vehicle: str, methods: tuple[str, ...] = METHODS, fusion: str = DEFAULT_FUSION,
                          imu: ImuModel | None = None) -> AgentConfig:
    """A vehicle without a site map: no stop lines (SL-SP and SL-CP then equal SP and CP).

    The IMU model (default :class:`ImuModel`) sets the filter's noise and initial biases; GNSS
    is taken at its reported σ as white noise (a real receiver's σ; no multipath states) and
    without the χ² gate: with an RTK receiver's centimetre σ the gate rejected the first fixes
    after each 15 s outage of the real drive (the INS σ is optimistic there) and the error with
    GNSS on rose from under 0.5 m to 0.66 m.
    """
    imu = imu or ImuModel()
    settings = FilterSettings(imu_noise_of(imu), init_gyro_bias_sigma=imu.gyro_turn_on,
                              init_accel_bias_sigma=imu.accel_turn_on, gnss_multipath_sigma=None,
                              gnss_gate=None, fusion=fusion)
    return AgentConfig(vehicle, tuple(methods), settings, StopGapModel(1.5, 0.3, 1.75, 0.3, 2.5), {},
                       (0.0, 0.0, 0.0))


def with_imu(cfg: AgentConfig, imu: ImuModel) -> AgentConfig:
    """``cfg`` with the filter's IMU noise and initial bias σ of ``imu``."""
    s = dataclasses.replace(cfg.settings, noise=imu_noise_of(imu), init_gyro_bias_sigma=imu.gyro_turn_on,
                            init_accel_bias_sigma=imu.accel_turn_on)
    return dataclasses.replace(cfg, settings=s)


def with_gnss(cfg: AgentConfig, fields: dict[str, float | None]) -> AgentConfig:
    """``cfg`` with GNSS filter settings given by their ``[gnss]`` names (:data:`GNSS_FIELDS`);
    a ``multipath_sigma`` of 0 means none (the reported σ is used as white noise), a ``gate`` of
    0 no χ² gate (every fix accepted)."""
    kw = {GNSS_FIELDS[k]: v for k, v in fields.items()}
    for k in ("gnss_multipath_sigma", "gnss_gate"):
        if kw.get(k) == 0:
            kw[k] = None
    return dataclasses.replace(cfg, settings=dataclasses.replace(cfg.settings, **kw))
