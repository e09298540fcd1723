"""A SUMO network's site: its lanes, the stop lines of its signalised approaches and their
signal plans, in the local frame of the junction a scenario is centred on.

SUMO's network coordinates are metres, ``x`` east and ``y`` north; the site's frame is north,
east from ``centre`` (the signalised junction, unless given). A lane ends in a stop line where
one of its connections is controlled by a traffic light: SUMO draws the stop line at the lane's
end, where the junction begins. Internal (junction) lanes are not site lanes: the turns across a
junction are not lanes an agent is constrained to.

Needs ``sumolib`` (``pip install 'slcp[sumo]'``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slcp.geo.site import Lane


class SumoNetworkError(ValueError):
    """A SUMO network cannot be used as a site (the message names the file and the reason)."""


def _sumolib():
    try:
        import sumolib
    except ImportError:
        raise SumoNetworkError("reading SUMO networks needs sumolib: pip install 'slcp[sumo]'") from None
    return sumolib


@dataclass(frozen=True)
class SumoSite:
    """The site of a SUMO network: lanes by SUMO lane id, the network point ``centre`` (x, y)
    [m] the frame is centred on, and, per signalised approach lane, its green windows within the
    cycle of its traffic light ([s], from the start of the program)."""

    lanes: dict[str, Lane]
    centre: tuple[float, float]
    cycle: float
    green: dict[str, list[tuple[float, float]]]
    tls: str


def read_net(path: str | Path):
    """The network, with internal lanes (a :class:`SumoNetworkError` naming the file if it is not one)."""
    sumolib = _sumolib()
    path = Path(path)
    if not path.is_file():
        raise SumoNetworkError(f"{path}: no such file")
    try:
        return sumolib.net.readNet(str(path), withInternal=True, withLatestPrograms=True)
    except Exception as exc:  # sumolib raises whatever its XML parser raises
        raise SumoNetworkError(f"{path}: not a SUMO network ({exc})") from exc


def _green_windows(tls, program) -> dict[str, list[tuple[float, float]]]:
    """Per incoming lane: the parts of the cycle when one of its links has green (G or g)."""
    links: dict[str, set[int]] = {}
    for inc, _out, idx in tls.getConnections():
        links.setdefault(inc.getID(), set()).add(int(idx))
    out: dict[str, list[tuple[float, float]]] = {}
    for lane, idx in links.items():
        t, windows = 0.0, []
        for ph in program.getPhases():
            green = any(ph.state[i] in "Gg" for i in idx if i < len(ph.state))
            if green and windows and abs(windows[-1][1] - t) < 1e-9:
                windows[-1] = (windows[-1][0], t + ph.duration)
            elif green:
                windows.append((t, t + ph.duration))
            t += ph.duration
        out[lane] = windows
    return out


def sumo_site(path: str | Path, centre: tuple[float, float] | None = None) -> SumoSite:
    """The site of the network in ``path`` (module docstring). With several traffic lights,
    the one nearest ``centre`` (or the network's middle) is the site's junction."""
    net = read_net(path)
    tlss = list(net.getTrafficLights())
    if not tlss:
        raise SumoNetworkError(f"{path}: the network has no traffic light (netgenerate --tls.guess adds them)")
    (x0, y0), (x1, y1) = net.getBBoxXY()
    mid = centre if centre is not None else (0.5 * (x0 + x1), 0.5 * (y0 + y1))

    def tls_xy(t) -> np.ndarray:
        return np.mean([c[0].getEdge().getToNode().getCoord() for c in t.getConnections()], axis=0)

    tls = min(tlss, key=lambda t: float(np.hypot(*(tls_xy(t) - np.asarray(mid)))))
    cx, cy = (float(v) for v in (centre if centre is not None else tls_xy(tls)))
    controlled = {inc.getID() for inc, _out, _i in tls.getConnections()}
    lanes: dict[str, Lane] = {}
    for edge in net.getEdges(withInternal=False):
        for ln in edge.getLanes():
            xy = np.asarray(ln.getShape(), float)[:, :2]
            ne = np.column_stack([xy[:, 1] - cy, xy[:, 0] - cx])
            keep = np.concatenate([[True], np.linalg.norm(np.diff(ne, axis=0), axis=1) > 1e-6])
            if keep.sum() < 2:
                continue
            lanes[ln.getID()] = Lane(ln.getID(), ne[keep], float(ln.getWidth()), ln.getID() in controlled)
    programs = tls.getPrograms()
    if not programs:
        raise SumoNetworkError(f"{path}: traffic light {tls.getID()!r} has no program")
    program = next(iter(programs.values()))  # the one SUMO runs by default
    cycle = float(sum(ph.duration for ph in program.getPhases()))
    return SumoSite(lanes, (cx, cy), cycle, _green_windows(tls, program), tls.getID())
