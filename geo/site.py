"""A site: the lanes and stop lines of an intersection in the local frame of its origin.

The one description of a site that the emulator, the agents and the map formats share: a
scenario's ``[[lanes]]`` (:mod:`hw_emulation.scenario`) and a Lanelet2 map
(:mod:`geo.lanelet2_site`) both become a :class:`Site`, and an agent's stop-line fixes and
lane constraint are built from one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def offset_polyline(points: np.ndarray, offset: float) -> np.ndarray:
    """Polyline shifted ``offset`` metres to the right of its direction of travel (NE frame)."""
    p = np.asarray(points, float)
    d = np.diff(p, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    right = np.column_stack([-d[:, 1], d[:, 0]])
    # per-vertex normal: average of adjacent segment normals
    nrm = np.vstack([right[:1], 0.5 * (right[:-1] + right[1:]), right[-1:]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return p + offset * nrm


@dataclass(frozen=True)
class Lane:
    id: str
    centerline: np.ndarray  #: (n, 2) north, east [m], in the direction of travel
    width: float  #: [m]
    stop_line: bool  #: a stop line across the lane at the end of its centre-line
    #: the painted lines on its left and right, as a map names them (e.g. ``"line_thin:dashed"``;
    #: "" when not known)
    markings: tuple[str, str] = ("", "")
    #: the stop line's direction (north, east; unit) where it is not at right angles to the lane
    #: (None: at right angles); it crosses the centre line at the lane's end either way
    stop_slant: tuple[float, float] | None = None

    @property
    def end_heading(self) -> float:
        d = self.centerline[-1] - self.centerline[-2]
        return math.atan2(d[1], d[0])

    @property
    def start_heading(self) -> float:
        d = self.centerline[1] - self.centerline[0]
        return math.atan2(d[1], d[0])

    def end_left_line(self) -> tuple[np.ndarray, np.ndarray]:
        """The left lane line at the lane's end: its end point (north, east) [m], (2,), and the
        unit direction of travel of the last centre-line segment, (2,)."""
        c = np.asarray(self.centerline[-2:], float)
        d = (c[1] - c[0]) / np.hypot(*(c[1] - c[0]))
        return offset_polyline(c, -self.width / 2)[-1], d

    def stop_line_ends(self) -> np.ndarray:
        """The stop line's two ends, left then right (north, east) [m], (2, 2): where it meets the
        lines a half lane width either side of the last centre-line segment, through the
        centre line's end (at right angles to it, or along :attr:`stop_slant`)."""
        left, d = self.end_left_line()
        end = np.asarray(self.centerline[-1], float)
        if self.stop_slant is None:
            return np.array([left, 2 * end - left])
        s = np.asarray(self.stop_slant, float)
        s = s if float(s @ (left - end)) >= 0.0 else -s  # pointing to the left of travel
        half = (self.width / 2) / abs(float(d[0] * s[1] - d[1] * s[0]))
        return np.array([end + half * s, end - half * s])


@dataclass(frozen=True)
class Site:
    """Lanes (by id) in the local north, east frame of ``origin_llh`` (latitude, longitude
    [rad], height [m]): the tangent plane at the origin (:func:`pymap3d.geodetic2ned`)."""

    origin_llh: tuple[float, float, float]
    lanes: dict[str, Lane] = field(default_factory=dict)

    @property
    def stop_lanes(self) -> list[Lane]:
        return [ln for ln in self.lanes.values() if ln.stop_line]
