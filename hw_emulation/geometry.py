"""Planar path geometry in the map frame (north, east in metres).

A :class:`Path` is a polyline resampled by arc length with a smooth heading function, so that a
vehicle moving along it has continuous heading and yaw rate. Turns between lanes are cubic Bézier
curves tangent to both lanes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def polyline_length(points: np.ndarray) -> float:
    """Total length [m] of a polyline of shape (n, 2)."""
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))


def bezier_turn(p0: np.ndarray, h0: float, p1: np.ndarray, h1: float, n: int = 40) -> np.ndarray:
    """Cubic Bézier from ``p0`` heading ``h0`` to ``p1`` heading ``h1`` [rad], shape (n, 2)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    k = 0.55 * np.linalg.norm(p1 - p0)
    c0 = p0 + k * np.array([math.cos(h0), math.sin(h0)])
    c1 = p1 - k * np.array([math.cos(h1), math.sin(h1)])
    u = np.linspace(0.0, 1.0, n)[:, None]
    return (1 - u) ** 3 * p0 + 3 * (1 - u) ** 2 * u * c0 + 3 * (1 - u) * u**2 * c1 + u**3 * p1


@dataclass
class Path:
    """A route through the map, parametrised by arc length.

    Parameters
    ----------
    points : ndarray, shape (n, 2)
        Polyline vertices (north, east) [m]; consecutive duplicates are removed.
    step : float
        Resampling step [m] for the heading spline.
    smooth : bool
        Smooth the chord headings (penalised spline; for densely sampled smooth curves, whose
        chord headings are stair-stepped), else interpolate them (monotone cubic, no overshoot:
        for a polyline the path must pass through, such as a traffic simulator's samples; the
        integrated heading then keeps within about ``step`` x the turn at a vertex / 8 of it).
    """

    points: np.ndarray
    step: float = 0.5
    smooth: bool = True
    length: float = field(init=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.points, float)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9])
        p = p[keep]
        if len(p) < 2:
            raise ValueError("a path needs at least two distinct points")
        seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(s[-1])
        m = max(4, int(math.ceil(self.length / self.step)) + 1)
        ss = np.linspace(0.0, self.length, m)
        xy = np.column_stack([np.interp(ss, s, p[:, 0]), np.interp(ss, s, p[:, 1])])
        # heading of each chord, smoothed by a penalised cubic spline (GCV): chord headings of a
        # densely sampled curve are stair-stepped, and an interpolating spline would ring on them
        d = np.diff(xy, axis=0)
        hd = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        mid = 0.5 * (ss[1:] + ss[:-1])
        # deferred: an agent loads its site map from this module and needs no splines
        from scipy.interpolate import CubicSpline

        from .smoothing_cache import gcv_smoothing_spline

        if np.ptp(hd) < 1e-12:
            self._heading = CubicSpline(mid[[0, -1]], hd[[0, -1]], extrapolate=True)
        elif not self.smooth:
            from scipy.interpolate import PchipInterpolator

            self._heading = PchipInterpolator(mid, hd, extrapolate=True)
        else:
            self._heading = gcv_smoothing_spline(mid, hd)
        self._heading_rate = self._heading.derivative(1)
        self._s_vertices = s
        self._vertices = p
        self.points = p

    def heading(self, s: np.ndarray) -> np.ndarray:
        """Heading [rad, clockwise from north] at arc length ``s``."""
        return self._heading(np.clip(s, 0.0, self.length))

    def curvature(self, s: np.ndarray) -> np.ndarray:
        """dHeading/ds [1/m] (zero beyond the ends)."""
        s = np.asarray(s, float)
        inside = (s >= 0.0) & (s <= self.length)
        return np.where(inside, self._heading_rate(np.clip(s, 0.0, self.length)), 0.0)

    def position(self, s: np.ndarray) -> np.ndarray:
        """Point(s) (north, east) on the polyline at arc length ``s``, shape (..., 2)."""
        s = np.clip(np.asarray(s, float), 0.0, self.length)
        return np.stack([np.interp(s, self._s_vertices, self._vertices[:, 0]),
                         np.interp(s, self._s_vertices, self._vertices[:, 1])], axis=-1)
