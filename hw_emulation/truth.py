"""Truth trajectories of a scenario's vehicles at the IMU rate, with consistent IMU increments.

Each vehicle's arc length on its route (traffic model, 0.1 s grid) is interpolated by a monotone
C¹ spline (PCHIP), so speed is continuous and never negative; heading is the route's smooth heading
at that arc length. :func:`hw_emulation.kinematics.generate` then integrates position and the
exact IMU increments from speed and attitude; integrating those increments with the navigation
core's mechanisation reproduces the truth (a test checks 0.05 m over 60 s).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pymap3d
from scipy.interpolate import PchipInterpolator

from slcp.geo import earth

from .geometry import Path
from .kinematics import Truth, generate
from .scenario import Scenario
from .traffic import STOPPED_SPEED, TrafficResult, driver_draws, first_stopped_flags, simulate_traffic


@dataclass(frozen=True)
class PathProfile:
    """A :class:`~hw_emulation.kinematics.KinematicProfile` moving along a planar path."""

    path: Path
    t_knots: np.ndarray
    s_knots: np.ndarray

    def __post_init__(self) -> None:
        sp = PchipInterpolator(self.t_knots, self.s_knots, extrapolate=True)
        object.__setattr__(self, "_s", sp)
        object.__setattr__(self, "_v", sp.derivative(1))
        object.__setattr__(self, "_a", sp.derivative(2))

    def arc(self, t: np.ndarray) -> np.ndarray:
        return self._s(t)

    def speed(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.maximum(self._v(t), 0.0), self._a(t)

    def euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = self._s(t)
        v = np.maximum(self._v(t), 0.0)
        yaw = self.path.heading(s)
        yaw_rate = self.path.curvature(s) * v
        z = np.zeros_like(yaw)
        return np.stack([z, z, yaw], 1), np.stack([z, z, yaw_rate], 1)


#: [m] how close to where it stands first stopped a vehicle counts as there (:attr:`VehicleTruth.first_stop_zone`)
SETTLE_DISTANCE = 0.05


@dataclass(frozen=True)
class VehicleTruth:
    """Truth of one vehicle at the IMU rate.

    Attributes
    ----------
    truth : Truth
        Position, velocity, attitude and exact IMU increments (see kinematics).
    arc : ndarray, shape (n,)
        Arc length along the route [m].
    stopped, first_stopped : ndarray of bool, shape (n,)
    segment : ndarray of str, shape (n,)
        Lane id (or ``A>B`` turn) occupied.
    present : ndarray of bool, shape (n,), or None
        Whether the vehicle is on the air (its sensors report) at each sample; None: always
        (a vehicle of external trajectories is on the air from its first sample to its last).
    """

    truth: Truth
    arc: np.ndarray
    stopped: np.ndarray
    first_stopped: np.ndarray
    segment: np.ndarray
    present: np.ndarray | None = None

    @cached_property
    def first_stop_zone(self) -> np.ndarray:
        """Where the vehicle is within :data:`SETTLE_DISTANCE` of where it stands first stopped,
        in the same stop (creeping into it, or just pulling away), shape (n,): a claim there puts
        the stop-line fix within centimetres of the truth, far inside the stop gap's spread,
        whatever the speed threshold of the label says (a driver model with a slow final creep,
        such as SUMO's, spends seconds there)."""
        zone = self.first_stopped.copy()
        f = self.first_stopped.astype(np.int8)
        starts = np.flatnonzero(np.diff(np.r_[0, f]) == 1)
        ends = np.flatnonzero(np.diff(np.r_[f, 0]) == -1)
        for a, b in zip(starts, ends):  # the arc length never decreases
            lo = int(np.searchsorted(self.arc, self.arc[a] - SETTLE_DISTANCE, side="left"))
            hi = int(np.searchsorted(self.arc, self.arc[b] + SETTLE_DISTANCE, side="right"))
            zone[lo:hi] = True
        return zone

    def present_over(self, t: np.ndarray) -> np.ndarray:
        """:meth:`present_at` of every time in ``t`` [s], shape of ``t``."""
        if self.present is None:
            return np.ones(np.shape(t), bool)
        return self.present[self.samples_over(t)]

    def present_at(self, t: float) -> bool:
        """Whether the vehicle is on the air at ``t`` [s] (its sensors report)."""
        return self.present is None or bool(self.present[self.sample_at(t)])

    def stopped_at(self, t: np.ndarray) -> np.ndarray:
        """Whether the vehicle truly stands at times ``t`` [s] (the first IMU sample not before
        each), shape of ``t``."""
        return self.stopped[self.samples_over(t)]

    def samples_over(self, t: np.ndarray) -> np.ndarray:
        """:meth:`sample_at` of every time in ``t`` [s], shape of ``t``."""
        return np.minimum(np.searchsorted(self.truth.t, np.asarray(t, float) - 1e-9), len(self.truth.t) - 1)

    def sample_at(self, t: float) -> int:
        """The index of the truth sample an estimate of time ``t`` [s] is scored against: the first
        IMU sample not before ``t`` (the last one after the end)."""
        return int(self.samples_over(t))

    def error_of(self, t: float, llh) -> tuple[np.ndarray, int]:
        """An estimate's position error: its NED offset [m] from the truth at ``t`` [s] (``llh``
        [rad, rad, m]), and the truth sample's index (:meth:`sample_at`)."""
        k = self.sample_at(t)
        return earth.ned_offset(*(float(x) for x in llh), *self.truth.llh[k]), k


@dataclass(frozen=True)
class ScenarioTruth:
    scenario: Scenario
    traffic: TrafficResult
    vehicles: dict[str, VehicleTruth]


def stance_rng(scn: Scenario, stop_seed: int | None = None) -> np.random.Generator:
    """The generator of the drivers' stop gaps and lateral offsets (:func:`build_truth`): the
    scenario's seed, combined with a run's ``stop_seed`` if given."""
    return np.random.default_rng(scn.seed if stop_seed is None else [scn.seed, stop_seed])


def stance_draws(scn: Scenario, stop_seed: int | None = None) -> dict[str, tuple[float, float]]:
    """The drivers' (d_s, d_l) [m] of :func:`build_truth` with this ``stop_seed``, without the
    traffic simulation (:func:`hw_emulation.traffic.driver_draws`)."""
    return driver_draws(scn, stance_rng(scn, stop_seed))


def build_truth(scn: Scenario, rng: np.random.Generator | None = None,
                stop_seed: int | None = None) -> ScenarioTruth:
    """Simulate traffic and generate every vehicle's truth.

    The traffic model's only random draws are where each driver stands in its lane: the stop
    gap d_s and the lateral offset d_l (the stop-line fix's noise). They come from ``rng``, else
    from the scenario's seed, combined with ``stop_seed`` (a run's seed) if given: a Monte-Carlo
    over runs then redraws them with the sensors instead of replaying one draw per scenario.
    """
    if scn.trajectories is not None:
        from .trajectory_truth import build_trajectory_truth

        return build_trajectory_truth(scn)
    traffic = simulate_traffic(scn, rng if rng is not None else stance_rng(scn, stop_seed))
    fs = first_stopped_flags(scn, traffic)
    out = {}
    for vid, route in traffic.routes.items():
        prof = PathProfile(route.path, traffic.t, traffic.s[vid])
        ne = route.path.position(traffic.s[vid][0])
        llh0 = pymap3d.ned2geodetic(ne[0], ne[1], 0.0, *scn.origin_llh, deg=False)
        tr = generate(prof, scn.duration, rate=scn.imu_rate, origin_llh=tuple(float(x) for x in llh0))
        arc = prof.arc(tr.t)
        idx = np.clip(np.round(tr.t / (traffic.t[1] - traffic.t[0])).astype(int), 0, len(traffic.t) - 1)
        seg = np.array([route.segment_at(a).key for a in arc[:: max(1, int(scn.imu_rate / 10))]])
        seg = np.repeat(seg, max(1, int(scn.imu_rate / 10)))[: len(tr.t)]
        stopped = np.linalg.norm(tr.v_ned, axis=1) < STOPPED_SPEED
        out[vid] = VehicleTruth(tr, arc, stopped, fs[vid][idx] & stopped, seg)
    return ScenarioTruth(scn, traffic, out)
