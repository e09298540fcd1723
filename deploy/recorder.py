"""The recorder: every estimate and diagnostics message of a run, as JSON lines.

Append-only and flushed after every batch taken off the queue (every 0.1 s), so a message the
recorder has taken survives a crash of the recorder (at most a last line cut short, which the
evaluation skips) and a restarted recorder continues the same file. Bad payloads are counted and dropped.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import IO

import numpy as np

from slcp.transport.bus import Subscription
from slcp.transport.codec import CodecError, decode
from slcp.transport.messages import Diagnostics, Estimate, Message


def to_json(m: Message) -> dict:
    """A message as a JSON-ready dict with its type name (arrays as lists, bytes as hex)."""
    out = {"type": type(m).__name__}
    for k, v in vars(m).items():
        out[k] = v.tolist() if isinstance(v, np.ndarray) else (v.hex() if isinstance(v, bytes) else v)
    return out


class Recorder:
    """Writes decoded messages to ``path`` (appending) and keeps a live view for the status table.

    Attributes
    ----------
    recorded, codec_errors : int
        Messages written; payloads that failed to decode.
    latest_t : dict
        Vehicle -> newest estimate time [s].
    last_wall : dict
        Vehicle -> monotonic receipt time [s] of its newest estimate.
    diag : dict
        Source -> (monotonic receipt time [s], counters, status) of its newest diagnostics.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: IO[str] = open(self.path, "a")
        self.recorded = 0
        self.codec_errors = 0
        self.latest_t: dict[str, float] = {}
        self.last_wall: dict[str, float] = {}  #: vehicle -> monotonic time [s] of its newest estimate
        self.diag: dict[str, tuple[float, dict, dict]] = {}
        self._subs: list[Subscription] = []

    def write(self, payloads: list[bytes]) -> None:
        """Decode, write and flush a batch of payloads."""
        for p in payloads:
            try:
                m = decode(p)
            except CodecError:
                self.codec_errors += 1
                continue
            self._file.write(json.dumps(to_json(m)) + "\n")
            self.recorded += 1
            if isinstance(m, Estimate):
                self.latest_t[m.vehicle] = max(self.latest_t.get(m.vehicle, 0.0), m.t)
                self.last_wall[m.vehicle] = time.monotonic()
            elif isinstance(m, Diagnostics):
                self.diag[m.source] = (time.monotonic(), m.counters, m.status)
        self._file.flush()

    async def run(self, sub: Subscription, poll_s: float = 0.1) -> None:
        """Record everything ``sub`` delivers, taken off its queue every ``poll_s`` [s wall] (the
        subscription should be non-waking: a fleet's estimates would otherwise wake the recorder
        hundreds of times a second), until cancelled; :meth:`close` records the rest."""
        self._subs.append(sub)
        while True:
            await asyncio.sleep(poll_s)
            batch = [payload for _, payload in sub.drain()]
            if batch:
                self.write(batch)

    def start(self, bus) -> list:
        """Subscribe on ``bus`` to every estimate and diagnostics message and record them; returns
        the two recording tasks (cancel them, then :meth:`close`)."""
        from slcp.transport import keys

        return [asyncio.create_task(self.run(bus.subscribe(keys.ROOT + "/estimate/**", 1_000_000, wake=False))),
                asyncio.create_task(self.run(bus.subscribe(keys.ROOT + "/diag/**", 100_000, wake=False)))]

    def close(self) -> None:
        """Record what is still queued, then close the file."""
        for sub in self._subs:
            batch = [payload for _, payload in sub.drain()]
            if batch:
                self.write(batch)
        self._file.close()
