"""The Zenoh implementation of the Bus: the only module of slcp that imports zenoh.

Publications use Zenoh's BLOCK congestion control: a full queue delays the publisher instead
of dropping the message, so the transport loses nothing (loss is the emulator's to inject).
Zenoh (1.x) has no asyncio API and runs callbacks on its own threads, where calling Zenoh or
blocking is forbidden: each callback copies the payload bytes into the subscription's queue
(thread-safe) and wakes the event loop with ``loop.call_soon_threadsafe`` only when no wake-up
is pending already (see :class:`transport.bus.Waker`). Sessions are closed explicitly, after
the last publications have had a moment to leave (:attr:`ZenohBus.CLOSE_LINGER_S`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import zenoh

from .bus import AliveCallback, Subscription, TapCallback, Waker

log = logging.getLogger(__name__)


AUTOCONNECT_STRATEGIES = ("greater-zid", "always")

#: A Zenoh runtime configuration (``ZENOH_RUNTIME``, RON) for a light client process: the
#: receive, accept and network runtimes hand their work over to one application worker thread,
#: and transmission keeps a thread of its own, so a client process runs 3 Zenoh threads instead
#: of 6. Transmission must not share the one worker: a task that waits for room in a link's
#: queue (BLOCK congestion control) would hold the only thread that can empty it, until Zenoh
#: closes the link after 5 s ("Unable to push non droppable network message"). Zenoh reads the
#: variable once, when its first session opens. ``slcp run`` gives it to the agents (unless
#: ``ZENOH_RUNTIME`` is set already): on one machine dozens of processes share a few cores, and
#: fewer threads to wake cost them less.
LIGHT_CLIENT_RUNTIME = ("(rx: (handover: app), acc: (handover: app), net: (handover: app), "
                        "tx: (worker_threads: 1), app: (worker_threads: 1))")


@dataclass(frozen=True)
class ZenohConfig:
    """Session settings.

    Attributes
    ----------
    mode : {"peer", "client", "router"}
        The session's role: a peer (dials and accepts), a client (through a router only) or a
        router.
    listen, connect : tuple of str
        Endpoints such as ``tcp/127.0.0.1:7447``.
    multicast_scouting : bool
        Off by default (tests and deployments name their endpoints).
    lease_ms : int
        Transport lease; a frozen peer is declared gone after about this long.
    autoconnect_strategy : {"greater-zid", "always"}
        How a peer dials the peers it learns of (gossip, multicast scouting). ``"greater-zid"``
        (default): of two peers only one dials the other, so a pair never holds two links that
        can expire one at a time. With ``"always"`` both dial, and a lease that expires on one
        side only (a process frozen for about a lease) can leave a pair split for good: data
        one way, nothing back, no liveliness change (eclipse-zenoh/zenoh#2806). Routers are
        always dialled.
    config_file : str, optional
        A Zenoh JSON5 configuration file (TLS, ACL, ...) loaded first; the fields above
        override it.
    extra : dict
        Further Zenoh configuration keys (JSON5 paths, e.g. ``transport/link/tx/lease``) and
        their values, inserted last.
    """

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    lease_ms: int = 2000
    autoconnect_strategy: str = "greater-zid"
    config_file: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_zenoh(self) -> zenoh.Config:
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"zenoh mode must be peer, client or router, got {self.mode!r}")
        conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        conf.insert_json5("transport/link/tx/lease", json.dumps(int(self.lease_ms)))
        if self.autoconnect_strategy not in AUTOCONNECT_STRATEGIES:
            raise ValueError(f"zenoh autoconnect_strategy must be one of {', '.join(AUTOCONNECT_STRATEGIES)}, "
                             f"got {self.autoconnect_strategy!r}")
        strategy = json.dumps({"peer": {"to_router": "always", "to_peer": self.autoconnect_strategy}})
        conf.insert_json5("scouting/gossip/autoconnect_strategy", strategy)
        conf.insert_json5("scouting/multicast/autoconnect_strategy", strategy)
        if self.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        if self.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        for k, v in self.extra.items():
            conf.insert_json5(k, json.dumps(v))
        return conf


class _Undeclarable(Protocol):
    """A publisher, subscriber or liveliness token: what :meth:`ZenohBus.close` undeclares."""

    def undeclare(self) -> object: ...


_zenoh_log_started = False


def _start_zenoh_log() -> None:
    """Zenoh's own log to stderr: its errors, or what ``RUST_LOG`` asks for (``slcp run`` sets
    ``zenoh=warn`` for its children, whose logs are files: lease expiries and lost links;
    ``RUST_LOG=zenoh=debug`` traces a link). Once per process: Zenoh's logger is set once."""
    global _zenoh_log_started
    if _zenoh_log_started:
        return
    _zenoh_log_started = True
    before = os.environ.get("NO_COLOR")
    os.environ["NO_COLOR"] = "1"  # plain text in log files; read once, when the logger starts
    try:
        zenoh.init_log_from_env_or("error")
    finally:
        if before is None:
            del os.environ["NO_COLOR"]
        else:
            os.environ["NO_COLOR"] = before


def _matching(pub: zenoh.Publisher) -> bool:
    status = pub.matching_status  # a MatchingStatus in zenoh-python 1.x (its stub says bool)
    return bool(getattr(status, "matching", status))


class ZenohBus:
    """Bus over a Zenoh session. Create inside a running event loop."""

    def __init__(self, config: ZenohConfig) -> None:
        self.loop = asyncio.get_running_loop()
        _start_zenoh_log()
        conf = config.to_zenoh()
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as e:  # e.g. a client whose router is not there
            # Zenoh's message ends with the Rust source line it came from: not the user's concern
            msg = re.sub(r"\s+at\s+\S+\.rs:\d+\.?", "", str(e)).strip()
            where = ", ".join([*(f"connect {e}" for e in config.connect), *(f"listen {e}" for e in config.listen)])
            where = where or "Zenoh's defaults"
            raise ConnectionError(f"cannot open a Zenoh session ({config.mode}) on {where}: {msg}") from None
        except BaseException as e:  # a Rust panic (pyo3 PanicException) is not an Exception
            if type(e).__name__ != "PanicException":
                raise
            raise RuntimeError(f"Zenoh could not start (is ZENOH_RUNTIME={os.environ.get('ZENOH_RUNTIME')!r} "
                               f"valid?): {str(e)[:300]}") from None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscribers: list[zenoh.Subscriber[None]] = []
        self._subs: list[Subscription] = []
        self._tokens: dict[str, zenoh.LivelinessToken] = {}
        self._closed = False
        self._last_publish = -math.inf  #: monotonic time [s] of the latest publication
        self._router = config.mode == "router"

    def _handler(self, callback: Callable[[zenoh.Sample], None]) -> zenoh.handlers.Callback[zenoh.Sample]:
        """``callback`` as this session's subscriptions run it. A peer's or a client's callbacks
        run in the Zenoh thread that received the sample: zenoh-python's default, a Python thread
        per subscription, queues samples of different keys in an order the OS scheduler decides (a
        GNSS fix overtaken by the IMU batches sent after it is a fix the filters drop late), at
        the cost of a thread and two hand-offs per subscription. A router's keep that default:
        its Zenoh threads route every other session's traffic, and must not wait there for this
        process's Python lock (its subscriptions are the recorder's and the viewers', each of
        which keeps its own stream). slcp's callbacks only copy and queue, never call Zenoh."""
        return zenoh.handlers.Callback(callback, indirect=self._router)

    def connected(self) -> bool:
        """Whether the session has a link to any router or peer right now."""
        info = self.session.info
        return any(True for _ in info.routers_zid()) or any(True for _ in info.peers_zid())

    def _publisher(self, key: str) -> zenoh.Publisher:
        pub = self._publishers.get(key)
        if pub is None:
            # BLOCK: Zenoh's default (DROP) discards a message that finds a link's queue full
            # for 1 ms, which a busy router does to sensor data of a fleet playing fast. slcp's
            # loss is the emulated radio's to inject
            pub = self._publishers[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        return pub

    async def publish(self, key: str, payload: bytes) -> None:
        self._publisher(key).put(payload)
        self._last_publish = time.monotonic()

    async def wait_subscribed(self, key_list: Sequence[str], timeout: float) -> bool:
        # Zenoh's matching status: this session has heard of a subscription matching the key
        # (a publication before that is dropped at the source)
        pubs = [self._publisher(k) for k in key_list]
        end = time.monotonic() + timeout
        while not all(_matching(p) for p in pubs):
            if time.monotonic() >= end:
                return False
            await asyncio.sleep(0.01)
        return True

    def subscribe(self, expr: str, maxsize: int = 1024, wake: bool = True,
                  waker: Waker | None = None, maxbytes: int | None = None,
                  max_payload: int | None = None) -> Subscription:
        sub = Subscription(expr, maxsize, self.loop, wake, waker, maxbytes, max_payload)

        def on_sample(sample: zenoh.Sample) -> None:  # zenoh thread: copy, queue, wake the loop at most once
            payload = sample.payload
            if len(payload) > sub.max_payload:  # counted, never copied
                sub.received += 1
                sub.oversized += 1
                return
            sub.offer(str(sample.key_expr), payload.to_bytes(), threadsafe=True)

        self._subscribers.append(self.session.declare_subscriber(expr, self._handler(on_sample)))
        self._subs.append(sub)
        return sub

    def tap(self, expr: str, callback: TapCallback) -> None:
        """``callback(key, payload)`` in Zenoh's thread at arrival (quick and thread-safe only)."""

        def on_sample(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.payload.to_bytes())

        self._subscribers.append(self.session.declare_subscriber(expr, self._handler(on_sample)))

    def declare_alive(self, key: str) -> None:
        if key in self._tokens:  # one token per key
            return
        self._tokens[key] = self.session.liveliness().declare_token(key)

    def withdraw_alive(self, key: str) -> None:
        token = self._tokens.pop(key, None)
        if token is not None:
            token.undeclare()  # type: ignore[no-untyped-call]  # zenoh's stub leaves it unannotated

    def watch_alive(self, expr: str, callback: AliveCallback, names: frozenset[str] | None = None) -> None:
        """``callback(key, alive: bool)`` on the event loop for tokens matching ``expr`` (with
        ``names``, only those whose last chunk is one of them: filtered in Zenoh's thread)."""
        loop = self.loop

        def on_sample(sample: zenoh.Sample) -> None:
            alive = sample.kind == zenoh.SampleKind.PUT
            key = str(sample.key_expr)
            if names is not None and key.rsplit("/", 1)[-1] not in names:
                return
            try:
                loop.call_soon_threadsafe(callback, key, alive)
            except RuntimeError:
                pass

        self._subscribers.append(self.session.liveliness().declare_subscriber(expr, self._handler(on_sample),
                                                                               history=True))

    #: [s] how long :meth:`close` lets a publication made just before it leave: closing the
    #: session drops what is still in its queues (a process's last message, such as its final
    #: diagnostics, was lost in 10-40 % of closes right after a burst of publications on loopback)
    CLOSE_LINGER_S = 0.5

    async def close(self) -> None:
        if self._closed:
            return
        wait = self.CLOSE_LINGER_S - (time.monotonic() - self._last_publish)
        if wait > 0:
            await asyncio.sleep(wait)
            if self._closed:  # closed by another caller meanwhile
                return
        self._closed = True
        for sub in self._subs:
            sub.closed = True
        entities: list[_Undeclarable] = [*self._tokens.values(), *self._subscribers, *self._publishers.values()]
        for obj in entities:
            try:
                obj.undeclare()
            except Exception:  # already gone with the session
                log.debug("undeclare failed", exc_info=True)
        self.session.close()  # type: ignore[no-untyped-call]  # zenoh's stub leaves Session.close unannotated
