"""Truth from external trajectories: a scenario whose ``[trajectories]`` give its vehicles' paths
(a SUMO simulation's, or any recorded or simulated CSV) instead of the traffic model's.

Each vehicle is *on the air* (its sensors report, so its agent runs) from its first sample to its
last: a vehicle that enters the simulation later or leaves it earlier than the scenario's span
drives on, off the air, for :data:`OFF_AIR_LEAD` seconds at its first or last speed along its
first or last heading (and stands beyond), so that its motion, hence its IMU, is smooth where it
appears and disappears. Between its samples the
reference point (``l0`` behind the front for positions of the front, as SUMO reports) follows the
samples' polyline, passing through every sample at its time.

The queues at the stop lines come from the samples' lanes and lane positions where the source
has them (SUMO does), else from the samples' positions projected onto the site's lanes: a
vehicle is the first stopped of its approach while it stands on a lane that ends in a stop line,
within the gate of the line, with no vehicle ahead of it on that lane.
"""

from __future__ import annotations

import numpy as np
import pymap3d
from scipy.interpolate import PchipInterpolator

from slcp.geo.site import Lane

from .external import Track, TrajectoryError
from .geometry import Path, polyline_length
from .kinematics import generate
from .scenario import Scenario
from .traffic import FIRST_STOP_GATE, STEP, STOPPED_SPEED, Route, Segment, TrafficResult
from .truth import PathProfile, ScenarioTruth, VehicleTruth

#: [m] the path's resampling step: a vertex of the samples' polyline is rounded within this
STEP_PATH = 0.1
#: [s] of driving on, off the air, before a vehicle's first sample and after its last
OFF_AIR_LEAD = 5.0


def _unit(heading: np.ndarray) -> np.ndarray:
    return np.column_stack([np.cos(heading), np.sin(heading)])


def motion_heading(track: Track) -> np.ndarray:
    """Each sample's heading [rad]: the track's own, else the direction of the next move of at
    least 5 cm (the last such move's while standing, and at the end)."""
    if track.heading is not None:
        return np.asarray(track.heading, float)
    ne = track.ne
    n = len(ne)
    out = np.full(n, np.nan)
    j = 0
    for i in range(n):
        j = max(j, i + 1)
        while j < n and np.linalg.norm(ne[j] - ne[i]) < 0.05:
            j += 1
        if j < n:
            out[i] = np.arctan2(ne[j, 1] - ne[i, 1], ne[j, 0] - ne[i, 0])
    for i in range(1, n):  # standing at the end: the last move's heading
        if np.isnan(out[i]):
            out[i] = out[i - 1]
    result: np.ndarray = np.nan_to_num(out, nan=0.0)
    return result


def reference_positions(track: Track, heading: np.ndarray, l0: float, point: str) -> np.ndarray:
    """The reference point's (north, east) [m] at each sample: the samples themselves, or
    ``l0`` behind positions of the front."""
    return track.ne - l0 * _unit(heading) if point == "front" else np.asarray(track.ne, float)


def _speed(track: Track, i: int) -> float:
    if track.speed is not None:
        return float(track.speed[i])
    j = (i + 1, i) if i == 0 else (i, i - 1)
    return float(np.linalg.norm(track.ne[j[0]] - track.ne[j[1]]) / (track.t[j[0]] - track.t[j[1]]))


def extended_profile(track: Track, ref: np.ndarray, heading: np.ndarray,
                     t_grid: np.ndarray) -> tuple[Path, np.ndarray]:
    """The reference point's path, extended straight before the first and after the last sample
    by :data:`OFF_AIR_LEAD` seconds of driving at the first and last speed (standing before and
    after that: the jolt is off the air, where no sensor reports), and its arc length [m] at the
    grid's times ``t_grid`` [s]. (A longer run-in would leave the map's tangent plane: a course
    of constant heading on the ellipsoid bends away from a straight line in it.)"""
    t = track.t
    v0, v1 = _speed(track, 0), _speed(track, len(t) - 1)
    lead0 = min(max(t[0] - t_grid[0], 0.0), OFF_AIR_LEAD)
    lead1 = min(max(t_grid[-1] - t[-1], 0.0), OFF_AIR_LEAD)
    pre, post = lead0 * v0, lead1 * v1
    s_samples = pre + np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ref, axis=0), axis=1))])
    pts = [ref]
    if pre > 1e-6:
        pts.insert(0, ref[:1] - pre * _unit(heading[:1]))
    if post > 1e-6:
        pts.append(ref[-1:] + post * _unit(heading[-1:]))
    # monotone cubic in time: exact at the samples, and a smooth speed between sparse ones
    s = PchipInterpolator(t, s_samples, extrapolate=True)(t_grid)
    before, after = t_grid < t[0], t_grid > t[-1]
    s[before] = pre - v0 * np.minimum(t[0] - t_grid[before], lead0)
    s[after] = s_samples[-1] + v1 * np.minimum(t_grid[after] - t[-1], lead1)
    if s_samples[-1] + post < 1e-3:  # never moves: a short stub along its heading keeps the path valid
        pts.append(ref[-1:] + 0.05 * _unit(heading[-1:]))
    return Path(np.vstack(pts), step=STEP_PATH, smooth=False), np.maximum.accumulate(np.maximum(s, 0.0))


def project_lanes(track: Track, heading: np.ndarray, lanes: dict[str, Lane]) -> tuple[np.ndarray, np.ndarray]:
    """Lane id and position along it [m] of each sample of a track without them: the lane whose
    centre line passes within half its width of the sample, travelled within 45° of the
    sample's heading ("" and NaN where none)."""
    lane = np.full(len(track.t), "", dtype=object)
    pos = np.full(len(track.t), np.nan)
    best = np.full(len(track.t), np.inf)
    u = _unit(heading)
    for ln in lanes.values():
        c = np.asarray(ln.centerline, float)
        seg = np.diff(c, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        s0 = np.concatenate([[0.0], np.cumsum(seg_len)])
        for k in range(len(seg)):
            d = seg[k] / seg_len[k]
            rel = track.ne - c[k]
            along = rel @ d
            lat = np.abs(rel @ np.array([-d[1], d[0]]))
            ok = (along >= 0) & (along <= seg_len[k]) & (lat <= ln.width / 2) & (lat < best) \
                & (u @ d > np.cos(np.pi / 4))
            lane[ok], pos[ok], best[ok] = ln.id, s0[k] + along[ok], lat[ok]
    return lane, pos


def queue_heads(scn: Scenario, tracks: dict[str, Track], lanes_of: dict[str, tuple[np.ndarray, np.ndarray]],
                t_grid: np.ndarray) -> dict[str, np.ndarray]:
    """Per vehicle and grid step: the vehicle nearest the stop line of a lane that ends in one,
    within the gate (the first stopped vehicle of its approach while it also stands, which the
    truth's own motion tells: :func:`build_trajectory_truth`)."""
    lengths = {lid: polyline_length(ln.centerline) for lid, ln in scn.lanes.items() if ln.stop_line}
    l0 = {v.id: v.l0 for v in scn.vehicles}
    n = len(t_grid)
    # each vehicle's sample at each grid step (-1 when off the air)
    at: dict[str, np.ndarray] = {}
    for vid, tr in tracks.items():
        k = np.clip(np.searchsorted(tr.t, t_grid - 1e-6), 0, len(tr.t) - 1)
        k[(t_grid < tr.t[0] - 1e-6) | (t_grid > tr.t[-1] + 1e-6)] = -1
        at[vid] = k
    flags = {vid: np.zeros(n, bool) for vid in tracks}
    for step in range(n):
        head: dict[str, tuple[float, str]] = {}  # stop lane -> (front position, vehicle) of the one ahead
        for vid, k in at.items():
            i = k[step]
            if i < 0:
                continue
            lane, pos = lanes_of[vid][0][i], lanes_of[vid][1][i]
            if lane in lengths and (lane not in head or pos > head[lane][0]):
                head[lane] = (pos, vid)
        for lane, (pos, vid) in head.items():
            # the traffic model's gate, on the reference point's distance to the line
            flags[vid][step] = lengths[lane] - pos + l0[vid] <= FIRST_STOP_GATE + 5.0
    return flags


def build_trajectory_truth(scn: Scenario) -> ScenarioTruth:
    """Every vehicle's truth from the scenario's ``[trajectories]``."""
    src = scn.trajectories
    assert src is not None
    tracks = src.tracks()
    specs = {v.id: v for v in scn.vehicles}
    missing = sorted(set(specs) - set(tracks))
    if missing:
        raise TrajectoryError(f"{src.file}: no samples of the scenario's vehicle(s) {', '.join(missing)}")
    tracks = {vid: tracks[vid] for vid in specs}
    n = int(round(scn.duration / STEP)) + 1
    t_grid = np.arange(n) * STEP
    headings = {vid: motion_heading(tr) for vid, tr in tracks.items()}
    lanes_of = {vid: (tr.lane, tr.lane_pos) if tr.detailed else project_lanes(tr, headings[vid], scn.lanes)
                for vid, tr in tracks.items()}
    heads = queue_heads(scn, tracks, lanes_of, t_grid)
    routes, s_grid, v_grid, gaps = {}, {}, {}, {}
    out = {}
    for vid, tr in tracks.items():
        ref = reference_positions(tr, headings[vid], specs[vid].l0, src.point)
        path, s = extended_profile(tr, ref, headings[vid], t_grid)
        prof = PathProfile(path, t_grid, s)
        ne = path.position(s[0])
        llh0 = pymap3d.ned2geodetic(ne[0], ne[1], 0.0, *scn.origin_llh, deg=False)
        lat0, lon0, h0 = (float(x) for x in llh0)
        truth = generate(prof, scn.duration, rate=scn.imu_rate, origin_llh=(lat0, lon0, h0))
        present = (truth.t >= tr.t[0] - 1e-6) & (truth.t <= tr.t[-1] + 1e-6)
        k = np.clip(np.searchsorted(tr.t, truth.t - 1e-6), 0, len(tr.t) - 1)
        segment = np.where(present, lanes_of[vid][0][k], "").astype(str)
        stopped = (np.linalg.norm(truth.v_ned, axis=1) < STOPPED_SPEED) & present
        g = np.clip(np.round(truth.t / STEP).astype(int), 0, n - 1)
        first = heads[vid][g] & stopped
        out[vid] = VehicleTruth(truth, prof.arc(truth.t), stopped, first, segment, present)
        routes[vid] = Route(path, [Segment("", 0.0, path.length, False)])  # the lanes are in ``segment``
        s_grid[vid], v_grid[vid] = s, np.gradient(s, t_grid)
        gaps[vid] = float("nan")  # the stop gap where it first stands first, front to line
        stop_at = np.flatnonzero(first)
        if len(stop_at) and tr.detailed:
            i = int(k[stop_at[0]])
            gaps[vid] = polyline_length(scn.lanes[str(tr.lane[i])].centerline) - float(tr.lane_pos[i])
    traffic = TrafficResult(t_grid, routes, s_grid, v_grid, gaps, {vid: () for vid in tracks})
    return ScenarioTruth(scn, traffic, out)
