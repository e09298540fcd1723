"""A Zenoh peer for the transport tests, run as a script: publishes ``probe/<name>`` every 50 ms
and appends, every 0.25 s, one JSON line to ``<out>`` with the names it heard in the last 0.5 s.

Usage: ``python _probe_peer.py NAME ENDPOINT LEASE_MS STRATEGY OUT`` (runs until SIGTERM).
"""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig  # noqa: E402


async def main(name: str, endpoint: str, lease_ms: int, strategy: str, out: Path) -> None:
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    bus = ZenohBus(ZenohConfig(mode="peer", connect=(endpoint,), lease_ms=lease_ms, autoconnect_strategy=strategy))
    sub = bus.subscribe("probe/*", wake=False)
    bus.declare_alive(f"probe-alive/{name}")  # as agents do: liveliness declarations in the traffic
    bus.watch_alive("probe-alive/*", lambda key, up: None)
    heard: dict[str, float] = {}
    k = 0
    with out.open("a") as f:
        while not stop.is_set():
            await bus.publish(f"probe/{name}", b"x")
            await asyncio.sleep(0.05)
            now = time.monotonic()
            for key, _ in sub.drain():
                heard[key.rsplit("/", 1)[-1]] = now
            k += 1
            if k % 5 == 0:
                f.write(json.dumps(sorted(n for n, t in heard.items() if now - t < 0.5)) + "\n")
                f.flush()
    await bus.close()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], Path(sys.argv[5])))
