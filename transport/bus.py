"""The Bus interface and an in-memory implementation for unit tests.

Subscriptions deliver ``(key, payload bytes)`` through a bounded asyncio queue. Drop policy: when
the queue is full the *oldest* item is dropped (fresh data wins, as for sensor and beacon
streams), and the drop is counted in :attr:`Subscription.dropped`.
"""

from __future__ import annotations

import asyncio
from collections import defaultdict
from typing import AsyncIterator, Protocol

from .keys import matches


class Subscription:
    """A bounded queue of ``(key, payload)`` fed by the bus; iterate with ``async for``."""

    def __init__(self, expr: str, maxsize: int, loop: asyncio.AbstractEventLoop) -> None:
        if maxsize < 1:
            raise ValueError("queue size must be >= 1")
        self.expr = expr
        self.queue: asyncio.Queue[tuple[str, bytes]] = asyncio.Queue(maxsize)
        self.loop = loop
        self.received = 0
        self.dropped = 0
        self.closed = False

    def offer(self, key: str, payload: bytes) -> None:
        """Enqueue from the event-loop thread, dropping the oldest item when full."""
        if self.closed:
            return
        self.received += 1
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped += 1
        self.queue.put_nowait((key, payload))

    async def get(self) -> tuple[str, bytes]:
        return await self.queue.get()

    def __aiter__(self) -> AsyncIterator[tuple[str, bytes]]:
        return self._iter()

    async def _iter(self) -> AsyncIterator[tuple[str, bytes]]:
        while not self.closed:
            yield await self.queue.get()


class Bus(Protocol):
    """What agents, the emulator service and the recorder need from a transport."""

    async def publish(self, key: str, payload: bytes) -> None: ...

    def subscribe(self, expr: str, maxsize: int = 1024) -> Subscription: ...

    def declare_alive(self, key: str) -> None: ...

    def tap(self, expr: str, callback) -> None:
        """``callback(key, payload)`` at arrival, on the transport's own thread (for measurements:
        it must be quick and thread-safe)."""

    def watch_alive(self, expr: str, callback) -> None: ...

    async def close(self) -> None: ...


class InMemoryNetwork:
    """A process-local 'network' connecting several :class:`InMemoryBus` instances."""

    def __init__(self) -> None:
        self.buses: list[InMemoryBus] = []
        self.alive: set[str] = set()
        self.watchers: list[tuple[str, object]] = []

    def bus(self) -> "InMemoryBus":
        b = InMemoryBus(self)
        self.buses.append(b)
        return b


class InMemoryBus:
    """Bus over an :class:`InMemoryNetwork`: delivery is immediate and lossless, in order."""

    def __init__(self, network: InMemoryNetwork) -> None:
        self.network = network
        self.subs: list[Subscription] = []
        self.tokens: list[str] = []
        self.published = defaultdict(int)
        self.taps: list[tuple[str, object]] = []

    async def publish(self, key: str, payload: bytes) -> None:
        self.published[key] += 1
        for bus in self.network.buses:
            for expr, cb in bus.taps:
                if matches(expr, key):
                    cb(key, bytes(payload))
            for sub in bus.subs:
                if matches(sub.expr, key):
                    sub.offer(key, bytes(payload))

    def subscribe(self, expr: str, maxsize: int = 1024) -> Subscription:
        sub = Subscription(expr, maxsize, asyncio.get_running_loop())
        self.subs.append(sub)
        return sub

    def tap(self, expr: str, callback) -> None:
        self.taps.append((expr, callback))

    def declare_alive(self, key: str) -> None:
        self.tokens.append(key)
        self.network.alive.add(key)
        for expr, cb in self.network.watchers:
            if matches(expr, key):
                cb(key, True)

    def watch_alive(self, expr: str, callback) -> None:
        self.network.watchers.append((expr, callback))
        for key in sorted(self.network.alive):
            if matches(expr, key):
                callback(key, True)

    async def close(self) -> None:
        for sub in self.subs:
            sub.closed = True
        for key in self.tokens:
            self.network.alive.discard(key)
            for expr, cb in self.network.watchers:
                if matches(expr, key):
                    cb(key, False)
        if self in self.network.buses:
            self.network.buses.remove(self)
