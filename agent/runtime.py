"""The agent: the asyncio host of one vehicle's engine (:mod:`agent.engine`).

It subscribes to its own IMU, GNSS, lane-camera and UWB topics and to the beacons the V2V radio
delivers to it, decodes each payload, hands the message to the engine, and publishes what the
engine sends (signing its beacons when configured). Bad payloads are counted and dropped;
nothing received can crash the agent.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from slcp.transport import keys
from slcp.transport.bus import Bus, Subscription, Waker, drain_in_arrival_order
from slcp.transport.codec import MAX_PAYLOAD, CodecError, decode, encode, peek_beacon
from slcp.transport.messages import Beacon, Diagnostics, Estimate, Message

from .engine import AgentConfig, VehicleEngine
from .engine_config import BeaconVerifier

__all__ = ["Agent", "AgentConfig"]

log = logging.getLogger(__name__)

#: [bytes] each input queue's bound beside its length: a flood of large payloads cannot hold more.
#: A payload the codec would refuse for its size (``codec.MAX_PAYLOAD``) is counted
#: (``oversized_<kind>``), not even copied.
QUEUE_BYTES = 4 << 20
#: [s] after the stop, how long the agent keeps taking messages still on their way (see ``_linger``)
LINGER_QUIET_S = 0.25
LINGER_MAX_S = 1.5


def _beacon_prefilter(trust: BeaconVerifier) -> Callable[[bytes], str]:
    """The checks a beacon payload meets in the transport's thread, before it is queued: that
    it names a fleet vehicle and carries that vehicle's key id (no signature verified). A flood
    of strangers' or spoofed beacons is shed here at a tenth of a decode's cost; what is not a
    beacon's map goes on to the decoder, which counts it."""

    def check(payload: bytes) -> str:
        try:
            vehicle, auth = peek_beacon(payload)
        except CodecError:
            return ""
        return trust.precheck_fields(vehicle, auth)

    return check


class Agent:
    """Subscribe → decode → engine → encode → publish, for one vehicle.

    The engine's state (``filters``, ``counters``, ``tables``, ``lost``, ...) reads through the
    agent, so a host's user sees one vehicle.
    """

    def __init__(self, cfg: AgentConfig, bus: Bus, engine: type[VehicleEngine] = VehicleEngine) -> None:
        """``engine``: the engine's class (:class:`agent.stand_in.StandInEngine` for benchmarks)."""
        keys.check_name(cfg.vehicle)
        self.engine = engine(cfg)
        self.engine.extra_counters = self._queue_counters
        self.cfg = cfg
        self.bus = bus
        self._subs: dict[str, Subscription] = {}
        self.dropped: dict[str, int] = {}

    def __getattr__(self, name: str) -> Any:
        # only called for names the agent itself lacks: the engine's state
        if name == "engine":
            raise AttributeError(name)
        return getattr(self.engine, name)

    # ----------------------------------------------------------------- lifecycle
    async def run(self, stop: asyncio.Event) -> None:
        v = self.cfg.vehicle
        waker = Waker(asyncio.get_running_loop())
        # only the IMU wakes the agent (10 Hz): beacons, fixes and ranges wait in their queues
        # until then (or until a queue is half full). Processing is driven by IMU time and held
        # back by ``imu_hold`` anyway, so this delays nothing the filters see, and it saves the
        # event loop a wake-up for every other message, the largest cost of a message. Until the
        # filters start, a GNSS fix wakes it too: the engine may hold IMU data for that fix, and
        # a fleet paced on the agents' estimates sends no more IMU until they report.
        subs = {
            kind: self.bus.subscribe(key, self.cfg.queue_size, wake=kind in ("imu", "gnss"), waker=waker,
                                     maxbytes=QUEUE_BYTES, max_payload=MAX_PAYLOAD)
            for kind, key in (("beacon", keys.radio_rx(v)), ("uwb", keys.uwb(v)), ("gnss", keys.gnss(v)),
                              ("lane", keys.lane(v)), ("imu", keys.imu(v)))
        }
        self._subs = subs
        trust = self.cfg.trust
        if trust is not None:
            subs["beacon"].prefilter = _beacon_prefilter(trust)
        self.bus.declare_alive(keys.alive("agent", v))
        # with a trust store, the fleet's vehicles only: a stranger's tokens are dropped in the
        # transport's thread (one subscriber, not one per vehicle: each has a thread of its own)
        fleet = frozenset(trust.identities("vehicle")) - {v} if trust is not None else None
        self.bus.watch_alive(keys.ROOT + "/alive/agent/*", self._on_alive, names=fleet)
        consumer = asyncio.create_task(self._consume(waker, subs), name=f"{v}-consume")
        stopped = asyncio.create_task(stop.wait())
        try:  # until the stop, or until the consumer fails (its exception is raised here)
            await asyncio.wait((consumer, stopped), return_when=asyncio.FIRST_COMPLETED)
        finally:
            stopped.cancel()
            consumer.cancel()
            try:
                await consumer
            except asyncio.CancelledError:
                pass
        await self._drain(subs)  # what arrived before the stop
        await self._linger(subs)
        self.engine.finish()
        await self._publish_outbox()
        self.dropped = {k: s.dropped for k, s in subs.items()}

    def _on_alive(self, key: str, alive: bool) -> None:
        self.engine.neighbour_alive(key.rsplit("/", 1)[-1], alive)

    def _queue_counters(self) -> dict[str, int]:
        out = {f"queue_dropped_{k}": s.dropped for k, s in self._subs.items()}
        out.update({f"oversized_{k}": s.oversized for k, s in self._subs.items() if s.oversized})
        for k, s in self._subs.items():
            out.update({f"prefilter_{k}_{why}": n for why, n in s.refused.items()})
        return out

    async def _consume(self, waker: Waker, subs: dict[str, Subscription]) -> None:
        while True:
            await waker.wait()
            await self._drain(subs)
            if subs["gnss"].wake and not self.engine.waiting_for_fix:
                subs["gnss"].wake = False

    async def _drain(self, subs: dict[str, Subscription]) -> int:
        n = 0
        for kind, _, payload in drain_in_arrival_order(subs):
            await self._receive(kind, payload)
            n += 1
        return n

    async def _linger(self, subs: dict[str, Subscription]) -> None:
        """Take what is still on its way after the stop: a fleet stops as its last messages
        (the radio's last deliveries, sent as the emulator ends) cross the router, and a beacon
        delivered to this agent should be counted by it. Until :data:`LINGER_QUIET_S` pass with
        nothing new, at most :data:`LINGER_MAX_S` (a flood never runs dry)."""
        loop = asyncio.get_running_loop()
        now = loop.time()
        end, quiet_until = now + LINGER_MAX_S, now + LINGER_QUIET_S
        while loop.time() < min(end, quiet_until):
            await asyncio.sleep(LINGER_QUIET_S / 5)
            if await self._drain(subs):
                quiet_until = loop.time() + LINGER_QUIET_S

    async def _receive(self, kind: str, payload: bytes) -> None:
        try:
            msg = decode(payload)
        except CodecError as exc:
            self.engine.counters["codec_errors"] += 1
            log.debug("%s: dropped bad %s payload: %s", self.cfg.vehicle, kind, exc)
            return
        await self.handle(msg)

    async def handle(self, msg: Message) -> None:
        """Hand one decoded message to the engine and publish what it sends."""
        self.engine.handle(msg)
        await self._publish_outbox()

    async def _publish_outbox(self) -> None:
        v = self.cfg.vehicle
        for out in self.engine.take_outbox():
            if isinstance(out, Beacon):
                if self.cfg.signer is not None:
                    out = self.cfg.signer.sign(out)
                await self.bus.publish(keys.radio_tx(v), encode(out))
            elif isinstance(out, Estimate):
                await self.bus.publish(keys.estimate(v, out.method), encode(out))
            elif isinstance(out, Diagnostics):
                await self.bus.publish(keys.diag(v), encode(out))
