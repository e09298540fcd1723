"""A fleet, live, in Foxglove: a WebSocket server speaking Foxglove's protocol (the foxglove-sdk
package), fed with every estimate and diagnostics message the recorder takes.

``slcp run --view`` serves the run's own fleet; ``slcp view --connect ENDPOINT`` a deployed one,
through its router (with ``--fleet DIR``, as the fleet's ``recorder`` identity). Open Foxglove
and connect to ``ws://127.0.0.1:<port>``. Topics, per vehicle ``V`` and method ``M``:

=============================  ============================================================
``/slcp/V/M/fix``              ``foxglove.LocationFix``: latitude and longitude [deg], height,
                               position covariance (east, north, up) [m²], heading [rad,
                               clockwise from north], velocity (east, north, up) [m/s], the
                               first-stopped claim in ``metadata``; the Map panel draws it
``/slcp/diagnostics``          JSON: one object per message, ``source``, ``t``, ``counters``,
                               ``status``
``/slcp/scene``                ``foxglove.SceneUpdate`` in ``map`` (east, north, up of the
                               site's origin; the 3D panel draws it): the lanes' centre lines
                               and stop lines (entity ``site``, sent again every second for
                               clients that join late), and five times a second each
                               vehicle's estimate of the best method running (SL-CP, CP, SL-SP,
                               SP) with its 95 % ellipse, an arrow along its heading and its
                               name, red when it claims to be first stopped (``vehicles``), and
                               the UWB links measured in the last second (``uwb_links``)
=============================  ============================================================

Messages are logged with the sensor time of the run [ns]. The server listens on loopback unless
told otherwise.
"""

from __future__ import annotations

import json
import logging
import math
import time
from typing import Any

import numpy as np

from slcp.transport.messages import Diagnostics, Estimate, Message

from .live_map import UWB_KEYS, LiveMapState
from .mcap_recording import log_time_ns, ned_to_enu_cov, topic_name

log = logging.getLogger(__name__)

DIAG_SCHEMA = {"type": "object", "properties": {
    "source": {"type": "string"}, "t": {"type": "number"},
    "counters": {"type": "object", "additionalProperties": {"type": "integer"}},
    "status": {"type": "object"}}}


class FoxgloveSink:
    """A Foxglove WebSocket server on ``host:port`` (port 0: any free one, see :attr:`port`)
    that publishes what it is given (a recorder's sink: ``write(m)``, ``close()``)."""

    observe_keys = UWB_KEYS

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "slcp", lanes=(),
                 origin_llh: tuple[float, float, float] | None = None) -> None:
        import foxglove
        from foxglove.channels import SceneUpdateChannel

        self._fg = foxglove
        self.ctx = foxglove.Context()
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port, context=self.ctx)
        except RuntimeError as exc:  # the SDK's FoxgloveError, e.g. the port taken
            raise OSError(f"cannot serve the Foxglove view on {host}:{port}: {exc}") from None
        self.port: int = self.server.port
        self._fix: dict[str, Any] = {}
        self._diag = foxglove.Channel("/slcp/diagnostics", context=self.ctx, message_encoding="json",
                                      schema=foxglove.Schema(name="slcp.Diagnostics", encoding="jsonschema",
                                                             data=json.dumps(DIAG_SCHEMA).encode()))
        self._scene = SceneUpdateChannel("/slcp/scene", context=self.ctx)
        self.state = LiveMapState(lanes, origin_llh)  #: the scene's estimates, links and site
        self._next_scene = self._next_site = 0.0
        # the one line a user needs to connect (the port may have been picked here)
        log.warning("Foxglove view: connect Foxglove to ws://%s:%d", host, self.port)

    def write(self, m: Message) -> None:
        ns = log_time_ns(m.t)
        if isinstance(m, Estimate):
            self._estimate(m, ns)
            self.state.write(m)
            now = time.monotonic()
            if now >= self._next_scene:
                self._next_scene = now + SCENE_PERIOD_S
                self._send_scene(m.t, ns, site=now >= self._next_site)
                if now >= self._next_site:
                    self._next_site = now + SITE_PERIOD_S
        elif isinstance(m, Diagnostics):
            self._diag.log({"source": m.source, "t": m.t, "counters": m.counters, "status": m.status}, log_time=ns)

    def _estimate(self, e: Estimate, ns: int) -> None:
        from foxglove.channels import LocationFixChannel
        from foxglove.messages import LocationFix, Timestamp, Vector3
        from foxglove.messages import LocationFixPositionCovarianceType as CovType

        topic = topic_name(e.vehicle, e.method, "fix")
        ch = self._fix.get(topic)
        if ch is None:
            ch = self._fix[topic] = LocationFixChannel(topic, context=self.ctx)
        c = ned_to_enu_cov(e.cov_pos)
        vn, ve, vd = (float(x) for x in e.v_ned)
        ch.log(LocationFix(timestamp=Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000),
                           frame_id=f"{e.vehicle}/{e.method}", latitude=math.degrees(float(e.llh[0])),
                           longitude=math.degrees(float(e.llh[1])), altitude=float(e.llh[2]),
                           position_covariance=c.ravel().tolist(), position_covariance_type=CovType.Known,
                           heading=float(e.rpy[2]) % (2 * math.pi), velocity=Vector3(x=ve, y=vn, z=-vd),
                           metadata=[_kv("first_stopped", str(bool(e.first_stopped)).lower())]),
               log_time=ns)

    def observe(self, m: Message) -> None:
        """A UWB round or range (for the scene's links)."""
        self.state.observe(m)

    def _send_scene(self, t: float, ns: int, site: bool) -> None:
        shown = self.state.shown_method()
        rows = self.state.latest(shown) if shown is not None else {}
        entities = [self._vehicles(ns, rows), self._uwb_links(t, ns, rows)]
        if site:
            entities.append(self._site(ns))
        self._scene.log(self._fg.messages.SceneUpdate(entities=entities), log_time=ns)

    def _site(self, ns: int):
        lines = []
        for ln in self.state.lanes:
            lines.append(_line([(e, n) for n, e in ln.centre], 0.15, (0.6, 0.6, 0.6, 1.0)))
            if ln.stop_line is not None:
                lines.append(_line([(e, n) for n, e in ln.stop_line], 0.4, (1.0, 1.0, 1.0, 1.0)))
        return _entity("site", ns, lines=lines)

    def _vehicles(self, ns: int, rows: dict[str, Estimate]):
        from foxglove.messages import ArrowPrimitive, TextPrimitive

        lines, arrows, texts = [], [], []
        for v, e in sorted(rows.items()):
            east, north = self.state.enu(e.llh)  # the map frame: the site's, or the first estimate's
            rgb = (0.85, 0.1, 0.1, 1.0) if e.first_stopped else (0.1, 0.45, 0.85, 1.0)
            c = np.asarray(e.cov_pos, float)
            lines.append(_line(_ellipse(east, north, c[1, 1], c[0, 1], c[0, 0]), 0.08, rgb))
            yaw = math.pi / 2 - float(e.rpy[2])  # from east, anticlockwise
            arrows.append(ArrowPrimitive(pose=_pose(east, north, yaw), shaft_length=2.5, shaft_diameter=0.3,
                                         head_length=1.0, head_diameter=0.8, color=_color(rgb)))
            texts.append(TextPrimitive(pose=_pose(east + 1.5, north + 1.5, 0.0), billboard=True, font_size=14.0,
                                       scale_invariant=True, color=_color((0.1, 0.1, 0.1, 1.0)), text=v))
        return _entity("vehicles", ns, lines=lines, arrows=arrows, texts=texts)

    def _uwb_links(self, t: float, ns: int, rows: dict[str, Estimate]):
        lines = []
        for a, b in self.state.links_at(t):
            if a in rows and b in rows:
                lines.append(_line([self.state.enu(rows[a].llh), self.state.enu(rows[b].llh)], 0.1,
                                   (0.96, 0.49, 0.0, 1.0)))
        return _entity("uwb_links", ns, lines=lines)

    def close(self) -> None:
        self.server.stop()


#: [s] of wall time between scenes, and between sends of the site
SCENE_PERIOD_S, SITE_PERIOD_S = 0.2, 1.0
#: 95 % of a 2-D Gaussian lies within this many σ (the square root of χ²₂'s 95 % quantile)
K95 = math.sqrt(5.991464547107979)


def _ellipse(east: float, north: float, ee: float, en: float, nn: float, n: int = 36) -> list[tuple[float, float]]:
    """The 95 % ellipse of an east, north covariance, as a closed polyline."""
    vals, vecs = np.linalg.eigh(np.array([[ee, en], [en, nn]]))
    axes = vecs * (K95 * np.sqrt(np.maximum(vals, 0.0)))
    a = np.linspace(0.0, 2 * math.pi, n + 1)
    pts = np.array([east, north]) + np.cos(a)[:, None] * axes[:, 0] + np.sin(a)[:, None] * axes[:, 1]
    return [(float(x), float(y)) for x, y in pts]


def _color(rgba):
    from foxglove.messages import Color

    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _pose(east: float, north: float, yaw: float):
    from foxglove.messages import Pose, Quaternion, Vector3

    return Pose(position=Vector3(x=east, y=north, z=0.0),
                orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


def _line(points, thickness: float, rgba):
    from foxglove.messages import LinePrimitive, LinePrimitiveLineType, Point3

    return LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=_pose(0.0, 0.0, 0.0), thickness=thickness,
                         scale_invariant=False, points=[Point3(x=x, y=y, z=0.0) for x, y in points],
                         color=_color(rgba))


def _entity(name: str, ns: int, **primitives):
    from foxglove.messages import Duration, SceneEntity, Timestamp

    return SceneEntity(timestamp=Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000), frame_id="map",
                       id=name, lifetime=Duration(sec=0, nsec=0), frame_locked=False, **primitives)


def _kv(key: str, value: str):
    from foxglove.messages import KeyValuePair

    return KeyValuePair(key=key, value=value)
