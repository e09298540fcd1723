"""The emulator service: publishes a scenario's sensor data on the bus and plays the V2V radio.

Impure shell over the pure emulation. Sensor data go out in sensor-time order: per vehicle, IMU
batches of ``batch`` samples (all vehicles' batches end at the same sample times, or at evenly
spread phases with the scenario's ``imu_stagger``), GNSS fixes, and UWB ranges to *both* ends of
each pair. The radio
subscribes to the agents' beacons (``radio/tx/*``) and delivers each to every other vehicle
(``radio/rx/<receiver>``) with the scenario's loss, latency and range limit, on sensor time.

Pacing: ``speed`` = N plays N× real time; ``speed = None`` plays as fast as the slowest agent
keeps up: publication never runs more than ``lead`` seconds of sensor time ahead of the slowest
agent's latest estimate (so no sample is dropped by a full queue and the agents stay within
``lead`` of each other), and never faster than ``max_speed``× real time.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from slcp.transport import keys
from slcp.transport.bus import Bus
from slcp.transport.codec import MAX_PAYLOAD, CodecError, decode, encode
from slcp.transport.messages import Beacon, Diagnostics, Estimate, GnssFix, ImuBatch, LaneMarkings, Message, UwbRound

from .playback import Radio, RadioStats, SensorPlayback
from .truth import ScenarioTruth

log = logging.getLogger(__name__)


@dataclass
class EmulatorService:
    truth: ScenarioTruth
    bus: Bus
    seed: int = 0
    speed: float | None = None
    #: IMU samples per message (default: the scenario's ``imu_batch``)
    batch: int | None = None
    #: agent-paced mode: how far [s of sensor time] the clock may run ahead of the slowest agent
    #: (default: what the agents' batches and hold need plus a margin; 0.5 s for 0.1 s batches)
    lead: float | None = None
    #: the agents' IMU hold [s] (``AgentConfig.imu_hold``), for the default ``lead``
    agent_hold: float = 0.25
    #: in agent-paced mode, never faster than this real-time factor: spreads publication so that
    #: reordering across topics stays far below the agents' IMU hold time
    max_speed: float = 20.0
    #: agent-paced mode: how long [s wall] the clock waits for an agent that left to come back
    rejoin_grace: float = 10.0
    #: agent-paced mode: how long [s wall] the clock waits for an agent that reports nothing new;
    #: then it goes on without that agent until the agent reports a later time
    stall_timeout: float = 30.0
    #: resume a scenario at this sensor time [s] (a restarted emulator): earlier events are skipped
    start_at: float | None = None
    radio_stats: RadioStats = field(default_factory=RadioStats)
    #: messages published per kind ("uwb": ranges, each to both ends in "uwb_rounds" messages)
    published: dict[str, int] = field(default_factory=lambda: {"imu": 0, "gnss": 0, "lane": 0, "uwb": 0,
                                                                          "uwb_rounds": 0})
    agent_time: dict[str, float] = field(default_factory=dict)
    #: misbehaving vehicles (their beacons are falsified in the radio, see hw_emulation.attacks)
    attacks: list = field(default_factory=list)
    #: vehicle -> transport.security.BeaconSigner, to re-sign an attacker's falsified beacons
    signers: dict = field(default_factory=dict)
    #: link and sensor faults (hw_emulation.faults.Fault); process faults are the launcher's
    faults: list = field(default_factory=list)
    fault_stats: dict[str, int] = field(default_factory=dict)
    #: [s of sensor time] between the emulator's diagnostics (``diag/emulator``); 0: none
    diag_period: float = 1.0

    def __post_init__(self) -> None:
        if self.batch is None:
            self.batch = self.truth.scenario.imu_batch
        # At a batch end t the clock has published IMU data up to t - P (P: a batch's duration),
        # and an agent has processed the whole batches that end ``agent_hold`` before that, up to
        # t - P - ceil(hold / P)·P; its newest estimate (10 Hz) is up to 0.1 s older when batches
        # are shorter than that. Leading by less would wait for agents that wait for data. The
        # margin (0.1 s, and a batch beyond 0.1 s) covers the start, where an agent initialised
        # inside a batch reports its next estimate only after the following one.
        period = self.batch / self.truth.scenario.imu_rate
        need = period + math.ceil(self.agent_hold / period - 1e-9) * period + max(0.0, 0.1 - period)
        self._lead = float(self.lead) if self.lead is not None else need + 0.1 + max(0.0, period - 0.1)
        self.playback = SensorPlayback(self.truth, self.seed, self.batch, self.faults, self.fault_stats,
                                       self.published)
        self.sensors, self.ranges, self.ids = self.playback.sensors, self.playback.ranges, self.playback.ids
        #: the newest estimate a vehicle that leaves the traffic can send [s]: its last IMU sample
        #: on the air, less the lead (what an agent holds back): pacing waits no longer for it
        self._last_data = {v: float(vt.truth.t[vt.present][-1]) - self._lead for v, vt in self.truth.vehicles.items()
                           if vt.present is not None and vt.present.any()}
        signers = self.signers

        def resign(b: Beacon) -> Beacon:
            signer = signers.get(b.vehicle)
            return signer.sign(b) if signer is not None else b

        self.radio = Radio(self.truth, self.seed, self.attacks, self.faults, self.fault_stats, self.radio_stats,
                           resign=resign, reencode=encode)
        self.now = float(next(iter(self.truth.vehicles.values())).truth.t[0])
        self.done = asyncio.Event()
        self._subs: tuple | None = None
        self._away: dict[str, float] = {}  #: vehicle -> monotonic time its agent left
        #: vehicle -> sensor time [s] of its last estimate when it stalled the clock; the clock no
        #: longer waits for it until it reports a later time
        self.stalled: dict[str, float] = {}
        #: departures of names that are not the scenario's vehicles, ignored
        self.unknown_liveliness = 0
        #: (monotonic time, sensor time) from which ``max_speed`` is measured (see :meth:`_pace`)
        self._rate_ref: tuple[float, float] | None = None

    # ----------------------------------------------------------------- diagnostics
    def diagnostics(self) -> Diagnostics:
        """The emulator's counters (what it published, the radio's and the faults' statistics)
        and, in the status, the radio's deliveries per link (``"V0>V1": [delivered, out of
        order]``) and the agents the clock no longer waits for."""
        counters = {f"published_{k}": v for k, v in self.published.items()}
        counters.update({f"radio_{k}": v for k, v in dataclasses.asdict(self.radio_stats).items()})
        counters.update({f"fault_{k}": v for k, v in self.fault_stats.items()})
        counters["unknown_liveliness"] = self.unknown_liveliness
        if self._subs is not None:
            counters["radio_queue_dropped"] = self._subs[0].dropped
        status = {"t": self.now, "links": {f"{tx}>{rx}": list(c) for (tx, rx), c in sorted(self.radio.links.items())},
                  "stalled": sorted(self.stalled)}
        return Diagnostics("emulator", self.now, counters, status)

    async def _publish_diag(self) -> None:
        await self.bus.publish(keys.diag("emulator"), encode(self.diagnostics()))

    # ----------------------------------------------------------------- radio
    def _radio_send(self, key: str, payload: bytes) -> None:
        try:
            b = decode(payload)
        except CodecError:
            self.radio_stats.codec_errors += 1
            return
        if not isinstance(b, Beacon):
            self.radio_stats.codec_errors += 1
            return
        # the key names the transmitter (on a secured fleet only it may publish there)
        self.radio.send(b, payload, self.now, transmitter=key.rsplit("/", 1)[-1])

    async def _radio_deliver(self) -> None:
        for _, rx, payload in self.radio.due(self.now):
            await self.bus.publish(keys.radio_rx(rx), payload)

    async def _radio_loop(self) -> None:
        sub = self._subs[0]
        while True:
            key, payload = await sub.get()
            self._radio_send(key, payload)
            for key, payload in sub.drain():  # the rest of a burst, from the same wake-up
                self._radio_send(key, payload)
            self.radio_stats.oversized = sub.oversized
            # deliver at once what is due: beacons arrive after the radio's clock passed their
            # time (agents trail it by their IMU hold), so waiting for the next sensor event
            # would add up to a batch period of latency
            await self._radio_deliver()

    def _read_estimates(self) -> None:
        """Pace on the agents' estimates queued since the last call (agent-paced mode only)."""
        if self._subs is None or self._subs[1] is None:
            return
        for _, payload in self._subs[1].drain():
            try:
                e = decode(payload)
            except CodecError:
                continue
            if isinstance(e, Estimate):
                self.agent_progress(e.vehicle, e.t)

    def agent_progress(self, vehicle: str, t: float) -> None:
        """An estimate of ``vehicle`` at sensor time ``t`` [s] arrived: pace on it. Ignored while
        the agent is away: an estimate its dead process sent just before its liveliness token
        went (still queued here) would put it back in the pacing at its old time, and the clock
        would then wait for a restarted agent that cannot start without new sensor data."""
        if vehicle in self._away:
            return
        if vehicle in self.stalled:
            if t <= self.stalled[vehicle]:
                return
            log.warning("agent %s reports again (t=%.2f); pacing on it", vehicle, t)
            del self.stalled[vehicle]
        self.agent_time[vehicle] = max(self.agent_time.get(vehicle, -np.inf), t)

    def forget_agent(self, vehicle: str) -> None:
        """The agent of ``vehicle`` left (its liveliness token went away): stop pacing on it. In
        agent-paced mode the clock waits up to ``rejoin_grace`` (wall) for it to come back, as it
        would not run ahead of a restarting vehicle in real time. A name that is not one of the
        scenario's vehicles is ignored (counted in :attr:`unknown_liveliness`): a token anyone
        could declare must not hold the clock."""
        if vehicle not in self.ids:
            self.unknown_liveliness += 1
            return
        self.agent_time.pop(vehicle, None)
        self._away[vehicle] = time.monotonic()

    def agent_back(self, vehicle: str) -> None:
        """The agent of ``vehicle`` (re)declared its liveliness. One that comes back is set aside
        until it reports: it has no estimate to report before the sensor data it missed, and
        when every agent was away (the network went down) the clock would wait for nobody."""
        if self._away.pop(vehicle, None) is not None and vehicle not in self.agent_time:
            self.stalled.setdefault(vehicle, -np.inf)
        elif vehicle in self.agent_time:
            # declared again before the last token's departure was seen (a process restarted
            # faster than its predecessor's token was withdrawn, on a busy router): the new
            # process has no estimate before the data it missed, so waiting for it at the old
            # time would hold the clock for stall_timeout; aside until it reports a newer one
            self.stalled[vehicle] = self.agent_time.pop(vehicle)

    # ----------------------------------------------------------------- playback
    def _events(self):
        """(time, order, kind, vehicle or ranging round, index) in sensor-time order."""
        return self.playback.events()

    def prepare(self) -> None:
        """Subscribe to the agents' beacons and, in agent-paced mode, to their estimates. Call it
        before waiting for the agents, so that no early estimate is missed (pacing waits for
        them); :meth:`run` calls it if needed. The estimates do not wake the emulator: the pacing
        loop reads them when it looks (at a fixed speed they are not needed at all)."""
        if self._subs is None:
            est = (self.bus.subscribe(keys.ROOT + "/estimate/**", 65536, wake=False, max_payload=MAX_PAYLOAD)
                   if self.speed is None else None)
            self._subs = (self.bus.subscribe(keys.ROOT + "/radio/tx/*", 65536, max_payload=MAX_PAYLOAD), est)

    async def run(self, stop: asyncio.Event | None = None) -> None:
        stop = stop or asyncio.Event()
        self.prepare()
        radio = asyncio.create_task(self._radio_loop(), name="radio")
        self.bus.declare_alive(keys.alive("emulator", "main"))
        if self.start_at is not None:
            self.now = max(self.now, float(self.start_at))
            log.warning("resuming the scenario at t=%.2f s", self.now)
        wall0, t0 = time.monotonic(), self.now
        self._rate_ref = None
        try:
            next_diag = t0
            for t, messages in self.playback.messages(start_at=t0):
                if stop.is_set():
                    break
                await self._pace(t, wall0, t0, stop)
                self.now = t
                await self._radio_deliver()
                for msg in messages:
                    await self.bus.publish(_topic(msg), encode(msg))
                if self.diag_period and t >= next_diag:
                    await self._publish_diag()
                    next_diag = t + self.diag_period
            # let the last beacons and estimates through (agents hold back a fraction of a second)
            await self._pace(self.now, wall0, t0, stop, final=True)
            await self._radio_deliver()
            if self.diag_period:
                await self._publish_diag()
        finally:
            radio.cancel()
            self.done.set()

    async def _pace(self, t: float, wall0: float, t0: float, stop: asyncio.Event, final: bool = False) -> None:
        if self.speed:
            delay = (t - t0) / self.speed - (time.monotonic() - wall0)
            if delay > 0:
                await asyncio.sleep(delay)
            else:
                await asyncio.sleep(0)
            return
        # as fast as the slowest agent keeps up, and no faster than max_speed measured from the
        # last time the clock was behind that rate: time spent waiting (for the agents, for one
        # that restarts, for a busy machine) is never made up in a burst, which could play the
        # rest of a scenario within a fraction of a second, before agents that are back after a
        # network outage report again
        now = time.monotonic()
        ref_wall, ref_t = self._rate_ref or (now, t)
        ahead = (t - ref_t) / self.max_speed - (now - ref_wall)
        if ahead > 0:
            self._rate_ref = (ref_wall, ref_t)
            await asyncio.sleep(ahead)
        else:
            self._rate_ref = (now, t)
        while not stop.is_set() and not final and any(
                time.monotonic() - left < self.rejoin_grace for left in self._away.values()):
            await asyncio.sleep(0.01)  # an agent left: hold the clock while it restarts
        deadline = time.monotonic() + (5.0 if final else self.stall_timeout)
        # (a vehicle of external trajectories only up to its last data: it reports no more)
        need = {v: min(t - self._lead, self._last_data.get(v, np.inf)) for v in self.ids}
        while not stop.is_set():
            self._read_estimates()
            # the slowest agent that reports (one that left is forgotten until it reports again,
            # so a dead agent never stalls the fleet and a restarted one rejoins the pacing)
            waiting = [v for v in self.ids if v in self.agent_time and self.agent_time[v] < need[v]]
            slow = -np.inf if not any(v in self.agent_time for v in self.ids) else (
                t if not waiting else min(self.agent_time[v] for v in waiting))
            if slow >= t - self._lead or (slow == -np.inf and (self.stalled or (not final and t - t0 < self._lead))):
                break  # (with every agent set aside, the clock runs at max_speed until one reports)
            if time.monotonic() > deadline:
                if final:
                    break
                # set the laggards aside (a hung agent, or one whose estimates no longer get
                # through): the clock would otherwise wait this long again at every event
                behind = sorted(v for v in self.ids if self.agent_time.get(v, np.inf) < need[v])
                for v in behind:
                    self.stalled[v] = self.agent_time.pop(v)
                if behind:
                    log.warning("agents stalled at t=%.2f (%s at %s); continuing without them until they report",
                                t, ", ".join(behind), ", ".join(f"{self.stalled[v]:.2f}" for v in behind))
                else:
                    # none reports: set them all aside too, or the clock would wait this long at
                    # every event (an agent's first report clears it, as a stalled one's does)
                    for v in self.ids:
                        if v not in self.agent_time:
                            self.stalled.setdefault(v, -np.inf)
                    log.warning("no agent reports at t=%.2f; continuing without waiting until one reports", t)
                break
            await asyncio.sleep(0.001)
        await asyncio.sleep(0)


def _topic(msg: Message) -> str:
    """The bus key a sensor message of the playback goes out on."""
    if isinstance(msg, ImuBatch):
        return keys.imu(msg.vehicle)
    if isinstance(msg, GnssFix):
        return keys.gnss(msg.vehicle)
    if isinstance(msg, LaneMarkings):
        return keys.lane(msg.vehicle)
    if isinstance(msg, UwbRound):
        return keys.uwb(msg.vehicle)
    raise TypeError(f"no sensor topic for {type(msg).__name__}")
