"""The recorder: every estimate and diagnostics message of a run, as JSON lines.

Append-only and flushed after every batch taken off the queue (every 0.1 s), so a message the
recorder has taken survives a crash of the recorder (at most a last line cut short, which the
evaluation skips) and a restarted recorder continues the same file. Bad payloads are counted and dropped.

The recorder trusts a message's key, not its content: on a secured fleet the router lets a process
publish only under its own keys (:mod:`deploy.zenoh_security`), so the key says who sent it. A
message whose content names another sender than its key (an estimate of V2 under V1's key, a
diagnostics message of V1 under another source's), or whose time lies outside the window the
recorder was given, is counted in :attr:`Recorder.rejected` and dropped: it would otherwise be
scored, shown, or set the launcher's clock, which times faults and the emulator's resume.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO

import numpy as np

from slcp.transport import keys
from slcp.transport.bus import Subscription
from slcp.transport.codec import MAX_PAYLOAD, CodecError, decode
from slcp.transport.messages import Diagnostics, Estimate, Message

log = logging.getLogger(__name__)


def to_json(m: Message) -> dict:
    """A message as a JSON-ready dict with its type name (arrays as lists, bytes as hex)."""
    out = {"type": type(m).__name__}
    for k, v in vars(m).items():
        out[k] = v.tolist() if isinstance(v, np.ndarray) else (v.hex() if isinstance(v, bytes) else v)
    return out


#: [bytes] each queue's bound (drained every 0.1 s: a 50-vehicle fleet's estimates fill a few MB)
QUEUE_BYTES = 128 << 20


class Recorder:
    """Writes decoded messages to ``path`` (appending) and keeps a live view for the status table.

    Attributes
    ----------
    recorded, codec_errors : int
        Messages written; payloads that failed to decode.
    rejected : dict
        Reason -> count of decodable messages dropped: ``"wrong_key"`` (the content names another
        sender or method than the key it came on), ``"wrong_type"`` (not an estimate under an
        estimate key, nor diagnostics under a diagnostics key), ``"out_of_window"`` (a time outside
        ``t_window``); and the queues' ``"oversized"`` (a payload over the codec's ``MAX_PAYLOAD``) and
        ``"queue_dropped"`` (a queue over its bound).
    latest_t : dict
        Vehicle -> newest estimate time [s].
    last_wall : dict
        Vehicle -> monotonic receipt time [s] of its newest estimate.
    diag : dict
        Source -> (monotonic receipt time [s], counters, status) of its newest diagnostics.
    """

    def __init__(self, path: Path | None, t_window: tuple[float, float] = (-math.inf, math.inf),
                 sinks: Sequence = ()) -> None:
        """``path``: the JSON lines file (None: none). ``t_window`` [s, sensor time]: the times a
        message may carry (a run's scenario, with a margin); the default takes any finite time.
        ``sinks`` (e.g. :class:`deploy.mcap_recording.McapSink`,
        :class:`deploy.foxglove_view.FoxgloveSink`) get every message recorded too (``write(m)``,
        ``close()``); their failures are logged and counted (``sink_errors``), and the JSON lines go on."""
        self.path = Path(path) if path is not None else None
        self.t_window = t_window
        self.rejected: collections.Counter[str] = collections.Counter()
        self._file: IO[str] | None = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "a")
        self.recorded = 0
        self.codec_errors = 0
        self.latest_t: dict[str, float] = {}
        self.last_wall: dict[str, float] = {}  #: vehicle -> monotonic time [s] of its newest estimate
        self.diag: dict[str, tuple[float, dict, dict]] = {}
        self._subs: list[Subscription] = []
        self.sinks = list(sinks)
        self.sink_errors = 0
        #: messages recorded per bus key
        self.counts: collections.Counter[str] = collections.Counter()

    def write(self, batch: list[tuple[str, bytes]]) -> None:
        """Decode, check against its key, write and flush a batch of ``(key, payload)``."""
        for key, p in batch:
            try:
                m = decode(p)
            except CodecError:
                self.codec_errors += 1
                continue
            why = self._refusal(key, m)
            if why:
                self.rejected[why] += 1
                continue
            if self._file is not None:
                self._file.write(json.dumps(to_json(m)) + "\n")
            self.recorded += 1
            self.counts[key] += 1
            for sink in self.sinks:
                self._to_sink(sink, m)
            if isinstance(m, Estimate):
                self.latest_t[m.vehicle] = max(self.latest_t.get(m.vehicle, 0.0), m.t)
                self.last_wall[m.vehicle] = time.monotonic()
            elif isinstance(m, Diagnostics):
                self.diag[m.source] = (time.monotonic(), m.counters, m.status)
        if self._file is not None:
            self._file.flush()

    def _refusal(self, key: str, m: Message) -> str:
        """Why ``m`` may not be recorded from ``key`` ("" if it may)."""
        if isinstance(m, Estimate):
            try:
                if key != keys.estimate(m.vehicle, m.method):
                    return "wrong_key"
            except ValueError:  # a name the keys cannot hold
                return "wrong_key"
        elif isinstance(m, Diagnostics):
            try:
                if key != keys.diag(m.source):
                    return "wrong_key"
            except ValueError:
                return "wrong_key"
        else:
            return "wrong_type"
        lo, hi = self.t_window
        if not lo <= m.t <= hi:  # also NaN
            return "out_of_window"
        return ""

    async def run(self, sub: Subscription, poll_s: float = 0.1) -> None:
        """Record everything ``sub`` delivers, taken off its queue every ``poll_s`` [s wall] (the
        subscription should be non-waking: a fleet's estimates would otherwise wake the recorder
        hundreds of times a second), until cancelled; :meth:`close` records the rest."""
        self._subs.append(sub)
        while True:
            await asyncio.sleep(poll_s)
            batch = sub.drain()
            if batch:
                self.write(batch)
            self._count_queue_losses()

    def _count_queue_losses(self) -> None:
        """The subscriptions' refusals (payloads over the codec's limit) and drops (a queue
        over its bound), in :attr:`rejected`."""
        for name, n in (("oversized", sum(s.oversized for s in self._subs)),
                        ("queue_dropped", sum(s.dropped for s in self._subs))):
            if n:
                self.rejected[name] = n

    def start(self, bus) -> list:
        """Subscribe on ``bus`` to every estimate and diagnostics message and record them; returns
        the recording tasks (cancel them, then :meth:`close`). A sink with ``observe_keys`` (key
        expressions) is also given, unrecorded, what is published under them (its ``observe(m)``)."""
        tasks = [asyncio.create_task(self.run(bus.subscribe(keys.ROOT + "/estimate/**", 1_000_000, wake=False,
                                                            maxbytes=QUEUE_BYTES, max_payload=MAX_PAYLOAD))),
                 asyncio.create_task(self.run(bus.subscribe(keys.ROOT + "/diag/**", 100_000, wake=False,
                                                            maxbytes=QUEUE_BYTES, max_payload=MAX_PAYLOAD)))]
        observers: dict[str, list] = {}  # key expression -> the sinks observing it: one subscription each
        for sink in self.sinks:
            for expr in getattr(sink, "observe_keys", ()):
                observers.setdefault(expr, []).append(sink)
        for expr, sinks in observers.items():
            sub = bus.subscribe(expr, 100_000, wake=False, maxbytes=QUEUE_BYTES // 8, max_payload=MAX_PAYLOAD)
            tasks.append(asyncio.create_task(self._observe(sub, sinks)))
        return tasks

    async def _observe(self, sub: Subscription, sinks: list, poll_s: float = 0.1) -> None:
        """Give ``sinks`` (their ``observe(m)``) what ``sub`` delivers, unrecorded, until cancelled."""
        while True:
            await asyncio.sleep(poll_s)
            for _, p in sub.drain():
                try:
                    m = decode(p)
                except CodecError:
                    self.codec_errors += 1
                    continue
                for sink in sinks:
                    self._to_sink(sink, m, "observe")

    def flush(self) -> None:
        """Record what is still queued (the recording tasks cancelled, or their bus closing)."""
        for sub in self._subs:
            batch = sub.drain()
            if batch:
                self.write(batch)
        self._count_queue_losses()

    def _to_sink(self, sink, m: Message, how: str = "write") -> None:
        try:
            getattr(sink, how)(m)
        except Exception:  # noqa: BLE001 - the JSON lines must go on whatever a sink does
            self.sink_errors += 1
            if self.sink_errors == 1:
                log.exception("%s failed; the recording goes on", type(sink).__name__)

    def close(self) -> None:
        """Record what is still queued, then close the file (and the sinks)."""
        self.flush()
        if self._file is not None:
            self._file.close()
        for sink in self.sinks:
            try:
                sink.close()
            except Exception:  # noqa: BLE001
                self.sink_errors += 1
                log.exception("closing %s failed", type(sink).__name__)
