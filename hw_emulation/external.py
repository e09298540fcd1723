"""External per-vehicle trajectories: CSV and SUMO FCD XML, turned into truth with consistent IMU.

CSV columns (header required, one row per vehicle and time, any order of rows)::

    time_s,vehicle_id,north_m,east_m[,heading_deg,speed_mps,lane,lane_pos_m]

positions in metres in the local NED frame of an origin given separately. The optional columns
(all four or none) carry what a traffic simulator knows: the heading (degrees clockwise from
north), the speed, the lane occupied and the position along it. SUMO FCD output
(``sumo --fcd-output``) gives ``<timestep time=...><vehicle id= x= y= angle= speed= lane= pos=/>``,
with ``x`` east and ``y`` north in metres (network coordinates, used as the local frame after
subtracting ``offset``) and ``angle`` the heading in degrees clockwise from north.

Low-rate or noisy input (SUMO's default 1 Hz) is smoothed with a penalised cubic smoothing spline
(generalised cross-validation), resampled at 10 Hz, and turned into a smooth path plus a monotone
arc-length profile, so that the synthesised specific force and angular rate are sane. Vehicles are
assumed never to reverse: backward steps (smoothing overshoot at abrupt stops) are dropped.
"""

from __future__ import annotations

import csv
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path as FsPath

import numpy as np
import pymap3d
from scipy.interpolate import make_smoothing_spline

from .geometry import Path
from .kinematics import Truth, generate
from .truth import PathProfile

RESAMPLE_RATE = 10.0  #: Hz
MIN_STEP = 0.05  #: points closer than this [m] are merged (standing still)


class TrajectoryError(ValueError):
    """An external trajectory file is invalid; the message names file, line/element and reason."""


@dataclass(frozen=True)
class Track:
    """Raw samples of one vehicle: times [s] and (north, east) [m], sorted by time; where the
    source has them, the heading [rad, clockwise from north], speed [m/s], lane id and position
    along the lane [m] of each sample."""

    vehicle: str
    t: np.ndarray
    ne: np.ndarray
    heading: np.ndarray | None = None
    speed: np.ndarray | None = None
    lane: np.ndarray | None = None
    lane_pos: np.ndarray | None = None

    @property
    def detailed(self) -> bool:
        return self.lane is not None


#: the CSV's optional columns, all or none
DETAIL_COLUMNS = ("heading_deg", "speed_mps", "lane", "lane_pos_m")


def read_csv_tracks(path: str | FsPath) -> dict[str, Track]:
    """Read the documented CSV format."""
    path = FsPath(path)
    rows: dict[str, list[tuple]] = {}
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            need = {"time_s", "vehicle_id", "north_m", "east_m"}
            if reader.fieldnames is None or not need <= set(reader.fieldnames):
                raise TrajectoryError(f"{path}: header must contain {', '.join(sorted(need))}")
            extra = set(DETAIL_COLUMNS) & set(reader.fieldnames)
            if extra and extra != set(DETAIL_COLUMNS):
                raise TrajectoryError(f"{path}: the optional columns {', '.join(DETAIL_COLUMNS)} come all or none "
                                      f"(missing: {', '.join(sorted(set(DETAIL_COLUMNS) - extra))})")
            for i, row in enumerate(reader, start=2):
                try:
                    r = tuple(float(row[k]) for k in ("time_s", "north_m", "east_m"))
                    if extra:
                        r += (np.radians(float(row["heading_deg"])), float(row["speed_mps"]),
                              float(row["lane_pos_m"]), str(row["lane"]))
                except (TypeError, ValueError) as exc:
                    raise TrajectoryError(f"{path}:{i}: {exc}") from exc
                if not all(np.isfinite(r[:-1] if extra else r)):
                    raise TrajectoryError(f"{path}:{i}: non-finite value")
                rows.setdefault(row["vehicle_id"], []).append(r)
    except OSError as exc:
        raise TrajectoryError(f"{path}: cannot read ({exc.strerror})") from exc
    except UnicodeDecodeError:
        raise TrajectoryError(f"{path}: not a CSV file (not UTF-8 text)") from None
    if not rows:
        raise TrajectoryError(f"{path}: no vehicles found")
    return {v: _track(v, r, str(path)) for v, r in rows.items()}


def read_sumo_fcd(path: str | FsPath, offset: tuple[float, float] = (0.0, 0.0)) -> dict[str, Track]:
    """Read SUMO floating-car-data XML (``x`` east, ``y`` north, metres, less ``offset`` (x, y));
    with each sample's heading, speed, lane and lane position where the file has them."""
    path = FsPath(path)
    rows: dict[str, list[tuple]] = {}
    x0, y0 = offset
    try:
        for _, el in ET.iterparse(path, events=("end",)):
            if el.tag != "timestep":
                continue
            try:
                t = float(el.get("time"))
                for v in el.findall("vehicle"):
                    r: tuple = (t, float(v.get("y")) - y0, float(v.get("x")) - x0)
                    if v.get("lane") is not None and v.get("angle") is not None:
                        r += (np.radians(float(v.get("angle"))), float(v.get("speed")), float(v.get("pos")),
                              v.get("lane"))
                    rows.setdefault(v.get("id"), []).append(r)
            except (TypeError, ValueError) as exc:
                raise TrajectoryError(f"{path}: timestep {el.get('time')!r}: bad attribute ({exc})") from exc
            el.clear()
    except ET.ParseError as exc:
        raise TrajectoryError(f"{path}: not valid FCD XML ({exc})") from exc
    except OSError as exc:
        raise TrajectoryError(f"{path}: cannot read ({exc.strerror})") from exc
    if not rows:
        raise TrajectoryError(f"{path}: no vehicles found")
    return {v: _track(v, r, str(path)) for v, r in rows.items()}


def _track(vehicle: str, rows: list[tuple], source: str) -> Track:
    rows = sorted(rows, key=lambda r: r[0])
    if len(rows) < 4:
        raise TrajectoryError(f"{source}: vehicle {vehicle!r} has {len(rows)} samples (need >= 4)")
    if len({len(r) for r in rows}) != 1:
        raise TrajectoryError(f"{source}: vehicle {vehicle!r} has samples with and without lane details")
    a = np.array([r[:3] for r in rows], float)
    if np.any(np.diff(a[:, 0]) <= 0):
        raise TrajectoryError(f"{source}: vehicle {vehicle!r} has repeated time stamps")
    if len(rows[0]) == 3:
        return Track(vehicle, a[:, 0], a[:, 1:3])
    d = np.array([r[3:6] for r in rows], float)
    if np.any(d[:, 1] < 0):
        raise TrajectoryError(f"{source}: vehicle {vehicle!r} has a negative speed")
    return Track(vehicle, a[:, 0], a[:, 1:3], heading=d[:, 0], speed=d[:, 1], lane_pos=d[:, 2],
                 lane=np.array([r[6] for r in rows], dtype=object))


def smooth_track(track: Track) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed (north, east) resampled at 10 Hz: returns ``t`` (m,), ``ne`` (m, 2)."""
    t = track.t
    tt = np.arange(t[0], t[-1] + 1e-9, 1.0 / RESAMPLE_RATE)
    ne = np.column_stack([make_smoothing_spline(t, track.ne[:, i])(tt) for i in range(2)])
    return tt, ne


def profile_from_track(track: Track) -> PathProfile:
    """A smooth path and a monotone arc-length profile for one vehicle."""
    tt, ne = smooth_track(track)
    keep = [0]
    heading: np.ndarray | None = None
    s = np.zeros(len(ne))
    s_last = 0.0  # arc length of the last kept point
    for i in range(1, len(ne)):
        d = ne[i] - ne[keep[-1]]
        dist = float(np.linalg.norm(d))
        # vehicles do not reverse: a step against the direction of travel is smoothing overshoot
        # (e.g. at an abrupt stop in the input) and is not a path point
        forward = heading is None or float(d @ heading) > 0.0
        if dist >= MIN_STEP and forward:
            heading = d / dist
            keep.append(i)
            s_last = s_last + dist
            s[i] = max(s[i - 1], s_last)
        else:
            # between path points: project onto the direction of travel so that the arc length
            # (hence speed) stays continuous at creeping speeds; never decreasing
            ahead = float(d @ heading) if heading is not None else 0.0
            s[i] = max(s[i - 1], s_last + max(ahead, 0.0))
    if len(keep) < 2:  # never moves: a short stub in the initial direction keeps the path valid
        pts = np.vstack([ne[0], ne[0] + [MIN_STEP, 0.0]])
        return PathProfile(Path(pts), tt, np.zeros(len(tt)))
    pts = ne[keep]
    return PathProfile(Path(pts, step=0.5), tt, s)


def truth_from_tracks(tracks: dict[str, Track], origin_llh: tuple[float, float, float],
                      imu_rate: float = 100.0) -> dict[str, Truth]:
    """Truth with consistent IMU increments for every track (origin in radians, metres)."""
    out = {}
    for vid, tr in tracks.items():
        prof = profile_from_track(tr)
        ne0 = prof.path.position(prof.s_knots[0])
        llh0 = pymap3d.ned2geodetic(ne0[0], ne0[1], 0.0, *origin_llh, deg=False)
        duration = float(prof.t_knots[-1] - prof.t_knots[0])
        out[vid] = generate(prof, duration, imu_rate, tuple(float(x) for x in llh0), t0=float(prof.t_knots[0]))
    return out


def write_csv_tracks(tracks: dict[str, Track], path: str | FsPath) -> None:
    """Write tracks in the documented CSV format (with the optional columns where every track
    has them)."""
    detailed = all(tr.detailed for tr in tracks.values())
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(("time_s", "vehicle_id", "north_m", "east_m", *(DETAIL_COLUMNS if detailed else ())))
        for vid, tr in tracks.items():
            for i in range(len(tr.t)):
                row = [f"{tr.t[i]:.3f}", vid, f"{tr.ne[i, 0]:.4f}", f"{tr.ne[i, 1]:.4f}"]
                if detailed:
                    row += [f"{np.degrees(tr.heading[i]):.3f}", f"{tr.speed[i]:.4f}", tr.lane[i],
                            f"{tr.lane_pos[i]:.4f}"]
                w.writerow(row)
