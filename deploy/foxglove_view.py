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
=============================  ============================================================

Messages are logged with the sensor time of the run [ns]. The server listens on loopback unless
told otherwise.
"""

from __future__ import annotations

import json
import logging
import math
from typing import Any

from slcp.transport.messages import Diagnostics, Estimate, Message

from .mcap_recording import log_time_ns, ned_to_enu_cov, topic_name

log = logging.getLogger(__name__)

DIAG_SCHEMA = {"type": "object", "properties": {
    "source": {"type": "string"}, "t": {"type": "number"},
    "counters": {"type": "object", "additionalProperties": {"type": "integer"}},
    "status": {"type": "object"}}}


class FoxgloveSink:
    """A Foxglove WebSocket server on ``host:port`` (port 0: any free one, see :attr:`port`)
    that publishes what it is given (a recorder's sink: ``write(m)``, ``close()``)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "slcp") -> None:
        import foxglove

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
        # the one line a user needs to connect (the port may have been picked here)
        log.warning("Foxglove view: connect Foxglove to ws://%s:%d", host, self.port)

    def write(self, m: Message) -> None:
        ns = log_time_ns(m.t)
        if isinstance(m, Estimate):
            self._estimate(m, ns)
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

    def close(self) -> None:
        self.server.stop()


def _kv(key: str, value: str):
    from foxglove.messages import KeyValuePair

    return KeyValuePair(key=key, value=value)
