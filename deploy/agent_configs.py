"""Agent configurations derived from a scenario (the map and each vehicle's sensor specs)."""

from __future__ import annotations

import dataclasses
import math

from agent.first_stopped import ApproachLane
from agent.lane_map import LaneMap
from agent.methods import DEFAULT_FUSION, METHODS, FilterSettings
from agent.nav.error_model import ImuNoise
from agent.nav.measurements.stop_line import Line2D, StopGapModel, StopLineApproach
from agent.range_gate import NlosModel
from agent.runtime import AgentConfig
from hw_emulation.scenario import Scenario
from hw_emulation.sensors.imu import ImuModel


def imu_noise_of(model: ImuModel) -> ImuNoise:
    """Filter IMU model matching an emulated IMU (in-run biases as Gauss-Markov)."""
    return ImuNoise(arw=model.arw, vrw=model.vrw, gyro_bias_sigma=model.gyro_in_run, gyro_bias_tau=model.bias_tau,
                    accel_bias_sigma=model.accel_in_run, accel_bias_tau=model.bias_tau)


def approach_lanes(scn: Scenario) -> dict[str, ApproachLane]:
    """Stop line (perpendicular, at the centre-line end) and left lane line of every approach."""
    out = {}
    for lane in scn.lanes.values():
        if not lane.stop_line:
            continue
        left, d = lane.end_left_line()
        approach = StopLineApproach(Line2D(tuple(lane.centerline[-1]), (-d[1], d[0])), Line2D(tuple(left), tuple(d)))
        out[lane.id] = ApproachLane(lane.id, approach, lane.width)
    return out


def lane_map(scn: Scenario) -> LaneMap:
    """Every lane of the site (centre lines and widths) for the lane-keeping row."""
    return LaneMap({lane.id: (lane.centerline, lane.width) for lane in scn.lanes.values()})


def agent_config(scn: Scenario, vehicle: str, methods: tuple[str, ...] = METHODS,
                 fusion: str = DEFAULT_FUSION, lane_constraint: bool = True) -> AgentConfig:
    """The configuration a vehicle computer would carry for this scenario's site and sensors
    (``lane_constraint``: the SL methods also keep to the map's lanes)."""
    specs = {v.id: v for v in scn.vehicles}
    if vehicle not in specs:
        raise ValueError(f"vehicle {vehicle!r} not in scenario {scn.name!r}")
    sp = specs[vehicle]
    gm = sp.gnss
    settings = FilterSettings(imu_noise_of(sp.imu), sigma_uwb=max(scn.uwb.sigma_los, 0.05),
                              init_gyro_bias_sigma=sp.imu.gyro_turn_on, init_accel_bias_sigma=sp.imu.accel_turn_on,
                              gnss_multipath_sigma=gm.multipath_h, gnss_multipath_tau=gm.multipath_tau_moving,
                              gnss_multipath_tau_static=gm.multipath_tau_static,
                              gnss_common_sigma=scn.common_mode_sigma, gnss_common_tau=scn.common_mode_tau,
                              gnss_white_sigma=max(gm.white_h, 0.1),
                              fusion=fusion, lane_constraint=lane_constraint)
    u = scn.uwb
    nlos = (NlosModel(u.nlos_enter, u.nlos_exit, u.nlos_bias_min, u.nlos_bias_max,
                      u.outlier_prob, u.outlier_min, u.outlier_max)
            if u.nlos_enter > 0 and u.nlos_exit > 0 and u.nlos_bias_max > u.nlos_bias_min else None)
    p_nlos = u.nlos_enter / (u.nlos_enter + u.nlos_exit) if u.nlos_enter > 0 else 0.0
    nlos_ms = (u.nlos_bias_min**2 + u.nlos_bias_min * u.nlos_bias_max + u.nlos_bias_max**2) / 3.0
    settings = dataclasses.replace(settings, uwb_nlos_sigma=math.sqrt(p_nlos * nlos_ms), uwb_nlos=nlos,
                                   max_range=u.max_range)
    gap = StopGapModel(sp.stop_gap[0], sp.stop_gap[1], sp.lateral[0], sp.lateral[1], sp.l0)
    return AgentConfig(vehicle, tuple(methods), settings, gap, approach_lanes(scn), scn.origin_llh,
                       nlos_bias_max=u.nlos_bias_max, lane_map=lane_map(scn))


#: ``[gnss]`` fields of an agent configuration -> :class:`FilterSettings` fields
GNSS_FIELDS = {"multipath_sigma": "gnss_multipath_sigma", "multipath_tau": "gnss_multipath_tau",
               "multipath_tau_static": "gnss_multipath_tau_static", "white_sigma": "gnss_white_sigma",
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
