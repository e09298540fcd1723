"""Sensor data of a scenario's vehicles from its truth (pure: everything comes from the rng).

IMU increments at the scenario's IMU rate; GNSS fixes at each vehicle's GNSS rate with the
urban error model (one common-mode realisation shared by all vehicles); the camera's lane-marking
classes; UWB ranges for every pair. The service that publishes these on the bus (issue
"Distributed fleet") consumes this.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from slcp.geo import earth
from slcp.geo.lane_markings import UNSEEN, LaneEdges, marking_classes

from .scenario import Scenario
from .sensors.camera import simulate_markings
from .sensors.gnss import GnssErrors, common_mode_error, simulate_gnss
from .sensors.imu import ImuErrors, corrupt_increments
from .sensors.uwb import UwbRanges, simulate_pair
from .truth import ScenarioTruth


@dataclass(frozen=True)
class GnssFixes:
    """GNSS output of one receiver.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Epoch times [s] (only epochs with a fix).
    llh : ndarray, shape (n, 3)
        Measured antenna latitude, longitude [rad], ellipsoidal height [m].
    v_ned : ndarray, shape (n, 3)
        Measured velocity [m/s].
    sigma_ned : ndarray, shape (n, 3)
        Reported position σ [m].
    sigma_v : ndarray, shape (n,)
        Reported velocity σ per axis [m/s].
    errors : GnssErrors
        The injected errors at every epoch (including those without a fix).
    """

    t: np.ndarray
    llh: np.ndarray
    v_ned: np.ndarray
    sigma_ned: np.ndarray
    sigma_v: np.ndarray
    errors: GnssErrors


@dataclass(frozen=True)
class LaneMarkingReports:
    """The camera's lane-marking classes: ``t`` (n,) [s], ``classes`` (n, 2) ints (left,
    right; see :mod:`geo.lane_markings`), ``truth`` (n, 2) the true classes."""

    t: np.ndarray
    classes: np.ndarray
    truth: np.ndarray


@dataclass(frozen=True)
class VehicleSensors:
    imu_t: np.ndarray  #: IMU sample times [s]; interval k spans imu_t[k]..imu_t[k+1]
    imu: ImuErrors
    gnss: GnssFixes
    lane: LaneMarkingReports | None = None  #: None if the scenario's vehicles have no camera


def true_marking_classes(scn: Scenario) -> dict[str, tuple[int, int]]:
    """The (left, right) marking classes of every lane of the scenario's map."""
    return marking_classes({lane.id: LaneEdges(*lane.end_left_line(), lane.width) for lane in scn.lanes.values()})


def _lane_reports(scn: Scenario, vt, classes: dict[str, tuple[int, int]],
                  rng: np.random.Generator) -> LaneMarkingReports:
    tr = vt.truth
    t = np.arange(tr.t[0], tr.t[-1] + 1e-9, 1.0 / scn.camera.rate)
    k = np.clip(np.searchsorted(tr.t, t - 1e-9), 0, len(tr.t) - 1)
    truth = np.array([classes.get(str(seg), (UNSEEN, UNSEEN)) for seg in vt.segment[k]], dtype=np.int64)
    return LaneMarkingReports(t, simulate_markings(scn.camera, truth, rng), truth)


def emulate_vehicle_sensors(truth: ScenarioTruth, rng: np.random.Generator) -> dict[str, VehicleSensors]:
    """IMU, GNSS and lane-marking camera of every vehicle."""
    scn = truth.scenario
    specs = {v.id: v for v in scn.vehicles}
    first = next(iter(truth.vehicles.values())).truth
    rate = max(v.gnss.rate for v in scn.vehicles)
    t_common = np.arange(first.t[0], first.t[-1] + 1e-9, 1.0 / rate)
    common = common_mode_error(t_common, scn.common_mode_sigma, scn.common_mode_tau, rng)
    out = {}
    for vid, vt in truth.vehicles.items():
        spec = specs[vid]
        tr = vt.truth
        imu = corrupt_increments(spec.imu, tr.dtheta, tr.dvel, np.diff(tr.t), rng)
        tg = np.arange(tr.t[0], tr.t[-1] + 1e-9, 1.0 / spec.gnss.rate)
        k = np.clip(np.searchsorted(tr.t, tg - 1e-9), 0, len(tr.t) - 1)
        moving = ~vt.stopped[k]
        cm = common[np.clip(np.searchsorted(t_common, tg - 1e-9), 0, len(t_common) - 1)]
        err = simulate_gnss(spec.gnss, tg, moving, rng, cm)
        llh = tr.llh[k].copy()
        rm, rn = np.vectorize(earth.radii, otypes=[float, float])(llh[:, 0])
        llh[:, 0] += err.pos_error[:, 0] / (rm + llh[:, 2])
        llh[:, 1] += err.pos_error[:, 1] / ((rn + llh[:, 2]) * np.cos(llh[:, 0]))
        llh[:, 2] -= err.pos_error[:, 2]
        v = tr.v_ned[k] + err.vel_error
        ok = err.valid
        fixes = GnssFixes(tg[ok], llh[ok], v[ok], err.reported_sigma[ok], err.reported_sigma_v[ok], err)
        out[vid] = VehicleSensors(tr.t, imu, fixes)
    if scn.camera.enabled:  # a stream of its own: the camera leaves every other draw as it was
        cam_rng = rng.spawn(1)[0]
        classes = true_marking_classes(scn)
        for vid, vt in truth.vehicles.items():
            out[vid] = dataclasses.replace(out[vid], lane=_lane_reports(scn, vt, classes, cam_rng))
    return out


def emulate_uwb(truth: ScenarioTruth, rng: np.random.Generator) -> dict[tuple[str, str], UwbRanges]:
    """UWB ranges for every vehicle pair at the scenario's UWB rate (one value per pair)."""
    scn = truth.scenario
    ids = sorted(truth.vehicles)
    first = truth.vehicles[ids[0]].truth
    step = max(1, int(round(scn.imu_rate / scn.uwb.rate)))
    idx = np.arange(0, len(first.t), step)
    out = {}
    for a, b in combinations(ids, 2):
        la, lb = truth.vehicles[a].truth.llh[idx], truth.vehicles[b].truth.llh[idx]
        rm, rn = earth.radii(float(la[0, 0]))
        d = np.column_stack([(la[:, 0] - lb[:, 0]) * rm, (la[:, 1] - lb[:, 1]) * rn * np.cos(la[:, 0]),
                             la[:, 2] - lb[:, 2]])
        out[(a, b)] = simulate_pair(scn.uwb, first.t[idx], np.linalg.norm(d, axis=1), rng)
    return out
