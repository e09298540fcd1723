"""Replay a recorded drive through the vehicle engine (SP) with simulated GNSS outages.

The drive becomes the messages a vehicle's sensor drivers would publish
(:func:`deploy.replay_publish.plan_drive`: IMU batches with the mounting rotation and time
offset applied, GNSS fixes with ellipsoidal heights, the fixes inside the outages withheld),
and the engine a vehicle runs (:class:`agent.engine.VehicleEngine`) takes them; its estimates
are scored against the file's fixes at their epochs. ``slcp replay --publish`` plays the same
messages to a live agent and scores the same way.

The outage protocol is the one the rtklibexplorer data's authors use: with ``t0`` the first GNSS
epoch and ``tN`` the last, outage ``k`` withholds the fixes in ``[S_k, S_k + length)`` with
``S_k = t0 + first + period * k`` for every ``k`` with ``S_k < tN - end_margin``. The engine is
causal: nothing is smoothed backwards.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from slcp.agent.engine import AgentConfig, VehicleEngine
from slcp.agent.nav.error_model import ImuNoise
from slcp.agent.own_sensors import IMU_MEMORY
from slcp.transport.messages import Estimate

from .datasets.rtklib import RtklibDrive
from .drive_scoring import score_estimates

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OutageProtocol:
    """Simulated GNSS outages [s]; ``length = 0`` disables them."""

    first: float = 40.0
    period: float = 45.0
    length: float = 15.0
    end_margin: float = 30.0

    def windows(self, t0: float, t_end: float) -> list[tuple[float, float]]:
        """Outage windows ``[start, end)`` in absolute time."""
        if self.length <= 0:
            return []
        if self.period <= 0:
            raise ValueError("outage period must be positive")
        out = []
        k = 0
        while (s := t0 + self.first + self.period * k) < t_end - self.end_margin:
            out.append((s, s + self.length))
            k += 1
        return out


@dataclass(frozen=True)
class ReplayConfig:
    """The drive's installation and the engine's options for a replay (SI units, radians).

    Defaults describe the rtklibexplorer drive: a TDK ICM-45686 class IMU (gyro noise
    0.0038 °/s/√Hz, accelerometer 70 µg/√Hz; both inflated ×2 for vibration and unmodelled
    scale-factor errors), the sensor-to-body rotation and antenna lever arm of its DATASET.md,
    a −0.125 s IMU logging delay and the site's geoid undulation.
    """

    noise: ImuNoise = ImuNoise(
        arw=2 * math.radians(0.0038), vrw=2 * 70e-6 * 9.80665,
        gyro_bias_sigma=math.radians(0.05), gyro_bias_tau=600.0,
        accel_bias_sigma=0.05, accel_bias_tau=600.0,
    )
    #: sensor-to-body rotation as roll, pitch, yaw [rad] (Groves' Euler_to_CTM convention)
    mount_rpy: tuple[float, float, float] = tuple(
        np.radians(np.array([180.0, 0.0, 180.0]) + np.array([0.0, -6.79, 5.35])).tolist())
    lever_arm_gnss: tuple[float, float, float] = (0.0, -0.05, 0.0)
    #: applied to the IMU time stamps (the sensor driver's offset) [s]
    imu_time_offset: float = -0.125
    #: estimate the remaining IMU-GNSS time offset online (an engine state)
    estimate_time_offset: bool = True
    time_offset_sigma: float = 0.05
    time_offset_rw: float = 1e-3
    #: geoid undulation added to the file's MSL heights [m] (EGM96 near 40.10 N 105.15 W)
    geoid_undulation: float = -16.8
    outage: OutageProtocol = OutageProtocol()
    zupt: bool = True
    nhc: bool = True
    #: with fixes, the NHC rows ride on their updates; without a fix for ``coast_after`` s
    #: they are applied on their own
    coast_after: float = 1.0
    nhc_sigma: float = 0.1
    #: NHC vertical-velocity sigma [m/s]; a mount-pitch error biases this row, so it is looser
    nhc_vertical_sigma: float = 0.1
    nhc_lever_uncertainty: float = 1.0
    zupt_sigma: float = 0.02
    #: the receiver's σ is widened ×``float_gain`` for float RTK and ×``single_gain`` for
    #: anything but fixed RTK
    float_gain: float = 2.0
    single_gain: float = 5.0
    init_att_sigma: tuple[float, float, float] = tuple(np.radians([2.0, 2.0, 60.0]).tolist())
    init_vel_sigma: float = 0.1
    init_gyro_bias_sigma: float = math.radians(0.1)
    init_accel_bias_sigma: float = 0.1
    #: the IMU's sample interval [s] (for the σ of the mean rate in ZARU)
    imu_interval: float = 0.01
    #: covariance propagation interval [s]: the fix period of this drive (4 Hz), so P is
    #: propagated once per epoch (plus at constraint updates)
    cov_interval: float = 0.25


@dataclass
class ReplayResult:
    """Per-epoch evaluation and the engine's trajectory; ``t0`` is the first GNSS epoch [s]."""

    t: np.ndarray
    h_err: np.ndarray
    withheld: np.ndarray
    outages: list[tuple[float, float]]
    trajectory: np.ndarray
    t0: float = 0.0
    metrics: dict = field(default_factory=dict)


TRAJECTORY_COLUMNS = (
    "time_gpst_s", "lat_deg", "lon_deg", "h_m", "vn_mps", "ve_mps", "vd_mps",
    "roll_deg", "pitch_deg", "yaw_deg", "sigma_n_m", "sigma_e_m", "sigma_d_m",
)


def run_replay(drive: RtklibDrive, cfg: ReplayConfig = ReplayConfig(), vehicle: str = "V0") -> ReplayResult:
    """The drive's messages through the vehicle engine (SP), scored at the GNSS epochs."""
    from .replay_publish import plan_drive

    wall0 = time.perf_counter()
    plan = plan_drive(drive, vehicle, cfg)
    engine = VehicleEngine(engine_config(cfg, vehicle))
    est: list[Estimate] = []
    for _, _, msg in plan.messages:
        engine.handle(msg)
        est += [o for o in engine.take_outbox() if isinstance(o, Estimate)]
    engine.finish()
    est += [o for o in engine.take_outbox() if isinstance(o, Estimate)]
    if not est:
        raise ValueError("the engine never started: no GNSS fix within a second of the IMU data")
    wall = time.perf_counter() - wall0
    figures, inside, err = score_estimates(plan.fix_t, plan.fix_llh, plan.withheld, est, cfg.lever_arm_gnss)
    t0 = float(drive.gnss.t[0])
    outages = cfg.outage.windows(t0, float(drive.gnss.t[-1]))
    res = ReplayResult(plan.fix_t[inside], err, plan.withheld[inside], outages, _trajectory(est), t0)
    imu_span = float(drive.imu.t[-1] - drive.imu.t[0])
    res.metrics = {**{k: (float("nan") if v is None else v) for k, v in figures.items()},
                   "imu_span_s": imu_span, "wall_s": wall,
                   "realtime_factor": imu_span / wall if wall > 0 else float("inf")}
    f = engine.filters["SP"]
    res.metrics["imu_time_offset_s"] = cfg.imu_time_offset + f.time_offset
    st = f.filter.stats
    res.metrics["filter_stats"] = {"imu_samples": st.imu_samples, "cov_steps": st.cov_steps,
                                   "updates": st.updates, "rejected": st.rejected}
    return res


def _trajectory(est: list[Estimate]) -> np.ndarray:
    """The estimates as rows of :data:`TRAJECTORY_COLUMNS`."""
    rows = []
    for e in est:
        rpy = np.degrees(e.rpy)
        sig = np.sqrt(np.maximum(np.diag(e.cov_pos), 0.0))
        rows.append([e.t, math.degrees(e.llh[0]), math.degrees(e.llh[1]), e.llh[2], *e.v_ned, *rpy, *sig])
    return np.array(rows).reshape(-1, len(TRAJECTORY_COLUMNS))


def phase_protocols(protocol: OutageProtocol, n: int) -> list[OutageProtocol]:
    """The outage protocol at ``n`` phases evenly spread over its period: the first outage
    starts at ``first + k · period / n`` for k = 0 … n − 1 (k = 0 is ``protocol`` itself), so
    the outages of all phases together cover the drive evenly."""
    if n < 1:
        raise ValueError("the number of phases must be at least 1")
    return [dataclasses.replace(protocol, first=protocol.first + k * protocol.period / n) for k in range(n)]


def pooled_metrics(results: list[ReplayResult]) -> dict:
    """Outage metrics over several replays of one drive (e.g. at the :func:`phase_protocols`):
    the RMS over every withheld fix of every run, the end-of-outage mean and max over every
    outage, the largest error; and each run's own figures under ``phases`` (``first_outage_s``
    after t0, [s]). Errors in metres."""
    withheld = np.concatenate([r.h_err[r.withheld] for r in results])
    ends = [e for r in results for e in r.metrics["outage_end_errors_m"]]
    phases = [{"first_outage_s": (r.outages[0][0] - r.t0) if r.outages else None,
               **{k: r.metrics[k] for k in ("n_outages", "n_withheld_fixes", "outage_h_rms_m",
                                            "outage_h_end_mean_m", "outage_h_end_max_m", "outage_h_max_m")}}
              for r in results]
    return {
        "n_phases": len(results),
        "n_outages": len(ends),
        "n_withheld_fixes": int(withheld.size),
        "outage_h_rms_m": float(np.sqrt(np.mean(np.square(withheld)))) if withheld.size else float("nan"),
        "outage_h_end_mean_m": float(np.mean(ends)) if ends else float("nan"),
        "outage_h_end_max_m": float(np.max(ends)) if ends else float("nan"),
        "outage_h_max_m": float(np.max(withheld)) if withheld.size else float("nan"),
        "phases": phases,
    }


def engine_config(cfg: ReplayConfig, vehicle: str = "V0") -> AgentConfig:
    """The vehicle engine's configuration for a drive replayed with ``cfg``: a vehicle without a
    site map running SP, with the drive's IMU noise and installation."""
    from .agent_configs import siteless_agent_config

    base = siteless_agent_config(vehicle, ("SP",))
    # ZARU weighs the mean rate of the engine's last IMU_MEMORY samples: white rate noise
    # averages to ARW/√T, doubled as the noise itself is for vibration
    zaru = 2.0 * cfg.noise.arw / math.sqrt(IMU_MEMORY * cfg.imu_interval)
    s = dataclasses.replace(
        base.settings, noise=cfg.noise, init_att_sigma=cfg.init_att_sigma, init_vel_sigma=cfg.init_vel_sigma,
        init_gyro_bias_sigma=cfg.init_gyro_bias_sigma, init_accel_bias_sigma=cfg.init_accel_bias_sigma,
        gnss_lever_arm=cfg.lever_arm_gnss, gnss_quality_scale=(1.0, cfg.float_gain, cfg.single_gain),
        gnss_min_sigma=0.005, gnss_min_sigma_v=0.02,
        nhc_sigma=cfg.nhc_sigma if cfg.nhc else None, nhc_vertical_sigma=cfg.nhc_vertical_sigma,
        nhc_lever_uncertainty=cfg.nhc_lever_uncertainty, nhc_coast_after=cfg.coast_after,
        zupt_sigma=cfg.zupt_sigma if cfg.zupt else None, zaru_sigma=zaru if cfg.zupt else None,
        time_offset=(cfg.time_offset_sigma, cfg.time_offset_rw) if cfg.estimate_time_offset else None,
        cov_interval=cfg.cov_interval)
    return dataclasses.replace(base, settings=s)
