"""A fleet on a map in the browser, live: a local web page and the WebSocket that feeds it.

``slcp run --view`` serves the run's own fleet; ``slcp view --connect ENDPOINT`` a deployed one,
through its router. Open ``http://127.0.0.1:<port>/``. The page (``web/live_map.html``, one
file with its script and styles: nothing is fetched from elsewhere, so it works offline) draws
the site's lanes and stop lines, each vehicle's estimate with its direction of travel and 95 %
error ellipse, its track, its truth in emulated runs, the UWB links measured in the last second,
and the first-stopped claims; a table gives each vehicle's error (emulated runs) or σ.

The WebSocket (``/ws``) sends JSON: once a ``site`` message, then a ``state`` message every
1/``rate_hz`` s, both in the local east, north frame of the site's origin [m]:

* ``site``: ``origin`` (latitude, longitude [deg], height [m]), ``lanes`` (``id``, ``centre``
  [[e, n], ...], ``width``, ``stop_line`` [[e, n], [e, n]] or null), ``truth_tracks`` (vehicle
  -> [[e, n], ...] at 1 Hz, emulated runs);
* ``state``: ``t`` (the newest estimate's time [s]), ``estimates`` (one per vehicle and method:
  ``vehicle``, ``method``, ``t``, ``e``, ``n``, ``cov`` [ee, en, nn] [m²], ``heading`` [rad,
  clockwise from north], ``speed`` [m/s], ``first_stopped``, ``sigma_h`` [m]; with the truth,
  ``truth`` [e, n] and ``err_h`` [m], the horizontal error scored as the run's report scores it),
  ``links`` ([a, b] pairs).

The server listens on loopback unless told otherwise and answers a WebSocket only to its own
page (the ``Origin`` header), so another web site open in the same browser cannot read the fleet.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from importlib import resources
from typing import Any

import numpy as np

from slcp.transport import keys
from slcp.transport.messages import Estimate, Message, UwbRange, UwbRound

from .ros2_cdr import LocalEnu
from .site_shapes import lane_shapes

log = logging.getLogger(__name__)

#: [s] a UWB link is drawn this long after its last range
LINK_TTL_S = 1.0
#: at most this many (vehicle, method) estimates and UWB pairs are kept: on an open bus anyone
#: can invent names (the ones beyond are counted in ``LiveMapState.refused``)
MAX_ROWS, MAX_LINKS = 1024, 8192
#: what a live view observes besides the recording: the UWB rounds (its links)
UWB_KEYS = (keys.ROOT + "/uwb/*",)
#: the method a view shows first: the first of these the fleet runs
SHOWN_METHODS = ("SL-CP", "CP", "SL-SP", "SP")


def _en(p_ne) -> list[float]:
    return [round(float(p_ne[1]), 3), round(float(p_ne[0]), 3)]


class LiveMapState:
    """What a live view shows (this page, and Foxglove's scene: :mod:`deploy.foxglove_view`),
    kept from the messages a recorder takes (``write``) and the UWB rounds it observes
    (``observe``); thread-safe. ``lanes`` and ``origin_llh`` [rad, rad, m] are the site (default:
    no lanes, the origin at the first estimate); ``truth`` a
    :class:`hw_emulation.truth.ScenarioTruth` (emulated runs). Positions are east, north [m] in
    the tangent plane at the origin."""

    def __init__(self, lanes=(), origin_llh: tuple[float, float, float] | None = None, truth=None) -> None:
        self._lock = threading.Lock()
        self.lanes = lane_shapes(lanes)
        self.origin: tuple[float, float, float] | None = None
        self._enu: LocalEnu | None = None
        if origin_llh is not None:
            self._set_origin(origin_llh)
        self._truth = dict(truth.vehicles) if truth is not None else {}
        self._est: dict[tuple[str, str], Estimate] = {}
        self._links: dict[tuple[str, str], float] = {}
        self.refused = 0

    def write(self, m: Message) -> None:
        if not isinstance(m, Estimate):
            return
        with self._lock:
            old = self._est.get((m.vehicle, m.method))
            if old is None and len(self._est) >= MAX_ROWS:
                self.refused += 1
                return
            if old is None or m.t >= old.t:
                self._est[(m.vehicle, m.method)] = m
            if self.origin is None:
                self._set_origin(m.llh)

    def _set_origin(self, llh) -> None:
        lat, lon, h = (float(x) for x in llh)
        self.origin = (lat, lon, h)
        self._enu = LocalEnu(self.origin)

    def enu(self, llh) -> tuple[float, float]:
        """East, north [m] of a position (latitude, longitude [rad], height [m])."""
        assert self._enu is not None, "no origin yet"
        e, n, _ = self._enu(*(float(x) for x in llh))
        return e, n

    def latest(self, method: str) -> dict[str, Estimate]:
        """Vehicle -> its newest estimate of ``method``."""
        with self._lock:
            return {v: e for (v, m), e in self._est.items() if m == method}

    def shown_method(self) -> str | None:
        """The first of :data:`SHOWN_METHODS` that some vehicle runs (None before any estimate)."""
        with self._lock:
            running = {m for _, m in self._est}
        return next((m for m in SHOWN_METHODS if m in running), None)

    def links_at(self, now: float) -> list[tuple[str, str]]:
        """The pairs ranged within :data:`LINK_TTL_S` before sensor time ``now`` [s]."""
        with self._lock:
            return [p for p, t in sorted(self._links.items()) if now - t <= LINK_TTL_S]

    def observe(self, m: Message) -> None:
        """A UWB round (or a single range): its pairs were measured at its time."""
        if isinstance(m, UwbRound):
            pairs = [(m.vehicle, p) for p in m.peers]
        elif isinstance(m, UwbRange):
            pairs = [(m.a, m.b)]
        else:
            return
        with self._lock:
            for a, b in pairs:
                pair = (a, b) if a < b else (b, a)
                if pair not in self._links and len(self._links) >= MAX_LINKS:
                    self.refused += 1
                    continue
                self._links[pair] = max(self._links.get(pair, -math.inf), float(m.t))

    def _en_of(self, llh) -> list[float]:
        e, n = self.enu(llh)
        return [round(e, 3), round(n, 3)]

    def site(self) -> dict[str, Any]:
        with self._lock:
            origin = self.origin
        tracks = {}
        if origin is not None:
            for vid, vt in self._truth.items():
                tr = vt.truth
                step = max(1, int(round(1.0 / float(np.median(np.diff(tr.t))))))
                tracks[vid] = [self._en_of(p) for p in tr.llh[::step]]
        return {"type": "site",
                "origin": None if origin is None else [math.degrees(origin[0]), math.degrees(origin[1]), origin[2]],
                "lanes": [{"id": ln.id, "centre": [_en(p) for p in ln.centre], "width": ln.width,
                           "stop_line": None if ln.stop_line is None else [_en(p) for p in ln.stop_line]}
                          for ln in self.lanes],
                "truth_tracks": tracks}

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            est = list(self._est.values())
        if not est or self.origin is None:
            return {"type": "state", "t": None, "estimates": [], "links": []}
        now = max(e.t for e in est)
        return {"type": "state", "t": now, "estimates": [self._row(e) for e in sorted(est, key=_order)],
                "links": [list(p) for p in self.links_at(now)]}

    def _row(self, e: Estimate) -> dict[str, Any]:
        east, north = self.enu(e.llh)
        c = np.asarray(e.cov_pos, float)
        vn, ve = float(e.v_ned[0]), float(e.v_ned[1])
        row: dict[str, Any] = {
            "vehicle": e.vehicle, "method": e.method, "t": e.t, "e": east, "n": north,
            "cov": [float(c[1, 1]), float(c[0, 1]), float(c[0, 0])], "heading": float(e.rpy[2]),
            "speed": math.hypot(vn, ve), "first_stopped": bool(e.first_stopped),
            "sigma_h": math.sqrt(max(0.0, float(c[0, 0] + c[1, 1])))}
        vt = self._truth.get(e.vehicle)
        if vt is not None:
            err, k = vt.error_of(e.t, e.llh)
            row["err_h"] = math.hypot(float(err[0]), float(err[1]))
            row["truth"] = self._en_of(vt.truth.llh[k])
        return row


def _order(e: Estimate) -> tuple[str, str]:
    return e.vehicle, e.method


class LiveMapSink:
    """The page's web server on ``host:port`` (0: any free port, see :attr:`port`), in its own
    threads: a recorder's sink (``write(m)``, ``close()``) that also observes the UWB rounds
    (:attr:`observe_keys`, ``observe(m)``)."""

    observe_keys = UWB_KEYS

    def __init__(self, state: LiveMapState, host: str = "127.0.0.1", port: int = 8780, rate_hz: float = 5.0) -> None:
        from websockets.sync.server import serve

        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self.state, self.host, self._period = state, host, 1.0 / rate_hz
        self._page = resources.files("slcp.deploy").joinpath("web/live_map.html").read_bytes()
        self._stop = threading.Event()
        try:
            self._server = serve(self._serve, host, port, process_request=self._http, compression=None)
        except OSError as exc:
            raise OSError(f"cannot serve the live map on {host}:{port}: {exc.strerror or exc}") from None
        self.port: int = self._server.socket.getsockname()[1]
        self._thread = threading.Thread(target=self._server.serve_forever, name="live-map", daemon=True)
        self._thread.start()
        log.warning("Live map: open http://%s:%d/ in a browser", host, self.port)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def write(self, m: Message) -> None:
        self.state.write(m)

    def observe(self, m: Message) -> None:
        self.state.observe(m)

    def _http(self, connection, request):
        """The page at ``/``; ``/ws`` on to the WebSocket handshake, from the page's own origin only."""
        path = request.path.split("?", 1)[0]
        if path == "/ws":
            origin = request.headers.get("Origin")
            if origin is not None and origin not in (f"http://{h}:{self.port}" for h in (self.host, "localhost")):
                return connection.respond(403, "the live map answers its own page only\n")
            return None
        if path not in ("/", "/index.html"):
            return connection.respond(404, "not found\n")
        r = connection.respond(200, "")
        r.body = self._page
        for name, value in (("Content-Type", "text/html; charset=utf-8"), ("Content-Length", str(len(self._page))),
                            ("Cache-Control", "no-store"),
                            ("Content-Security-Policy", "default-src 'none'; script-src 'unsafe-inline'; "
                             "style-src 'unsafe-inline'; img-src data:; connect-src 'self'")):
            if name in r.headers:
                del r.headers[name]
            r.headers[name] = value
        return r

    def _serve(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            site = self.state.site()
            ws.send(json.dumps(site))
            while not self._stop.wait(self._period):
                if site["origin"] is None and self.state.origin is not None:  # a deployed fleet's first estimate
                    site = self.state.site()
                    ws.send(json.dumps(site))
                ws.send(json.dumps(self.state.snapshot()))
        except ConnectionClosed:
            pass

    def close(self) -> None:
        self._stop.set()
        self._server.shutdown()
        self._thread.join(5)
