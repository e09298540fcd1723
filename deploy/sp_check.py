"""SP (GNSS/INS) on a scenario's emulated sensors, and its RMSE per vehicle and evaluation window
beside the paper's SP row.

Filter initialisation (documented simplification until the agent's own alignment runs on
emulated data): position and velocity from the first GNSS fix, attitude from the truth plus
errors drawn from the initial covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slcp.agent.nav.ins_filter import InsFilter
from slcp.agent.nav.measurements.gnss import gnss_position, gnss_velocity
from slcp.agent.nav.rotation import euler_to_quat
from slcp.agent.nav.state import NavState, apply_error
from slcp.geo import earth
from slcp.hw_emulation.emulate import VehicleSensors, emulate_vehicle_sensors
from slcp.hw_emulation.events import window_bounds
from slcp.hw_emulation.sensors.imu import ImuModel
from slcp.hw_emulation.truth import ScenarioTruth, VehicleTruth

from .agent_configs import imu_noise_of

EVAL_STEP = 10  #: evaluate every 10th IMU sample (10 Hz at 100 Hz)


@dataclass(frozen=True)
class SpRun:
    t: np.ndarray  #: evaluation times [s]
    h_err: np.ndarray  #: horizontal error [m]
    h_sigma: np.ndarray  #: reported horizontal σ [m]


def run_sp(vt: VehicleTruth, vs: VehicleSensors, imu_model: ImuModel, rng: np.random.Generator) -> SpRun:
    """Run SP for one vehicle over its emulated IMU and GNSS."""
    tr = vt.truth
    g = vs.gnss
    p_att = np.radians([1.0, 1.0, 3.0])
    p0 = np.concatenate([p_att, [0.3] * 3, np.maximum(g.sigma_ned[0], 0.5),
                         [math.hypot(imu_model.gyro_turn_on, imu_model.gyro_in_run)] * 3,
                         [math.hypot(imu_model.accel_turn_on, imu_model.accel_in_run)] * 3]) ** 2
    att_err = np.zeros(15)
    att_err[0:3] = rng.normal(0.0, p_att)
    st = apply_error(NavState(*tr.llh[0], tr.v_ned[0].copy(), euler_to_quat(*tr.euler[0])), att_err)
    if g.t.size and g.t[0] <= tr.t[0] + 1e-6:
        st.lat, st.lon, st.h = g.llh[0]
        st.v = g.v_ned[0].copy()
    flt = InsFilter(st, np.diag(p0), imu_noise_of(imu_model), t=float(tr.t[0]), cov_interval=0.1)
    gi = 1 if g.t.size and g.t[0] <= tr.t[0] + 1e-6 else 0
    dth, dvl = vs.imu.dtheta.tolist(), vs.imu.dvel.tolist()
    dts = np.diff(tr.t).tolist()
    n = len(dts)
    # the IMU intervals run between events (a fix to take, an evaluation) in one call each
    fix_k = np.searchsorted(tr.t[1:], g.t[gi:] - 1e-6, side="left")  # interval after which each fix applies
    ends = np.union1d(fix_k[fix_k < n], np.arange(EVAL_STEP - 1, n, EVAL_STEP))
    ts, errs, sigs = [], [], []
    start = 0
    for k in (*ends.tolist(), n - 1):
        if k < start:
            continue
        flt.propagate_run(dth[start:k + 1], dvl[start:k + 1], dts[start:k + 1])
        start = k + 1
        tk = tr.t[k + 1]
        while gi < len(g.t) and g.t[gi] <= tk + 1e-6:
            flt.update(gnss_position(flt.state, g.llh[gi], np.diag(g.sigma_ned[gi] ** 2)))
            flt.update(gnss_velocity(flt.state, g.v_ned[gi], np.eye(3) * g.sigma_v[gi] ** 2, np.zeros(3)))
            gi += 1
        if (k + 1) % EVAL_STEP == 0:
            s = flt.state
            e = earth.ned_offset(s.lat, s.lon, s.h, *tr.llh[k + 1])
            p = flt.position_cov
            ts.append(tk)
            errs.append(math.hypot(e[0], e[1]))
            sigs.append(math.sqrt(p[0, 0] + p[1, 1]))
    return SpRun(np.array(ts), np.array(errs), np.array(sigs))


def window_rmse(run: SpRun, bounds: tuple[float, float]) -> float:
    m = (run.t >= bounds[0]) & (run.t <= bounds[1])
    return float(np.sqrt(np.mean(run.h_err[m] ** 2))) if m.any() else math.nan


def sp_table(truth: ScenarioTruth, seeds: list[int]) -> dict[str, dict[str, list[float]]]:
    """RMSE of SP per window and vehicle for each sensor seed: ``{window: {vehicle: [rmse...]}}``.

    Only the (window, vehicle) cells that the scenario's ``[paper]`` table lists, or all cells if
    it has none.
    """
    scn = truth.scenario
    specs = {v.id: v for v in scn.vehicles}
    bounds = window_bounds(truth)
    cells = {w: [vid for vid in scn.paper_table.get(w, {}) if "SP" in scn.paper_table[w][vid]] or
             (list(truth.vehicles) if not scn.paper_table else []) for w in bounds}
    out = {w: {vid: [] for vid in vids} for w, vids in cells.items() if vids}
    for seed in seeds:
        rng = np.random.default_rng(seed)
        sensors = emulate_vehicle_sensors(truth, rng)
        for vid, vt in truth.vehicles.items():
            if not any(vid in out[w] for w in out):
                continue
            run = run_sp(vt, sensors[vid], specs[vid].imu, rng)
            for w in out:
                if vid in out[w]:
                    out[w][vid].append(window_rmse(run, bounds[w]))
    return out
