"""The Bus interface and an in-memory implementation for unit tests.

Subscriptions deliver ``(key, payload bytes)`` through a queue bounded in messages and in bytes.
Drop policy: when the queue is full the *oldest* item is dropped (fresh data wins, as for sensor
and beacon streams), and the drop is counted in :attr:`Subscription.dropped`; a payload larger
than the subscription's ``max_payload`` is not queued at all (:attr:`Subscription.oversized`), so
a flood of huge payloads costs neither memory nor a decode. Waking the event loop is the dominant
cost of a message on a busy machine, so a consumer is woken once per burst, and a subscription
may be non-waking (drained when its consumer wakes for another one).
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
from collections import defaultdict, deque
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Protocol

from . import codec
from .keys import matches

#: arrival stamps shared by every subscription of the process (``next`` is atomic in CPython), so
#: that a consumer of several queues can take their items in the order they arrived
_arrival = itertools.count()

#: ``callback(key, payload)`` of :meth:`Bus.tap` (its return value is ignored)
TapCallback = Callable[[str, bytes], object]
#: ``callback(key, alive)`` of :meth:`Bus.watch_alive` (its return value is ignored)
AliveCallback = Callable[[str, bool], object]


class Waker:
    """Wakes the consumer of one or several subscriptions; safe to signal from any thread.

    A signal that arrives while one is already pending costs nothing more: a burst of messages
    wakes the event loop once, and the consumer drains everything queued.
    """

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._event = asyncio.Event()
        self._pending = False

    def signal(self, threadsafe: bool = False) -> None:
        """Wake the consumer (``threadsafe``: called from a thread other than the loop's)."""
        if self._pending:
            return
        self._pending = True
        if threadsafe:
            try:
                self.loop.call_soon_threadsafe(self._event.set)
            except RuntimeError:  # loop closed during shutdown
                pass
        else:
            self._event.set()

    async def wait(self) -> None:
        """Wait for the next signal. The pending flag is cleared first, so that an item offered
        while the consumer drains signals again (never lost, at worst one spare wake-up)."""
        await self._event.wait()
        self._event.clear()
        self._pending = False


class Subscription:
    """A bounded queue of ``(key, payload)`` fed by the bus.

    ``offer`` may be called from any thread (a deque's append and popleft are atomic). A *waking*
    subscription signals its :class:`Waker` for every offer; a non-waking one (``wake=False``)
    only queues, and signals once it is half full, so its consumer drains it whenever it is woken
    for something else (an agent drains beacons when its IMU arrives). Several subscriptions may
    share one waker. ``await get()`` and ``async for`` serve single-subscription consumers.
    """

    #: default bounds: a payload the codec would refuse for its size anyway, and a queue of 64 MB
    MAX_PAYLOAD = codec.MAX_PAYLOAD
    MAX_BYTES = 64 << 20

    def __init__(self, expr: str, maxsize: int, loop: asyncio.AbstractEventLoop, wake: bool = True,
                 waker: Waker | None = None, maxbytes: int | None = None, max_payload: int | None = None) -> None:
        if maxsize < 1:
            raise ValueError("queue size must be >= 1")
        self.expr = expr
        self.maxsize = maxsize
        self.maxbytes = self.MAX_BYTES if maxbytes is None else int(maxbytes)
        self.max_payload = self.MAX_PAYLOAD if max_payload is None else int(max_payload)
        if self.max_payload < 1 or self.maxbytes < self.max_payload:
            raise ValueError(f"need 1 <= max_payload <= maxbytes, got {self.max_payload} and {self.maxbytes}")
        self.loop = loop
        self.wake = wake
        self.waker = waker if waker is not None else Waker(loop)
        self._items: deque[tuple[int, str, bytes]] = deque()  # (arrival stamp, key, payload)
        self._high_water = max(1, maxsize // 2)
        self.received = 0
        self.dropped = 0
        self.oversized = 0
        self.closed = False
        #: ``prefilter(payload)`` -> "" to queue the payload, else the reason it is refused
        #: (counted in :attr:`refused`): a receiver's cheapest checks, run in the producer's
        #: thread so that a flood never fills the queue (it must be quick and thread-safe)
        self.prefilter: Callable[[bytes], str] | None = None
        self.refused: dict[str, int] = {}
        # queued bytes = _added - _shed - _taken; each counter has one writer (the producer's
        # thread for the first two, the consumer's for the third), so no update is lost
        self._added = self._shed = self._taken = 0

    def __len__(self) -> int:
        return len(self._items)

    def offer(self, key: str, payload: bytes, threadsafe: bool = False) -> None:
        """Enqueue, dropping (and counting) the oldest item when full."""
        if self.closed:
            return
        self.received += 1
        n = len(payload)
        if n > self.max_payload:
            self.oversized += 1
            return
        if self.prefilter is not None:
            why = self.prefilter(payload)
            if why:
                self.refused[why] = self.refused.get(why, 0) + 1
                return
        items = self._items
        while items and (len(items) >= self.maxsize or self.queued_bytes + n > self.maxbytes):
            try:
                self._shed += len(items.popleft()[2])
                self.dropped += 1
            except IndexError:  # drained meanwhile by the consumer
                break
        items.append((next(_arrival), key, payload))
        self._added += n
        if self.wake or len(items) >= self._high_water:
            self.waker.signal(threadsafe)

    @property
    def queued_bytes(self) -> int:
        """Payload bytes queued now (approximate while the other thread is at work)."""
        return self._added - self._shed - self._taken

    def _take(self, before: int | None = None) -> list[tuple[int, str, bytes]]:
        """The queued items, oldest first; with ``before``, only those stamped before it (the
        rest stay queued, in order)."""
        out = []
        items = self._items
        taken = 0
        while items:
            try:
                item = items.popleft()
            except IndexError:
                break
            if before is not None and item[0] >= before:
                items.appendleft(item)  # the oldest left: back in front of what came after it
                break
            out.append(item)
            taken += len(item[2])
        self._taken += taken
        return out

    def drain(self) -> list[tuple[str, bytes]]:
        """Everything queued now, oldest first, as ``(key, payload)``."""
        return [(k, p) for _, k, p in self._take()]

    async def get(self) -> tuple[str, bytes]:
        while not self._items:
            await self.waker.wait()
        _, key, payload = self._items.popleft()
        self._taken += len(payload)
        return key, payload

    def __aiter__(self) -> AsyncIterator[tuple[str, bytes]]:
        return self._iter()

    async def _iter(self) -> AsyncIterator[tuple[str, bytes]]:
        while not self.closed:
            yield await self.get()


def drain_in_arrival_order(subs: dict[str, Subscription]) -> list[tuple[str, str, bytes]]:
    """Everything queued now in several subscriptions, as ``(name, key, payload)`` in the order
    the messages arrived (``subs`` maps a name to its subscription). "Now" is one instant for
    all of them: the queues are taken one after the other while the transport's thread keeps
    adding, so a message that arrived after the cut stays queued for the next drain (else a
    later queue's newer messages would be handed over before an earlier queue's message that
    arrived just after it was taken: an IMU batch before the GNSS fix that preceded it)."""
    cut = next(_arrival)
    runs = [[(stamp, name, key, payload) for stamp, key, payload in sub._take(cut)] for name, sub in subs.items()]
    return [(name, key, payload) for _, name, key, payload in heapq.merge(*runs)]


class Bus(Protocol):
    """What agents, the emulator service and the recorder need from a transport."""

    async def publish(self, key: str, payload: bytes) -> None: ...

    def subscribe(self, expr: str, maxsize: int = 1024, wake: bool = True,
                  waker: Waker | None = None, maxbytes: int | None = None,
                  max_payload: int | None = None) -> Subscription:
        """A subscription to ``expr`` (see :class:`Subscription` for the other arguments)."""

    def declare_alive(self, key: str) -> None: ...

    async def wait_subscribed(self, key_list: Sequence[str], timeout: float) -> bool:
        """Whether every key of ``key_list`` has a subscriber on the bus within ``timeout`` [s]
        (what this bus publishes on them from then on reaches someone)."""

    def withdraw_alive(self, key: str) -> None:
        """Undeclare this bus's liveliness token ``key`` (its watchers see it go)."""

    def tap(self, expr: str, callback: TapCallback) -> None:
        """``callback(key, payload)`` at arrival, on the transport's own thread (for measurements:
        it must be quick and thread-safe)."""

    def watch_alive(self, expr: str, callback: AliveCallback, names: frozenset[str] | None = None) -> None:
        """``callback(key, alive)`` for the liveliness tokens matching ``expr``; with ``names``,
        only for keys whose last chunk is one of them (the others are dropped where they
        arrive: a stranger churning thousands of tokens costs no wake-up of the consumer)."""

    async def close(self) -> None: ...


class InMemoryNetwork:
    """A process-local 'network' connecting several :class:`InMemoryBus` instances."""

    def __init__(self) -> None:
        self.buses: list[InMemoryBus] = []
        self.alive: set[str] = set()
        self.watchers: list[tuple[str, AliveCallback]] = []

    def bus(self) -> InMemoryBus:
        b = InMemoryBus(self)
        self.buses.append(b)
        return b


class InMemoryBus:
    """Bus over an :class:`InMemoryNetwork`: delivery is immediate and lossless, in order."""

    def __init__(self, network: InMemoryNetwork) -> None:
        self.network = network
        self.subs: list[Subscription] = []
        self.tokens: list[str] = []
        self.published: defaultdict[str, int] = defaultdict(int)
        self.taps: list[tuple[str, TapCallback]] = []

    async def publish(self, key: str, payload: bytes) -> None:
        self.published[key] += 1
        for bus in self.network.buses:
            for expr, cb in bus.taps:
                if matches(expr, key):
                    cb(key, bytes(payload))
            for sub in bus.subs:
                if matches(sub.expr, key):
                    sub.offer(key, bytes(payload))

    def subscribe(self, expr: str, maxsize: int = 1024, wake: bool = True,
                  waker: Waker | None = None, maxbytes: int | None = None,
                  max_payload: int | None = None) -> Subscription:
        sub = Subscription(expr, maxsize, asyncio.get_running_loop(), wake, waker, maxbytes, max_payload)
        self.subs.append(sub)
        return sub

    def tap(self, expr: str, callback: TapCallback) -> None:
        self.taps.append((expr, callback))

    async def wait_subscribed(self, key_list: Sequence[str], timeout: float) -> bool:
        def heard(key: str) -> bool:
            return any(matches(expr, key) for bus in self.network.buses
                       for expr in [*(s.expr for s in bus.subs if not s.closed), *(e for e, _ in bus.taps)])

        end = asyncio.get_running_loop().time() + timeout
        while not all(heard(k) for k in key_list):
            if asyncio.get_running_loop().time() >= end:
                return False
            await asyncio.sleep(0.01)
        return True

    def declare_alive(self, key: str) -> None:
        self.tokens.append(key)
        self.network.alive.add(key)
        for expr, cb in self.network.watchers:
            if matches(expr, key):
                cb(key, True)

    def withdraw_alive(self, key: str) -> None:
        if key not in self.tokens:
            return
        self.tokens.remove(key)
        self.network.alive.discard(key)
        for expr, cb in self.network.watchers:
            if matches(expr, key):
                cb(key, False)

    def watch_alive(self, expr: str, callback: AliveCallback, names: frozenset[str] | None = None) -> None:
        if names is not None:
            inner = callback

            def callback(key: str, alive: bool) -> object:
                return inner(key, alive) if key.rsplit("/", 1)[-1] in names else None

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
