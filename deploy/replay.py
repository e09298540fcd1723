"""Replay a recorded drive through the SP filter (GNSS/INS) with simulated GNSS outages.

The outage protocol is the one the rtklibexplorer data's authors use: with ``t0`` the first GNSS
epoch and ``tN`` the last, outage ``k`` withholds the fixes in ``[S_k, S_k + length)`` with
``S_k = t0 + first + period * k`` for every ``k`` with ``S_k < tN - end_margin``. The filter is
causal: every error is that of the estimate at the epoch *before* any update at that epoch, and
nothing is smoothed backwards.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from agent.nav.error_model import ImuNoise
from agent.nav.ins_filter import InsFilter, level_from_accel
from agent.nav.kalman import Measurement
from agent.nav.measurements.common import point_llh
from agent.nav.measurements.gnss import gnss_position, gnss_velocity
from agent.nav.measurements.vehicle import non_holonomic, zero_angular_rate, zero_velocity
from agent.nav.motion import StationaryDetector
from agent.nav.rotation import euler_to_dcm, euler_to_quat, quat_to_euler
from agent.nav.state import NavState
from geo import earth

from .datasets.rtklib import RtklibDrive
from .sensors.imu import imu_increments

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
    """Filter and sensor configuration of a replay (SI units, radians).

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
    imu_time_offset: float = -0.125
    #: estimate the IMU-GNSS time offset online (extra filter state) starting from the above
    estimate_time_offset: bool = True
    time_offset_sigma: float = 0.05
    time_offset_rw: float = 1e-3
    #: IMU scale-factor states (accel sigma, gyro sigma, correlation time s); None disables
    scale_factors: tuple[float, float, float] | None = None
    #: geoid undulation added to the file's MSL heights [m] (EGM96 near 40.10 N 105.15 W)
    geoid_undulation: float = -16.8
    outage: OutageProtocol = OutageProtocol()
    use_velocity: bool = True
    zupt: bool = True
    nhc: bool = True
    #: with GNSS on, NHC rows are stacked into each GNSS update instead of being applied at
    #: ``constraint_rate`` (same information per epoch, a third of the updates); while coasting
    #: (no fix for ``coast_after`` s) NHC runs at ``constraint_rate``
    nhc_only_coasting: bool = True
    coast_after: float = 1.0
    nhc_sigma: float = 0.1
    #: NHC vertical-velocity sigma [m/s]; a mount-pitch error biases this row, so it is looser
    nhc_vertical_sigma: float = 0.1
    nhc_lever_uncertainty: float = 1.0
    zupt_sigma: float = 0.02
    constraint_rate: float = 10.0
    yaw_align_speed: float = 1.0
    float_gain: float = 2.0
    single_gain: float = 5.0
    #: covariance propagation interval [s]: the fix period of this drive (4 Hz), so P is
    #: propagated once per epoch (plus at constraint updates); 0.2 s gives the same metrics to
    #: 1 cm with 40 % more covariance steps
    cov_interval: float = 0.25
    init_att_sigma: tuple[float, float, float] = tuple(np.radians([2.0, 2.0, 60.0]).tolist())
    init_vel_sigma: float = 0.1
    init_gyro_bias_sigma: float = math.radians(0.1)
    init_accel_bias_sigma: float = 0.1
    detector: StationaryDetector = StationaryDetector()


@dataclass
class ReplayResult:
    """Per-epoch evaluation and the recorded trajectory; ``t0`` is the first GNSS epoch [s]."""

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


def run_replay(drive: RtklibDrive, cfg: ReplayConfig = ReplayConfig()) -> ReplayResult:
    """Run SP over a drive with the outage protocol and evaluate against the withheld fixes."""
    wall0 = time.perf_counter()
    imu, gnss = drive.imu, drive.gnss
    c_sb = euler_to_dcm(*cfg.mount_rpy).T  # Groves' Euler_to_CTM = transpose of body-to-nav
    t_imu = imu.t + cfg.imu_time_offset
    dtheta_a, dvel_a, dt_a = imu_increments(t_imu, imu.accel, imu.gyro, c_sb)
    # plain lists: indexing them in the hot loop is far cheaper than numpy rows
    dtheta, dvel, dt = dtheta_a.tolist(), dvel_a.tolist(), dt_a.tolist()
    w_b = imu.gyro @ c_sb.T
    f_b = imu.accel @ c_sb.T
    stationary = cfg.detector.detect(f_b, w_b) if cfg.zupt else np.zeros(len(t_imu), bool)
    lever = np.array(cfg.lever_arm_gnss, float)
    llh_ref = gnss.llh.copy()
    llh_ref[:, 2] += cfg.geoid_undulation

    t0, t_end = float(gnss.t[0]), float(gnss.t[-1])
    outages = cfg.outage.windows(t0, t_end)
    out_start = np.array([o[0] for o in outages])
    out_end = np.array([o[1] for o in outages])

    # whether each epoch's fix is withheld (one vectorised test, not one per epoch)
    withheld_epoch = (
        ((gnss.t[:, None] >= out_start[None, :]) & (gnss.t[:, None] < out_end[None, :])).any(axis=1).tolist()
    )

    # start at the first GNSS epoch with one second of IMU history for levelling
    k_level = int(np.searchsorted(t_imu, t_imu[0] + 1.0))
    gi = int(np.searchsorted(gnss.t, t_imu[k_level]))
    if gi >= len(gnss.t):
        raise ValueError("no GNSS epoch after the first second of IMU data")
    k = int(np.searchsorted(t_imu, gnss.t[gi], side="right")) - 1  # last IMU sample <= epoch
    roll, pitch = level_from_accel(f_b[max(0, k - 100): k + 1].mean(axis=0))
    lat, lon, h = llh_ref[gi]
    state = NavState(lat, lon, h, gnss.v_ned[gi].copy(), euler_to_quat(roll, pitch, 0.0))
    P0 = np.diag(np.concatenate([
        np.square(cfg.init_att_sigma), np.full(3, cfg.init_vel_sigma**2),
        np.square(np.maximum(gnss.sd_neu[gi], 0.05)),
        np.full(3, cfg.init_gyro_bias_sigma**2), np.full(3, cfg.init_accel_bias_sigma**2),
    ]))
    # the state is at the antenna: shift to the IMU
    state.lat, state.lon, state.h = point_llh(state, -lever)
    extra = ((cfg.imu_time_offset, cfg.time_offset_sigma, cfg.time_offset_rw**2),) \
        if cfg.estimate_time_offset else ()
    flt = InsFilter(state, P0, cfg.noise, t=float(gnss.t[gi]), cov_interval=cfg.cov_interval,
                    extra_states=extra, scale_factors=cfg.scale_factors)

    def epoch_time(i: int) -> float:
        """Filter time at which GNSS epoch ``i`` is applied (shifted by the offset estimate)."""
        if not cfg.estimate_time_offset:
            return float(gnss.t[i])
        return float(gnss.t[i]) - (float(flt.extra[0]) - cfg.imu_time_offset)
    yaw_aligned = False
    last_fix_time = -math.inf

    n_ep = len(gnss.t)
    err_t, err_h, err_w = [], [], []
    traj = []
    step = max(1, int(round(1.0 / (cfg.constraint_rate * np.median(dt_a)))))
    # IMU interval j spans [t_imu[j], t_imu[j+1]]; the filter sits at gnss.t[gi] inside interval k
    j = k
    t_cur = float(gnss.t[gi])
    pending = _remainder(dtheta[j], dvel[j], t_imu[j], t_imu[j + 1], t_cur) if j < len(dt) else None

    def handle_epoch(i: int) -> None:
        nonlocal yaw_aligned, last_fix_time
        st = flt.state
        alat, alon, ah = point_llh(st, lever)
        e = earth.ned_offset(alat, alon, ah, *llh_ref[i])
        wh = withheld_epoch[i]
        err_t.append(gnss.t[i])
        err_h.append(math.hypot(e[0], e[1]))
        err_w.append(wh)
        rpy = np.degrees(quat_to_euler(st.q))
        sig = np.sqrt(np.diag(flt.position_cov))
        traj.append([gnss.t[i], math.degrees(st.lat), math.degrees(st.lon), st.h, *st.v, *rpy, *sig])
        if wh:
            return
        last_fix_time = flt.t
        gain = {1: 1.0, 2: cfg.float_gain}.get(int(gnss.quality[i]), cfg.single_gain)
        cov_p = np.diag(np.square(np.maximum(gnss.sd_neu[i] * gain, 0.005)))
        jj = min(j, len(w_b) - 1)
        meas = [gnss_position(st, llh_ref[i], cov_p, lever)]
        if cfg.use_velocity:
            cov_v = np.diag(np.square(np.maximum(gnss.sd_v[i] * gain, 0.02)))
            meas.append(gnss_velocity(st, gnss.v_ned[i], cov_v, w_b[jj], lever))
        moving = not (cfg.zupt and stationary[min(jj, len(stationary) - 1)])
        if cfg.nhc and cfg.nhc_only_coasting and yaw_aligned and moving:
            meas.append(_nhc(flt.state, w_b[jj], cfg))
        if cfg.estimate_time_offset:
            # the state at this filter time is the truth at t_gnss - dtau: z = ... - v dtau
            a_n = st.dcm @ f_b[max(0, jj - 9): jj + 1].mean(axis=0) - st.dcm @ st.ba
            a_n[2] += earth.gravity(st.lat, st.h)
            cols = [-st.v] + ([-a_n] if cfg.use_velocity else [])
            cols += [np.zeros(m.dim) for m in meas[len(cols):]]
            meas = [Measurement(m.z, flt.full_jacobian(m.H, c[:, None]), m.R, m.name) for m, c in zip(meas, cols)]
        speed = math.hypot(gnss.v_ned[i, 0], gnss.v_ned[i, 1])
        if not yaw_aligned and speed > cfg.yaw_align_speed:
            course = math.atan2(gnss.v_ned[i, 1], gnss.v_ned[i, 0])
            sigma = math.hypot(math.radians(3.0), gnss.sd_v[i, :2].max() / speed)
            flt.reset_yaw(course, sigma)
            yaw_aligned = True
            log.info("yaw aligned to GNSS course %.1f deg at %.2f s", math.degrees(course), gnss.t[i] - t0)
        flt.update_stacked(meas)

    handle_epoch(gi)
    gi += 1
    # filter time of the next epoch; changes only when an update moves the offset estimate
    t_ep = epoch_time(gi) if gi < n_ep else math.inf
    n_int = len(dt)
    t_list = t_imu.tolist()
    # runs of whole intervals are integrated at once; intervals shorter than this are skipped
    # (as the per-interval path does), so runs stop before them
    tiny = np.flatnonzero(dt_a <= 1e-9).tolist() + [n_int]

    def constrain(j: int) -> None:
        """ZUPT (and zero angular rate) at rest, else NHC while coasting, at sample ``j``."""
        if j >= len(stationary):
            return
        if stationary[j]:
            flt.update(zero_velocity(flt.state, cfg.zupt_sigma))
            flt.update(zero_angular_rate(flt.state, cfg.detector.window_mean_gyro(w_b, j),
                                         cfg.noise.arw / math.sqrt(cfg.detector.window * 0.01) * 2))
        elif cfg.nhc and yaw_aligned and (
                not cfg.nhc_only_coasting or flt.t - last_fix_time > cfg.coast_after):
            flt.update(_nhc(flt.state, w_b[j], cfg))

    while j < n_int:
        if pending is None:
            # whole intervals before the next constraint step, the next epoch and the next tiny one
            end = min((j // step + 1) * step, bisect.bisect_left(t_list, t_ep, j + 1) - 1,
                      tiny[bisect.bisect_left(tiny, j)])
            if end > j:
                flt.propagate_run(dtheta[j:end], dvel[j:end], dt[j:end])
                t_cur = t_list[end]
                j = end
                if j % step == 0:
                    constrain(j)
                continue
        t_next = t_list[j + 1]
        dth, dv, dtt = pending if pending is not None else (dtheta[j], dvel[j], dt[j])
        while t_ep <= t_next:
            tg = t_ep
            if tg > t_cur:
                a = (tg - t_cur) / dtt
                flt.propagate([a * x for x in dth], [a * x for x in dv], tg - t_cur)
                dth, dv, dtt = [(1 - a) * x for x in dth], [(1 - a) * x for x in dv], dtt * (1 - a)
                t_cur = tg
            handle_epoch(gi)
            gi += 1
            t_ep = epoch_time(gi) if gi < n_ep else math.inf
        if dtt > 1e-9:
            flt.propagate(dth, dv, dtt)
        t_cur = t_next
        j += 1
        pending = None
        if j % step == 0:
            constrain(j)
        if gi >= n_ep:
            break

    wall = time.perf_counter() - wall0
    res = ReplayResult(np.array(err_t), np.array(err_h), np.array(err_w, bool), outages, np.array(traj), t0)
    res.metrics = _metrics(res, outages, float(t_imu[-1] - t_imu[0]), wall)
    res.metrics["imu_time_offset_s"] = float(flt.extra[0]) if cfg.estimate_time_offset else cfg.imu_time_offset
    res.metrics["filter_stats"] = {"imu_samples": flt.stats.imu_samples, "cov_steps": flt.stats.cov_steps,
                                   "updates": flt.stats.updates, "rejected": flt.stats.rejected}
    return res


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


def _nhc(state: NavState, w_b: np.ndarray, cfg: ReplayConfig):
    """NHC with the lateral sigma inflated by yaw rate x the unknown IMU-to-rear-axle distance."""
    sig = math.hypot(cfg.nhc_sigma, abs(float(w_b[2])) * cfg.nhc_lever_uncertainty)
    return non_holonomic(state, sig, cfg.nhc_vertical_sigma)


def _remainder(dth, dv, t0, t1, t_from):
    a = (t_from - t0) / (t1 - t0)
    a = min(max(a, 0.0), 1.0)
    return [(1 - a) * x for x in dth], [(1 - a) * x for x in dv], (t1 - t0) * (1 - a)


def _metrics(res: ReplayResult, outages, imu_span: float, wall: float) -> dict:
    t, e, w = res.t, res.h_err, res.withheld
    ends = []
    for s, f in outages:
        idx = np.nonzero((t >= s) & (t < f))[0]
        if idx.size:
            ends.append(float(e[idx[-1]]))
    def rms(x):
        return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")
    return {
        "outage_h_rms_m": rms(e[w]),
        "outage_h_end_mean_m": float(np.mean(ends)) if ends else float("nan"),
        "outage_h_end_max_m": float(np.max(ends)) if ends else float("nan"),
        "outage_h_max_m": float(np.max(e[w])) if w.any() else float("nan"),
        "gnss_on_h_rms_m": rms(e[~w]),
        "n_outages": len(outages),
        "n_withheld_fixes": int(w.sum()),
        "outage_end_errors_m": ends,
        "imu_span_s": imu_span,
        "wall_s": wall,
        "realtime_factor": imu_span / wall if wall > 0 else float("inf"),
    }


def engine_config(cfg: ReplayConfig, vehicle: str = "V0"):
    """The vehicle engine's configuration for a drive replayed with ``cfg``: a vehicle without a
    site map running SP, with the drive's IMU noise and the filter options of ``cfg``."""
    import dataclasses as dc

    from .agent_configs import siteless_agent_config

    base = siteless_agent_config(vehicle, ("SP",))
    s = dc.replace(base.settings, noise=cfg.noise, init_att_sigma=cfg.init_att_sigma,
                   init_vel_sigma=cfg.init_vel_sigma, init_gyro_bias_sigma=cfg.init_gyro_bias_sigma,
                   init_accel_bias_sigma=cfg.init_accel_bias_sigma,
                   gnss_lever_arm=cfg.lever_arm_gnss, gnss_quality_scale=(1.0, cfg.float_gain, cfg.single_gain),
                   gnss_min_sigma=0.005, gnss_min_sigma_v=0.02,
                   nhc_sigma=cfg.nhc_sigma if cfg.nhc else None, nhc_vertical_sigma=cfg.nhc_vertical_sigma,
                   nhc_lever_uncertainty=cfg.nhc_lever_uncertainty, nhc_coast_after=cfg.coast_after,
                   zupt_sigma=cfg.zupt_sigma if cfg.zupt else None,
                   zaru_sigma=(cfg.noise.arw / math.sqrt(cfg.detector.window * 0.01) * 2) if cfg.zupt else None,
                   time_offset=(cfg.time_offset_sigma, cfg.time_offset_rw) if cfg.estimate_time_offset else None)
    return dc.replace(base, settings=s)
