"""Which lane of the map a vehicle drives in, from its own estimate and its camera (no truth).

The lane-keeping constraint (:mod:`agent.nav.measurements.lane_line`) pulls the estimate
across the lane onto the lane's offset: in the wrong lane it pulls it a lane width off. So the
association is conservative, like the first-stopped decision:

1. the estimated heading runs with a lane segment within ``heading_tol``, and its σ is at most
   that: a vehicle turning inside the junction is left alone (at 10° into a turn of 10 m
   radius it stands 0.15 m off the lane's line), and so is one whose heading is not known (a
   vehicle that starts standing, whose yaw may point down the oncoming lane). A tolerance a
   third as wide keeps vehicles standing in a queue, whose yaw σ grows, out of their lane;
2. the estimate lies across the segment no farther outside the lane than ``lane_k_sigma`` of
   its lateral σ, and along it no farther beyond its ends than as many σ along it (a queue head
   stands at the lane's end, and an along-track error of metres put it into the junction: its
   lane, lost for 2 s, was redrawn as it took the stop line); beyond a lane's end, only a
   vehicle that has not turned keeps the heading;
3. if several lanes match (lanes of one direction side by side, a lateral σ comparable to the
   lane width), the camera's settled marking classes must name exactly one of them
   (:mod:`geo.lane_markings`); otherwise there is no association;
4. except that the lane the vehicle keeps already (``current``) stays its lane while it still
   matches 1-2 and the markings do not contradict it: a vehicle leaves its lane by crossing a
   line, not by its estimate growing wider. Without this, a queue's cooperative updates, which
   widen the estimate across the lane (covariance intersection inflates every shared
   direction; a range along the queue shrinks only one), made the lane ambiguous, the rows
   stopped, and the lateral σ grew unchecked.
   A lane row refused by its χ² gate releases the lane
   (:meth:`agent.methods.MethodFilter.lane_line`).

Pure: numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slcp.geo.lane_markings import UNSEEN, LaneEdges, consistent, marking_classes

from .nav.measurements.stop_line import Line2D


@dataclass(frozen=True)
class LaneSegment:
    """One straight piece of a lane's left lane line.

    Attributes
    ----------
    lane : str
        Lane id.
    left_line : Line2D
        The left lane line, its point at the piece's start, directed along travel.
    length : float
        Length of the piece [m].
    width : float
        Lane width [m].
    """

    lane: str
    left_line: Line2D
    length: float
    width: float


@dataclass(frozen=True)
class LaneMatch:
    lane: str
    left_line: Line2D


def _left_line_pieces(lane: str, centerline: np.ndarray, width: float) -> list[LaneSegment]:
    out = []
    c = np.asarray(centerline, float)
    for a, b in zip(c[:-1], c[1:]):
        d = b - a
        length = float(np.hypot(*d))
        if length < 1e-6:
            continue
        centre = Line2D(tuple(a), tuple(d))
        left = a - centre.right_normal * (width / 2.0)
        out.append(LaneSegment(lane, Line2D(tuple(left), centre.direction), length, width))
    return out


class LaneMap:
    """Every lane of a site: centre-line polylines (north, east) [m] in the map frame and widths.

    Parameters
    ----------
    lanes : dict
        Lane id -> (centre line, shape (k, 2), in the direction of travel; width [m]).
    heading_tol : float
        Largest difference between the estimated heading and the segment's [rad].
    lane_k_sigma : float
        How many lateral σ the estimate may stand outside the lane [σ].
    """

    def __init__(self, lanes: dict[str, tuple[np.ndarray, float]], heading_tol: float = math.radians(10.0),
                 lane_k_sigma: float = 3.0) -> None:
        self.heading_tol = heading_tol
        self.lane_k_sigma = lane_k_sigma
        self.segments: list[LaneSegment] = []
        edges = {}
        for lid, (cl, width) in lanes.items():
            cl = np.asarray(cl, float)
            if cl.ndim != 2 or cl.shape[0] < 2 or cl.shape[1] != 2 or not np.all(np.isfinite(cl)):
                raise ValueError(f"lane {lid!r}: centre line must be at least two finite (north, east) points")
            if not width > 0.0:
                raise ValueError(f"lane {lid!r}: width must be > 0, got {width}")
            pieces = _left_line_pieces(lid, cl, float(width))
            if not pieces:
                raise ValueError(f"lane {lid!r}: centre line has no length")
            self.segments.extend(pieces)
            last = pieces[-1]
            end = np.asarray(last.left_line.point) + last.length * np.asarray(last.left_line.direction)
            edges[lid] = LaneEdges(end, np.asarray(last.left_line.direction), float(width))
        #: (left, right) marking classes each lane implies
        self.marks = marking_classes(edges)
        self._start = np.array([s.left_line.point for s in self.segments]).reshape(-1, 2)
        self._dir = np.array([s.left_line.direction for s in self.segments]).reshape(-1, 2)
        self._right = np.column_stack([-self._dir[:, 1], self._dir[:, 0]])  # right normals
        self._len = np.array([s.length for s in self.segments])
        self._width = np.array([s.width for s in self.segments])
        self._heading = np.arctan2(self._dir[:, 1], self._dir[:, 0])

    def left_line_at(self, lane: str, ne: np.ndarray) -> Line2D:
        """The left lane line of ``lane`` on its piece nearest to ``ne`` (north, east) [m]."""
        best, line = math.inf, None
        for seg in self.segments:
            if seg.lane != lane:
                continue
            d = np.asarray(ne, float) - np.asarray(seg.left_line.point)
            u = np.asarray(seg.left_line.direction)
            a = min(max(float(u @ d), 0.0), seg.length)
            dist = float(np.hypot(*(d - a * u)))
            if dist < best:
                best, line = dist, seg.left_line
        if line is None:
            raise KeyError(f"no lane {lane!r} in the map")
        return line

    def locate(self, ne: np.ndarray, cov_ne: np.ndarray, yaw: float,
               markings: tuple[int, int] = (UNSEEN, UNSEEN), yaw_sigma: float = 0.0,
               current: str | None = None) -> LaneMatch | None:
        """The lane the vehicle drives in, or None if that is not certain.

        Parameters
        ----------
        ne : ndarray, shape (2,)
            Estimated reference-point position (north, east) [m], map frame.
        cov_ne : ndarray, shape (2, 2)
            Its covariance [m²].
        yaw : float
            Estimated heading [rad], clockwise from north.
        markings : tuple of int
            The camera's settled (left, right) marking classes.
        yaw_sigma : float
            σ of the heading [rad].
        current : str, optional
            The lane the vehicle keeps now: kept while it matches (rule 4).
        """
        if not self.segments or not yaw_sigma <= self.heading_tol:
            return None
        d = np.asarray(ne, float)[None, :] - self._start
        along = np.einsum("ij,ij->i", d, self._dir)
        right_n = self._right
        right = np.einsum("ij,ij->i", d, right_n)
        c = np.asarray(cov_ne, float)
        k = self.lane_k_sigma * np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", right_n, c, right_n), 0.0))
        k_along = self.lane_k_sigma * np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", self._dir, c, self._dir), 0.0))
        dyaw = np.abs((yaw - self._heading + math.pi) % (2.0 * math.pi) - math.pi)
        ok = ((dyaw <= self.heading_tol) & (along >= -k_along) & (along <= self._len + k_along)
              & (right >= -k) & (right <= self._width + k))
        hits = {self.segments[i].lane: self.segments[i] for i in np.flatnonzero(ok)}
        if len(hits) > 1 and current in hits and consistent(self.marks[current], markings):
            hits = {current: hits[current]}
        if len(hits) > 1:
            hits = {lid: s for lid, s in hits.items() if consistent(self.marks[lid], markings)}
        if len(hits) != 1:
            return None
        seg = next(iter(hits.values()))
        return LaneMatch(seg.lane, seg.left_line)

