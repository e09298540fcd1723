"""Lane identity from the markings a forward camera sees on either side of the ego lane.

A camera cannot read a lane's name, but it classifies the markings left and right of the ego
lane: a *divider* (white, dashed or solid: another lane of my travel direction lies beyond it)
or a *boundary* (centre line, road edge or kerb: no lane of my direction beyond it). On an
approach of up to three lanes these two classes name the lane (leftmost: boundary/divider,
rightmost: divider/boundary, middle: divider/divider); ADAS cameras report the same as an
"ego lane index". The stop-line fix needs the lane: on a multi-lane approach a GNSS-level
lateral σ (1-2 m) cannot tell lanes 3.5 m apart.

This module is pure: the classes a map implies for each lane (:func:`marking_classes`), and the
majority of a camera's recent reports (:class:`MarkingWindow`). The emulator uses the first for
the truth, the agent for its map.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

UNSEEN = 0  #: the camera reports no class for this side (worn, hidden, inside the junction)
DIVIDER = 1  #: a lane of my travel direction lies beyond this marking
BOUNDARY = 2  #: no lane of my travel direction beyond (centre line, road edge, kerb)
CLASSES = (UNSEEN, DIVIDER, BOUNDARY)


@dataclass(frozen=True)
class LaneEdges:
    """Where a lane's left lane line is and which way it runs.

    Attributes
    ----------
    point : ndarray, shape (2,)
        A point of the left lane line (north, east) [m], near the lane's end.
    direction : ndarray, shape (2,)
        Unit direction of travel (north, east).
    width : float
        Lane width [m].
    """

    point: np.ndarray
    direction: np.ndarray
    width: float


def marking_classes(lanes: dict[str, LaneEdges], parallel_tol: float = math.radians(10.0),
                    offset_tol: float = 0.5, along_tol: float = 60.0) -> dict[str, tuple[int, int]]:
    """The (left, right) marking classes every lane of a map implies.

    Lane B lies right of lane A when both run the same way (within ``parallel_tol`` [rad]),
    B's left lane line is A's right one (B's line ``width_A`` right of A's, within
    ``offset_tol`` [m]) and their reference points are within ``along_tol`` [m] along the road.
    """
    out = {}
    for a, ea in lanes.items():
        right = left = False
        rn = np.array([-ea.direction[1], ea.direction[0]])  # right normal of (north, east)
        for b, eb in lanes.items():
            if b == a or float(ea.direction @ eb.direction) < math.cos(parallel_tol):
                continue
            d = eb.point - ea.point
            if abs(float(ea.direction @ d)) > along_tol:
                continue
            off = float(rn @ d)
            right |= abs(off - ea.width) <= offset_tol
            left |= abs(off + eb.width) <= offset_tol
        out[a] = (DIVIDER if left else BOUNDARY, DIVIDER if right else BOUNDARY)
    return out


def consistent(expected: tuple[int, int], seen: tuple[int, int]) -> bool:
    """Whether a lane with ``expected`` classes agrees with what the camera ``seen``."""
    return all(s == UNSEEN or s == e for e, s in zip(expected, seen))


class MarkingWindow:
    """The camera's recent (left, right) reports and their settled classes.

    A side's class is settled when at least ``min_frames`` reports of the last ``window`` s
    classified it and at least ``agreement`` of them agree; otherwise it is :data:`UNSEEN`.
    Camera errors last for many frames (the same wear or shadow), so one frame proves little.
    """

    def __init__(self, window: float = 2.0, min_frames: int = 5, agreement: float = 0.8) -> None:
        self.window = window
        self.min_frames = min_frames
        self.agreement = agreement
        self._q: deque[tuple[float, int, int]] = deque(maxlen=256)

    def observe(self, t: float, left: int, right: int) -> None:
        """A report at sensor time ``t`` [s]; classes outside :data:`CLASSES` count as unseen."""
        if not math.isfinite(t):
            return
        self._q.append((t, left if left in CLASSES else UNSEEN, right if right in CLASSES else UNSEEN))
        while self._q and self._q[0][0] < t - self.window:
            self._q.popleft()

    def settled(self, t: float, min_frames: int | None = None) -> tuple[int, int]:
        """The settled (left, right) classes at sensor time ``t`` [s]; ``min_frames`` overrides
        the number of classified reports a side needs."""
        recent = [(le, ri) for tq, le, ri in self._q if t - self.window <= tq <= t + 0.5]
        n = self.min_frames if min_frames is None else min_frames
        return self._side([le for le, _ in recent], n), self._side([ri for _, ri in recent], n)

    def _side(self, seen: list[int], min_frames: int) -> int:
        seen = [c for c in seen if c != UNSEEN]
        if len(seen) < min_frames:
            return UNSEEN
        n_div = sum(c == DIVIDER for c in seen)
        for cls, n in ((DIVIDER, n_div), (BOUNDARY, len(seen) - n_div)):
            if n >= self.agreement * len(seen):
                return cls
        return UNSEEN
