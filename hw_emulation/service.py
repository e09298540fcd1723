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
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pymap3d

from transport import keys
from transport.bus import Bus
from transport.codec import CodecError, decode, encode
from transport.messages import Beacon, Estimate, GnssFix, ImuBatch, LaneMarkings, UwbRound

from .emulate import emulate_uwb, emulate_vehicle_sensors
from .faults import LINK_FAULTS
from .sensors.radio import RadioModel
from .truth import ScenarioTruth

log = logging.getLogger(__name__)


@dataclass
class RadioStats:
    sent: int = 0
    delivered: int = 0
    lost: int = 0
    out_of_range: int = 0
    stale: int = 0
    codec_errors: int = 0


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
        rng = np.random.default_rng(self.seed)
        self.sensors = emulate_vehicle_sensors(self.truth, rng)
        self.ranges = emulate_uwb(self.truth, rng)
        self.radio_rng = np.random.default_rng(self.seed + 1_000_003)
        self.attack_rng = np.random.default_rng(self.seed + 2_000_003)
        self.radio: RadioModel = self.truth.scenario.radio
        self.ids = sorted(self.truth.vehicles)
        self._index = {vid: k for k, vid in enumerate(self.ids)}
        lat0, lon0, h0 = self.truth.scenario.origin_llh
        self._ne = []  # per vehicle: its truth north, east [m] of the origin, (n, 2)
        for vid in self.ids:
            llh = self.truth.vehicles[vid].truth.llh
            n, e, _ = pymap3d.geodetic2ned(llh[:, 0], llh[:, 1], llh[:, 2], lat0, lon0, h0, deg=False)
            self._ne.append(np.stack([n, e], 1))
        # the vehicles share one time grid (as build_truth makes them): positions stacked
        # (n, N, 2), one search per clock value instead of one per vehicle
        t_all = [self.truth.vehicles[vid].truth.t for vid in self.ids]
        self._grid_t = t_all[0] if all(t.shape == t_all[0].shape and np.array_equal(t, t_all[0])
                                       for t in t_all) else None
        self._ne_grid = np.stack(self._ne, 1) if self._grid_t is not None else None
        if self._ne_grid is not None:  # one copy: the per-vehicle rows as views of the stack
            self._ne = [self._ne_grid[:, k] for k in range(len(self.ids))]
        self._ne_at: tuple[float, np.ndarray] | None = None
        self._pending: list[tuple[float, str, bytes]] = []  # (deliver at, receiver, payload)
        self._ge_bad: dict[tuple[str, str], bool] = {}
        self.now = float(next(iter(self.truth.vehicles.values())).truth.t[0])
        self.done = asyncio.Event()
        self._subs: tuple | None = None
        self._away: dict[str, float] = {}  #: vehicle -> monotonic time its agent left
        #: vehicle -> sensor time [s] of its last estimate when it stalled the clock; the clock no
        #: longer waits for it until it reports a later time
        self.stalled: dict[str, float] = {}

    # ----------------------------------------------------------------- radio
    def _radio_positions(self) -> np.ndarray:
        """True horizontal positions of ``self.ids`` at the radio's clock ``self.now``, shape
        (N, 2) [m] north and east of the scenario's origin (computed once per clock value)."""
        if self._ne_at is None or self._ne_at[0] != self.now:
            if self._ne_grid is not None:
                t = self._grid_t
                ne = self._ne_grid[min(int(np.searchsorted(t, self.now)), len(t) - 1)]
            else:
                rows = []
                for vid, ne in zip(self.ids, self._ne):
                    t = self.truth.vehicles[vid].truth.t
                    rows.append(ne[min(int(np.searchsorted(t, self.now)), len(t) - 1)])
                ne = np.array(rows)
            self._ne_at = (self.now, ne)
        return self._ne_at[1]

    def _radio_send(self, payload: bytes) -> None:
        try:
            b = decode(payload)
        except CodecError:
            self.radio_stats.codec_errors += 1
            return
        if not isinstance(b, Beacon) or b.vehicle not in self.truth.vehicles:
            self.radio_stats.codec_errors += 1
            return
        self.radio_stats.sent += 1
        for attack in self.attacks:
            forged = attack.apply(b, self.truth.scenario.origin_llh, self.attack_rng)
            if forged is not b:
                signer = self.signers.get(b.vehicle)
                forged = signer.sign(forged) if signer is not None else forged
                payload, b = encode(forged), forged
        r = self.radio
        ne = self._radio_positions()
        d = np.hypot(*(ne - ne[self._index[b.vehicle]]).T)
        self.radio_stats.out_of_range += int(np.count_nonzero(d > r.max_range))
        for k in np.flatnonzero(d <= r.max_range):  # receivers in range, in id order
            rx = self.ids[k]
            if rx == b.vehicle:
                continue
            active = [f for f in self.faults if f.kind in LINK_FAULTS and f.active(b.t) and f.hits_link(b.vehicle, rx)]
            if any(f.kind == "v2v_blackout" for f in active):
                self._fault_count("v2v_blackout")
                continue
            if any(f.kind == "burst_loss" and self.radio_rng.random() < f.loss for f in active):
                self._fault_count("burst_loss")
                continue
            link = (b.vehicle, rx)
            bad = self._ge_bad.get(link, False)
            u = self.radio_rng.random()
            bad = (u >= r.ge_p_bad_to_good) if bad else (u < r.ge_p_good_to_bad)
            self._ge_bad[link] = bad
            if self.radio_rng.random() < (r.ge_loss_bad if bad else r.loss):
                self.radio_stats.lost += 1
                continue
            if self.radio_rng.random() < r.stale_prob:
                lat = self.radio_rng.uniform(r.stale_min, r.stale_max)
                self.radio_stats.stale += 1
            else:
                lat = min(r.latency_min + self.radio_rng.exponential(r.jitter_mean), r.latency_max)
            spike = sum(f.latency for f in active if f.kind == "latency_spike")
            if spike:
                self._fault_count("latency_spike")
            # the radio works in sensor time: the beacon reaches rx at its own time plus latency
            self._pending.append((b.t + lat + spike, rx, payload))

    async def _radio_deliver(self) -> None:
        due = [p for p in self._pending if p[0] <= self.now]
        if not due:
            return
        self._pending = [p for p in self._pending if p[0] > self.now]
        for _, rx, payload in sorted(due, key=lambda p: p[0]):
            await self.bus.publish(keys.radio_rx(rx), payload)
            self.radio_stats.delivered += 1

    async def _radio_loop(self) -> None:
        sub = self._subs[0]
        while True:
            _, payload = await sub.get()
            self._radio_send(payload)
            for _, payload in sub.drain():  # the rest of a burst, from the same wake-up
                self._radio_send(payload)
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

    def _fault_count(self, kind: str) -> None:
        self.fault_stats[kind] = self.fault_stats.get(kind, 0) + 1

    def _sensor_fault(self, kind: str, t: float, who) -> bool:
        """Whether a GNSS fix (``who`` a vehicle) or a range (``who`` a pair) is withheld at ``t``."""
        for f in self.faults:
            if f.kind == kind and f.active(t) and (f.hits_pair(*who) if kind == "uwb_outage" else f.hits_vehicle(who)):
                self._fault_count(kind)
                return True
        return False

    def forget_agent(self, vehicle: str) -> None:
        """The agent of ``vehicle`` left (its liveliness token went away): stop pacing on it. In
        agent-paced mode the clock waits up to ``rejoin_grace`` (wall) for it to come back, as it
        would not run ahead of a restarting vehicle in real time."""
        self.agent_time.pop(vehicle, None)
        self._away[vehicle] = time.monotonic()

    def agent_back(self, vehicle: str) -> None:
        """The agent of ``vehicle`` (re)declared its liveliness."""
        self._away.pop(vehicle, None)

    # ----------------------------------------------------------------- playback
    def _events(self):
        """(time, kind, vehicle or pair, index) in sensor-time order."""
        ev = []
        stagger = self.truth.scenario.imu_stagger
        for k, vid in enumerate(self.ids):
            t = self.sensors[vid].imu_t
            # staggered: vehicle k's batches end ``k * batch / n`` samples later than the first's
            first = self.batch + ((k * self.batch) // len(self.ids) if stagger else 0)
            for j in range(first, len(t), self.batch):
                ev.append((float(t[j]), 1, "imu", vid, j))
            g = self.sensors[vid].gnss
            for i in range(len(g.t)):
                if g.t[i] > t[0] + 1e-9:
                    ev.append((float(g.t[i]), 0, "gnss", vid, i))
            cam = self.sensors[vid].lane
            if cam is not None:
                ev.extend((float(tc), 0, "lane", vid, i) for i, tc in enumerate(cam.t) if tc > t[0] + 1e-9)
        # one event per ranging round: every pair with a range at that time, (pair, index)
        rounds: dict[float, list[tuple[tuple[str, str], int]]] = {}
        for pair, rr in self.ranges.items():
            for i in np.flatnonzero(np.isfinite(rr.range)):
                if rr.t[i] > 0:
                    rounds.setdefault(float(rr.t[i]), []).append((pair, int(i)))
        for t, members in rounds.items():
            ev.append((t, 0, "uwb", members, members[0][1]))
        ev.sort(key=lambda e: (e[0], e[1]))
        return ev

    def prepare(self) -> None:
        """Subscribe to the agents' beacons and, in agent-paced mode, to their estimates. Call it
        before waiting for the agents, so that no early estimate is missed (pacing waits for
        them); :meth:`run` calls it if needed. The estimates do not wake the emulator: the pacing
        loop reads them when it looks (at a fixed speed they are not needed at all)."""
        if self._subs is None:
            est = (self.bus.subscribe(keys.ROOT + "/estimate/**", 65536, wake=False)
                   if self.speed is None else None)
            self._subs = (self.bus.subscribe(keys.ROOT + "/radio/tx/*", 65536), est)

    async def run(self, stop: asyncio.Event | None = None) -> None:
        stop = stop or asyncio.Event()
        self.prepare()
        radio = asyncio.create_task(self._radio_loop(), name="radio")
        self.bus.declare_alive(keys.alive("emulator", "main"))
        if self.start_at is not None:
            self.now = max(self.now, float(self.start_at))
            log.warning("resuming the scenario at t=%.2f s", self.now)
        wall0, t0 = time.monotonic(), self.now
        seq: dict[str, int] = {}
        try:
            for t, _, kind, who, idx in self._events():
                if stop.is_set():
                    break
                if t < t0:
                    continue  # played before a restart
                if kind == "imu":  # batch numbers as an uninterrupted emulator would have them
                    seq.setdefault(who, idx // self.batch - 1)
                await self._pace(t, wall0, t0, stop)
                self.now = t
                await self._radio_deliver()
                if kind == "imu":
                    s = self.sensors[who]
                    j0 = idx - self.batch
                    msg = ImuBatch(who, seq.setdefault(who, 0), s.imu_t[j0 + 1: idx + 1],
                                   np.diff(s.imu_t[j0: idx + 1]), s.imu.dtheta[j0: idx], s.imu.dvel[j0: idx])
                    seq[who] += 1
                    await self.bus.publish(keys.imu(who), encode(msg))
                    self.published["imu"] += 1
                elif kind == "gnss":
                    if self._sensor_fault("gnss_outage", t, who):
                        continue
                    g = self.sensors[who].gnss
                    msg = GnssFix(who, idx, float(g.t[idx]), g.llh[idx], g.v_ned[idx], g.sigma_ned[idx],
                                   float(g.sigma_v[idx]))
                    await self.bus.publish(keys.gnss(who), encode(msg))
                    self.published["gnss"] += 1
                elif kind == "lane":
                    cam = self.sensors[who].lane
                    left, right = (int(c) for c in cam.classes[idx])
                    await self.bus.publish(keys.lane(who), encode(LaneMarkings(who, idx, float(cam.t[idx]), left, right)))
                    self.published["lane"] += 1
                else:
                    # a ranging round: each vehicle gets one message with its ranges of the round
                    # (a range goes to both ends of its pair)
                    per: dict[str, tuple[list[str], list[float]]] = {}
                    for pair, i in who:
                        if self._sensor_fault("uwb_outage", t, pair):
                            continue
                        r = float(self.ranges[pair].range[i])
                        a, b = pair
                        pa, pb = per.setdefault(a, ([], [])), per.setdefault(b, ([], []))
                        pa[0].append(b)
                        pa[1].append(r)
                        pb[0].append(a)
                        pb[1].append(r)
                        self.published["uwb"] += 1
                    for vid in sorted(per):
                        peers, rs = per[vid]
                        msg = UwbRound(vid, idx, t, tuple(peers), np.array(rs))
                        await self.bus.publish(keys.uwb(vid), encode(msg))
                        self.published["uwb_rounds"] += 1
            # let the last beacons and estimates through (agents hold back a fraction of a second)
            await self._pace(self.now, wall0, t0, stop, final=True)
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
        # as fast as the slowest agent keeps up (and no faster than max_speed)
        ahead = (t - t0) / self.max_speed - (time.monotonic() - wall0)
        if ahead > 0:
            await asyncio.sleep(ahead)
        while not stop.is_set() and not final and any(
                time.monotonic() - left < self.rejoin_grace for left in self._away.values()):
            await asyncio.sleep(0.01)  # an agent left: hold the clock while it restarts
        deadline = time.monotonic() + (5.0 if final else self.stall_timeout)
        while not stop.is_set():
            self._read_estimates()
            # the slowest agent that reports (one that left is forgotten until it reports again,
            # so a dead agent never stalls the fleet and a restarted one rejoins the pacing)
            slow = min((self.agent_time[v] for v in self.ids if v in self.agent_time), default=-np.inf)
            if slow >= t - self._lead or (not final and slow == -np.inf and (t - t0 < self._lead or self.stalled)):
                break  # (with every agent set aside, the clock runs at max_speed until one reports)
            if time.monotonic() > deadline:
                if final:
                    break
                # set the laggards aside (a hung agent, or one whose estimates no longer get
                # through): the clock would otherwise wait this long again at every event
                behind = sorted(v for v in self.ids if self.agent_time.get(v, np.inf) < t - self._lead)
                for v in behind:
                    self.stalled[v] = self.agent_time.pop(v)
                if behind:
                    log.warning("agents stalled at t=%.2f (%s at %s); continuing without them until they report",
                                t, ", ".join(behind), ", ".join(f"{self.stalled[v]:.2f}" for v in behind))
                else:
                    log.warning("no agent reports at t=%.2f; continuing", t)
                break
            await asyncio.sleep(0.001)
        await asyncio.sleep(0)
