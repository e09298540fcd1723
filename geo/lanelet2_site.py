"""Sites as Lanelet2 maps (the lanelet2 package): read a map into a :class:`~geo.site.Site`,
write a site as one.

Lanelet2 keeps a map as OSM XML in latitude and longitude; a projection turns it into metres.
slcp uses the local tangent plane at an origin (Lanelet2's ``LocalCartesianProjector``: x east,
y north), the frame of every site. The origin comes, as in Autoware, from
``map_projector_info.yaml`` beside the map (``projector_type: LocalCartesian`` and
``map_origin`` with ``latitude``, ``longitude`` [deg] and ``altitude`` [m]), or is given.

What is read:

* every lanelet whose ``subtype`` is a road for vehicles (``road``, ``highway``, ``play_street``,
  ``bus_lane`` or none given) becomes a lane: its centre line (midway between its bounds, in the
  direction of travel; Lanelet2's own centre line smooths bends, by several centimetres at a
  bend of a few degrees), its width (the mean distance between its bounds along the centre line), and the
  type and subtype of its bounds as its markings (``"line_thin:dashed"``). Its id is its
  ``slcp:lane`` attribute, else its ``name``, else its Lanelet2 id;
* a stop line is the reference line of a traffic-light, right-of-way or traffic-sign regulatory
  element of the lanelet (Autoware's ``stop_line``). The lane is cut where its centre line
  crosses the stop line, which then lies across its last segment at its end; a stop line that
  the centre line (or its last segment prolonged by up to :data:`STOP_LINE_REACH` m) does not
  cross is left out with a warning. A stop line more than half a degree off the lane's normal
  keeps its slant (``Lane.stop_slant``), which the stop-line fix takes.

What is written: each lane as a lanelet (``subtype road``, one way) with its own left and right
bounds (``line_thin``, ``solid`` unless the lane's markings say otherwise), its id in
``slcp:lane``; each stop line as a ``stop_line`` line string, the reference line of a
``traffic_light`` regulatory element with a traffic light 3 m beyond it, 5 m up.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from .site import Lane, Site, offset_polyline

log = logging.getLogger(__name__)

PROJECTOR_INFO = "map_projector_info.yaml"
#: [m] how far past a lanelet's end its stop line may lie and still be taken
STOP_LINE_REACH = 2.0
ROAD_SUBTYPES = frozenset({"", "road", "highway", "play_street", "bus_lane"})


class SiteMapError(ValueError):
    """A site map cannot be read; the message names the file and the reason."""


def _lanelet2() -> tuple[Any, Any, Any, Any]:
    try:
        import lanelet2
        from lanelet2 import core, io, projection
    except ImportError as exc:  # pragma: no cover - a dependency
        raise SiteMapError(f"Lanelet2 maps need the lanelet2 package ({exc})") from None
    return lanelet2, core, io, projection


def _projector(origin_llh: tuple[float, float, float]) -> Any:
    _, _, io, projection = _lanelet2()
    lat, lon, h = origin_llh
    return projection.LocalCartesianProjector(io.Origin(math.degrees(lat), math.degrees(lon), float(h)))


def read_projector_info(path: Path) -> tuple[float, float, float]:
    """The origin (latitude, longitude [rad], height [m]) of Autoware's ``map_projector_info.yaml``."""
    import yaml

    try:
        info = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise SiteMapError(f"{path}: cannot read ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise SiteMapError(f"{path}: not YAML ({exc})") from None
    kind = info.get("projector_type") if isinstance(info, dict) else None
    if kind != "LocalCartesian":
        raise SiteMapError(f"{path}: projector_type {kind!r}: slcp reads LocalCartesian maps "
                           "(give the origin instead to read the map's latitudes and longitudes in that frame)")
    o = info.get("map_origin")
    try:
        lat, lon, alt = (float(o[k]) for k in ("latitude", "longitude", "altitude"))
    except (TypeError, KeyError, ValueError):
        raise SiteMapError(f"{path}: map_origin must give latitude, longitude [deg] and altitude [m]") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(alt)):
        raise SiteMapError(f"{path}: map_origin ({lat}, {lon}, {alt}) is not a place on Earth")
    return math.radians(lat), math.radians(lon), alt


def write_projector_info(path: Path, origin_llh: tuple[float, float, float]) -> None:
    lat, lon, h = origin_llh
    Path(path).write_text("projector_type: LocalCartesian\nvertical_datum: WGS84\nmap_origin:\n"
                          f"  latitude: {math.degrees(lat):.12f}\n  longitude: {math.degrees(lon):.12f}\n"
                          f"  altitude: {float(h):.4f}\n")


def read_lanelet2(path: Path, origin_llh: tuple[float, float, float] | None = None) -> Site:
    """The site of the Lanelet2 map ``path`` in the frame of ``origin_llh`` [rad, rad, m]
    (default: the ``map_projector_info.yaml`` beside it)."""
    path = Path(path)
    if not path.is_file():
        raise SiteMapError(f"{path}: no such file")
    if origin_llh is None:
        info = path.parent / PROJECTOR_INFO
        if not info.exists():
            raise SiteMapError(f"{path}: no {PROJECTOR_INFO} beside it: give the map's origin")
        origin_llh = read_projector_info(info)
    lanelet2, _, _, _ = _lanelet2()
    try:
        lmap, errors = lanelet2.io.loadRobust(str(path), _projector(origin_llh))
    except Exception as exc:  # noqa: BLE001 - the C++ parser's errors arrive as plain RuntimeErrors
        raise SiteMapError(f"{path}: not a Lanelet2 map ({exc})") from None
    for e in errors[:5]:
        log.warning("%s: %s", path, e)
    lanes: dict[str, Lane] = {}
    for ll in sorted(lmap.laneletLayer, key=lambda x: x.id):  # in the order written
        a = ll.attributes
        if (a["subtype"] if "subtype" in a else "") not in ROAD_SUBTYPES:
            continue
        lane = _lane(ll, path)
        if lane.id in lanes:
            raise SiteMapError(f"{path}: two lanelets are lane {lane.id!r}")
        lanes[lane.id] = lane
    if not lanes:
        raise SiteMapError(f"{path}: no road lanelets")
    lat, lon, h = origin_llh
    return Site((float(lat), float(lon), float(h)), lanes)


def _ne(linestring: Any) -> np.ndarray:
    """A line string's points as (n, 2) north, east [m]."""
    return np.array([(p.y, p.x) for p in linestring], float).reshape(-1, 2)


def _lane(ll: Any, path: Path) -> Lane:
    a = ll.attributes
    lid = next((a[k] for k in ("slcp:lane", "name") if k in a), str(ll.id))
    left, right = _ne(ll.leftBound), _ne(ll.rightBound)
    centre = _distinct(_midline(left, right))
    if len(centre) < 2:
        raise SiteMapError(f"{path}: lanelet {ll.id} has no length")
    width = float(np.mean([_distance(p, left) + _distance(p, right) for p in centre]))
    markings = tuple(":".join(b.attributes[k] for k in ("type", "subtype") if k in b.attributes)
                     for b in (ll.leftBound, ll.rightBound))
    stop = _stop_line(ll)
    cut = _cut_at(centre, stop) if stop is not None else None
    if stop is not None and cut is None:
        log.warning("%s: lanelet %s (lane %s): its stop line does not cross its centre line; left out",
                    path, ll.id, lid)
    if cut is None or stop is None:
        return Lane(lid, centre, width, False, (markings[0], markings[1]))
    cut = _distinct(cut)
    return Lane(lid, cut, width, True, (markings[0], markings[1]), _slant(cut, stop))


#: a stop line within this angle of the lane's normal is taken at right angles [rad]
RIGHT_ANGLE_TOL = math.radians(0.5)


def _slant(centre: np.ndarray, stop: np.ndarray) -> tuple[float, float] | None:
    """The stop line's unit direction (north, east) where it is slanted by more than
    :data:`RIGHT_ANGLE_TOL` from the normal of the lane's last segment, else None."""
    d = centre[-1] - centre[-2]
    d = d / np.linalg.norm(d)
    s = stop[1] - stop[0]
    s = s / np.linalg.norm(s)
    if abs(float(d @ s)) <= math.sin(RIGHT_ANGLE_TOL):
        return None
    return float(s[0]), float(s[1])


def _distinct(p: np.ndarray, tol: float = 1e-4) -> np.ndarray:
    """A polyline without points closer than ``tol`` [m] to the point before (the last kept)."""
    keep = [0]
    for k in range(1, len(p)):
        if np.hypot(*(p[k] - p[keep[-1]])) > tol:
            keep.append(k)
    if len(keep) > 1 and keep[-1] != len(p) - 1:
        keep[-1] = len(p) - 1  # the end stays where it is
    return p[keep]


def _midline(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The line midway between a lanelet's bounds: the mean of their corresponding points, where
    the bounds have as many points, else of points at the same fraction of each bound's length
    (one at every vertex of either)."""
    if len(left) == len(right):
        return np.asarray((left + right) / 2, float)

    def fractions(p: np.ndarray) -> np.ndarray:
        s = np.asarray(np.r_[0.0, np.cumsum(np.hypot(*np.diff(p, axis=0).T))], float)
        return s / s[-1] if s[-1] > 0 else s

    fl, fr = fractions(left), fractions(right)
    f = np.unique(np.r_[fl, fr])

    def at(p: np.ndarray, fp: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(f, fp, p[:, 0]), np.interp(f, fp, p[:, 1])])

    return np.asarray((at(left, fl) + at(right, fr)) / 2, float)


def _stop_line(ll: Any) -> np.ndarray | None:
    for re in ll.regulatoryElements:
        for name in ("stopLine", "refLines"):
            line = getattr(re, name, None)
            if line is None:
                continue
            if name == "refLines":
                if len(line) == 0:
                    continue
                line = line[0]
            pts = _ne(line)
            if len(pts) >= 2:
                return pts[[0, -1]]
    return None


def _distance(p: np.ndarray, poly: np.ndarray) -> float:
    """The distance from point ``p`` to polyline ``poly`` [m]."""
    a, b = poly[:-1], poly[1:]
    d = b - a
    u = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-18), 0.0, 1.0)
    return float(np.min(np.hypot(*(a + u[:, None] * d - p).T)))


def _cut_at(centre: np.ndarray, stop: np.ndarray) -> np.ndarray | None:
    """The centre line up to where it crosses the stop line (the segment ``stop``, prolonged
    across the lane), or its last segment prolonged up to :data:`STOP_LINE_REACH` m; None if
    neither."""
    s0, s1 = stop
    n = np.array([-(s1 - s0)[1], (s1 - s0)[0]])
    n /= np.linalg.norm(n)
    side = (centre - s0) @ n
    for k in range(len(centre) - 1):
        if side[k + 1] == 0.0:  # a vertex on the line
            return centre[: k + 2]
        if side[k] != 0.0 and np.sign(side[k]) != np.sign(side[k + 1]):
            f = side[k] / (side[k] - side[k + 1])
            return np.vstack([centre[: k + 1], centre[k] + f * (centre[k + 1] - centre[k])])
    d = centre[-1] - centre[-2]
    d /= np.linalg.norm(d)
    along = d @ n
    if abs(along) > 1e-9:
        reach = -side[-1] / along
        if 0.0 <= reach <= STOP_LINE_REACH:
            return np.vstack([centre, centre[-1] + reach * d])
    return None


def write_lanelet2(site: Site, path: Path) -> None:
    """Write ``site`` as a Lanelet2 map at ``path`` (OSM), and its origin to the
    ``map_projector_info.yaml`` beside it."""
    lanelet2, core, _, _ = _lanelet2()
    path = Path(path)
    lmap = core.LaneletMap()

    def line(ne: np.ndarray, attrs: dict[str, str], z: float = 0.0) -> Any:
        return core.LineString3d(core.getId(), [core.Point3d(core.getId(), float(e), float(n), z) for n, e in ne],
                                 core.AttributeMap(attrs))

    for lane in site.lanes.values():
        c = np.asarray(lane.centerline, float)
        bounds = [line(offset_polyline(c, side * lane.width / 2), _marking(m))
                  for side, m in ((-1, lane.markings[0]), (1, lane.markings[1]))]
        ll = core.Lanelet(core.getId(), bounds[0], bounds[1], core.AttributeMap({
            "type": "lanelet", "subtype": "road", "location": "urban", "one_way": "yes",
            "participant:vehicle": "yes", "slcp:lane": lane.id}))
        if lane.stop_line:
            ends = lane.stop_line_ends()
            d = c[-1] - c[-2]
            d /= np.linalg.norm(d)
            light = line(ends + 3.0 * d, {"type": "traffic_light", "subtype": "red_yellow_green"}, z=5.0)
            regulation = core.AttributeMap({"type": "regulatory_element", "subtype": "traffic_light"})
            ll.addRegulatoryElement(core.TrafficLight(core.getId(), regulation, [light],
                                                      line(ends, {"type": "stop_line"})))
        lmap.add(ll)
    path.parent.mkdir(parents=True, exist_ok=True)
    lanelet2.io.write(str(path), lmap, _projector(site.origin_llh))
    write_projector_info(path.parent / PROJECTOR_INFO, site.origin_llh)


def _marking(m: str) -> dict[str, str]:
    """A lane's marking (``"type:subtype"``) as a bound's attributes (default a thin solid line)."""
    kind, _, sub = m.partition(":")
    if not kind:
        return {"type": "line_thin", "subtype": "solid"}
    return {"type": kind, "subtype": sub} if sub else {"type": kind}
