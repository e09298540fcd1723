"""A site's shapes for drawing: each lane's centre line and, where it ends at one, its stop line,
in the local north, east frame of the scenario's origin [m]. The bag's site markers and the
live map draw the same shapes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LaneShape:
    id: str
    centre: np.ndarray  #: (n, 2) north, east [m]
    width: float  #: [m]
    stop_line: np.ndarray | None  #: (2, 2) its two ends, north, east [m], or None


def lane_shapes(lanes) -> list[LaneShape]:
    """The shapes of ``lanes`` (:class:`geo.site.Lane`)."""
    out = []
    for ln in lanes:
        c = np.asarray(ln.centerline, float)
        stop = ln.stop_line_ends() if ln.stop_line else None
        out.append(LaneShape(str(ln.id), c, float(ln.width), stop))
    return out
