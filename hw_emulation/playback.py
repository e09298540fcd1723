"""A scenario's sensor data as messages in sensor-time order, and the V2V radio (pure).

The emulator service (:mod:`hw_emulation.service`) publishes these on the bus; the lab's
in-process runner hands them to the vehicle engines directly. Both draw the same sensor data
from one seed and see the same faults, so they play the same world.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pymap3d

from slcp.transport.messages import Beacon, GnssFix, ImuBatch, LaneMarkings, Message, UwbRound
from slcp.transport.rate_limit import TokenBuckets

from .emulate import emulate_uwb, emulate_vehicle_sensors
from .faults import LINK_FAULTS
from .sensors.radio import RadioModel
from .truth import ScenarioTruth


def _count(stats: dict[str, int], kind: str) -> None:
    stats[kind] = stats.get(kind, 0) + 1


@dataclass
class SensorPlayback:
    """Every vehicle's emulated sensors of one seed, as wire messages in sensor-time order.

    IMU batches of ``batch`` samples (all vehicles' batches end at the same sample times, or at
    evenly spread phases with the scenario's ``imu_stagger``), GNSS fixes, lane-camera reports,
    and one UWB round message per vehicle and ranging round (a range goes to both ends of its
    pair). Sensor faults (``gnss_outage``, ``uwb_outage``) withhold data and are counted in
    ``fault_stats``.
    """

    truth: ScenarioTruth
    seed: int = 0
    #: IMU samples per message (default: the scenario's ``imu_batch``)
    batch: int | None = None
    faults: list = field(default_factory=list)
    fault_stats: dict[str, int] = field(default_factory=dict)
    #: messages produced per kind ("uwb": ranges, each to both ends in "uwb_rounds" messages)
    published: dict[str, int] = field(default_factory=lambda: {"imu": 0, "gnss": 0, "lane": 0, "uwb": 0,
                                                                          "uwb_rounds": 0})

    def __post_init__(self) -> None:
        if self.batch is None:
            self.batch = self.truth.scenario.imu_batch
        rng = np.random.default_rng(self.seed)
        self.sensors = emulate_vehicle_sensors(self.truth, rng)
        self.ranges = emulate_uwb(self.truth, rng)
        self.ids = sorted(self.truth.vehicles)

    def events(self) -> list[tuple[float, int, str, Any, int]]:
        """(time, order, kind, vehicle or ranging round, index) in sensor-time order; a vehicle
        that is off the air (:attr:`VehicleTruth.present`) has none (an IMU batch only if it is
        on the air over the whole batch)."""
        ev: list[tuple[float, int, str, Any, int]] = []
        stagger = self.truth.scenario.imu_stagger
        vt = self.truth.vehicles
        for k, vid in enumerate(self.ids):
            t = self.sensors[vid].imu_t
            on = vt[vid].present_at
            # staggered: vehicle k's batches end ``k * batch / n`` samples later than the first's
            first = self.batch + ((k * self.batch) // len(self.ids) if stagger else 0)
            for j in range(first, len(t), self.batch):
                if on(float(t[j - self.batch])) and on(float(t[j])):
                    ev.append((float(t[j]), 1, "imu", vid, j))
            g = self.sensors[vid].gnss
            for i in range(len(g.t)):
                if g.t[i] > t[0] + 1e-9 and on(float(g.t[i])):
                    ev.append((float(g.t[i]), 0, "gnss", vid, i))
            cam = self.sensors[vid].lane
            if cam is not None:
                ev.extend((float(tc), 0, "lane", vid, i) for i, tc in enumerate(cam.t) if tc > t[0] + 1e-9 and on(tc))
        # one event per ranging round: every pair with a range at that time, (pair, index)
        rounds: dict[float, list[tuple[tuple[str, str], int]]] = {}
        for pair, rr in self.ranges.items():
            ok = np.isfinite(rr.range) & (rr.t > 0) & vt[pair[0]].present_over(rr.t) & vt[pair[1]].present_over(rr.t)
            for i in np.flatnonzero(ok):
                rounds.setdefault(float(rr.t[i]), []).append((pair, int(i)))
        for t, members in rounds.items():
            ev.append((t, 0, "uwb", members, members[0][1]))
        ev.sort(key=lambda e: (e[0], e[1]))
        return ev

    def messages(self, start_at: float | None = None) -> Iterator[tuple[float, list[Message]]]:
        """(sensor time, the messages of that event) from ``start_at`` on (a resumed scenario:
        IMU batch numbers continue as an uninterrupted playback would have them)."""
        seq: dict[str, int] = {}
        for t, _, kind, who, idx in self.events():
            if start_at is not None and t < start_at:
                continue
            if kind == "imu":
                s = self.sensors[who]
                j0 = idx - self.batch
                n = seq.setdefault(who, idx // self.batch - 1)
                seq[who] = n + 1
                self.published["imu"] += 1
                yield t, [ImuBatch(who, n, s.imu_t[j0 + 1: idx + 1], np.diff(s.imu_t[j0: idx + 1]),
                                   s.imu.dtheta[j0: idx], s.imu.dvel[j0: idx])]
            elif kind == "gnss":
                if self._sensor_fault("gnss_outage", t, who):
                    continue
                g = self.sensors[who].gnss
                self.published["gnss"] += 1
                yield t, [GnssFix(who, idx, float(g.t[idx]), g.llh[idx], g.v_ned[idx], g.sigma_ned[idx],
                                  float(g.sigma_v[idx]))]
            elif kind == "lane":
                cam = self.sensors[who].lane
                left, right = (int(c) for c in cam.classes[idx])
                self.published["lane"] += 1
                yield t, [LaneMarkings(who, idx, float(cam.t[idx]), left, right)]
            else:
                yield t, self._round(t, who, idx)

    def _round(self, t: float, members: list[tuple[tuple[str, str], int]], idx: int) -> list[Message]:
        """A ranging round: each vehicle gets one message with its ranges of the round."""
        per: dict[str, tuple[list[str], list[float]]] = {}
        for pair, i in members:
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
        self.published["uwb_rounds"] += len(per)
        return [UwbRound(vid, idx, t, tuple(per[vid][0]), np.array(per[vid][1])) for vid in sorted(per)]

    def _sensor_fault(self, kind: str, t: float, who) -> bool:
        """Whether a GNSS fix (``who`` a vehicle) or a range (``who`` a pair) is withheld at ``t``."""
        for f in self.faults:
            if f.kind == kind and f.active(t) and (f.hits_pair(*who) if kind == "uwb_outage" else f.hits_vehicle(who)):
                _count(self.fault_stats, kind)
                return True
        return False


#: the furthest ahead of the radio's clock a beacon's stamp may be [s]: senders run on the
#: emulator's sensor time, so a beacon from further ahead is forged or broken, and would wait in
#: the radio for ever
MAX_AHEAD = 1.0


@dataclass
class RadioStats:
    sent: int = 0
    delivered: int = 0
    lost: int = 0
    out_of_range: int = 0
    #: receivers in range but off the air (a vehicle not yet in the traffic, or gone from it)
    off_air: int = 0
    stale: int = 0
    codec_errors: int = 0
    #: beacons stamped further ahead of the radio's clock than :data:`MAX_AHEAD`: dropped
    future_dated: int = 0
    #: beacons beyond the transmitter's share of the channel (``RadioModel.max_tx_rate``): not sent
    channel_busy: int = 0
    #: payloads over the radio's size limit: not decoded, not sent
    oversized: int = 0


@dataclass
class Radio:
    """The V2V radio on sensor time: who receives a beacon, and when.

    :meth:`send` takes a beacon and its payload (the encoded bytes, or the beacon itself in an
    in-process run) and draws its fate on every link from the sender, with the scenario's
    range limit, Gilbert-Elliott loss, latency and stale deliveries, and the link faults;
    :meth:`due` returns the deliveries due by a time. Misbehaving vehicles' beacons are
    falsified here (``attacks``), then re-signed by ``resign`` and re-encoded by ``reencode``.
    """

    truth: ScenarioTruth
    seed: int = 0
    attacks: list = field(default_factory=list)
    faults: list = field(default_factory=list)
    fault_stats: dict[str, int] = field(default_factory=dict)
    stats: RadioStats = field(default_factory=RadioStats)
    resign: Callable[[Beacon], Beacon] | None = None
    reencode: Callable[[Beacon], Any] | None = None

    def __post_init__(self) -> None:
        self.model: RadioModel = self.truth.scenario.radio
        self.rng = np.random.default_rng(self.seed + 1_000_003)
        self.attack_rng = np.random.default_rng(self.seed + 2_000_003)
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
        self._may_leave = any(self.truth.vehicles[vid].present is not None for vid in self.ids)
        self._on_air_at: tuple[float, np.ndarray] | None = None
        #: (deliver at, receiver, payload, (transmitter, receiver, method), beacon time)
        self._pending: list[tuple[float, str, Any, tuple[str, str, str], float]] = []
        #: (transmitter, receiver) -> [delivered, out of order]: a beacon is out of order when
        #: it reaches the receiver after a newer one of the same transmitter and method (a late
        #: delivery overtaken), so a receiver that refuses old beacons rightly drops it. Bounded
        #: by the scenario's vehicles (the radio carries no other transmitter).
        self.links: dict[tuple[str, str], list[int]] = {}
        self._newest: dict[tuple[str, str, str], float] = {}
        self._earliest = math.inf  #: at most the earliest delivery time pending [s]
        self._ge_bad: dict[tuple[str, str], bool] = {}
        # the channel's share of each transmitter (see RadioModel.max_tx_rate): a second's burst
        self._airtime = TokenBuckets(self.model.max_tx_rate, self.model.max_tx_rate)

    def positions(self, now: float) -> np.ndarray:
        """True horizontal positions of ``ids`` at sensor time ``now``, shape (N, 2) [m] north and
        east of the scenario's origin (computed once per clock value)."""
        if self._ne_at is None or self._ne_at[0] != now:
            if self._ne_grid is not None:
                t = self._grid_t
                ne = self._ne_grid[min(int(np.searchsorted(t, now)), len(t) - 1)]
            else:
                rows = []
                for vid, ne in zip(self.ids, self._ne):
                    t = self.truth.vehicles[vid].truth.t
                    rows.append(ne[min(int(np.searchsorted(t, now)), len(t) - 1)])
                ne = np.array(rows)
            self._ne_at = (now, ne)
        return self._ne_at[1]

    def on_air(self, now: float) -> np.ndarray | None:
        """Which of ``ids`` are on the air at sensor time ``now``, shape (N,) (computed once per
        clock value); None when every vehicle is, always."""
        if not self._may_leave:
            return None
        if self._on_air_at is None or self._on_air_at[0] != now:
            self._on_air_at = (now, np.array([self.truth.vehicles[vid].present_at(now) for vid in self.ids]))
        return self._on_air_at[1]

    def send(self, b: Beacon, payload: Any, now: float, transmitter: str | None = None) -> None:
        """A beacon sent when the radio's clock reads ``now`` [s sensor time] by ``transmitter``
        (the station whose key it came on; default the vehicle it names)."""
        if b.vehicle not in self._index or (transmitter is not None and transmitter not in self._index):
            self.stats.codec_errors += 1  # not a vehicle of the scenario
            return
        if not b.t <= now + MAX_AHEAD:
            self.stats.future_dated += 1
            return
        if not self._airtime.take(transmitter or b.vehicle, now):
            self.stats.channel_busy += 1
            return
        self.stats.sent += 1
        for attack in self.attacks:
            forged = attack.apply(b, self.truth.scenario.origin_llh, self.attack_rng)
            if forged is not b:
                forged = self.resign(forged) if self.resign is not None else forged
                b = forged
                payload = self.reencode(forged) if self.reencode is not None else forged
        ne = self.positions(now)
        d = np.hypot(*(ne - ne[self._index[b.vehicle]]).T)
        reach = d <= self.model.max_range
        self.stats.out_of_range += int(np.count_nonzero(~reach))
        on = self.on_air(now)
        if on is not None:  # a vehicle before or after its time in the traffic has no radio there
            self.stats.off_air += int(np.count_nonzero(reach & ~on))
            reach &= on
        for k in np.flatnonzero(reach):  # receivers in range, in id order
            rx = self.ids[k]
            if rx != b.vehicle:
                self._link(b, payload, rx)

    def _link(self, b: Beacon, payload: Any, rx: str) -> None:
        r, rng = self.model, self.rng
        active = [f for f in self.faults if f.kind in LINK_FAULTS and f.active(b.t) and f.hits_link(b.vehicle, rx)]
        if any(f.kind == "v2v_blackout" for f in active):
            _count(self.fault_stats, "v2v_blackout")
            return
        if any(f.kind == "burst_loss" and rng.random() < f.loss for f in active):
            _count(self.fault_stats, "burst_loss")
            return
        link = (b.vehicle, rx)
        bad = self._ge_bad.get(link, False)
        u = rng.random()
        bad = (u >= r.ge_p_bad_to_good) if bad else (u < r.ge_p_good_to_bad)
        self._ge_bad[link] = bad
        if rng.random() < (r.ge_loss_bad if bad else r.loss):
            self.stats.lost += 1
            return
        if rng.random() < r.stale_prob:
            lat = rng.uniform(r.stale_min, r.stale_max)
            self.stats.stale += 1
        else:
            lat = min(r.latency_min + rng.exponential(r.jitter_mean), r.latency_max)
        spike = sum(f.latency for f in active if f.kind == "latency_spike")
        if spike:
            _count(self.fault_stats, "latency_spike")
        # the radio works in sensor time: the beacon reaches rx at its own time plus latency
        at = b.t + lat + spike
        self._pending.append((at, rx, payload, (b.vehicle, rx, b.method), b.t))
        self._earliest = min(self._earliest, at)

    def due(self, now: float) -> list[tuple[float, str, Any]]:
        """The deliveries due by ``now`` (deliver time, receiver, payload), in time order."""
        if not self._pending or self._earliest > now:  # the common case: nothing due, no scan
            return []
        due: list = []
        keep: list = []
        earliest = math.inf
        for p in self._pending:
            if p[0] <= now:
                due.append(p)
            else:
                keep.append(p)
                earliest = min(earliest, p[0])
        self._pending, self._earliest = keep, earliest
        due.sort(key=lambda p: p[0])
        self.stats.delivered += len(due)
        newest, links = self._newest, self.links
        for *_, stream, t in due:
            counts = links.get(stream[:2])
            if counts is None:
                counts = links[stream[:2]] = [0, 0]
            counts[0] += 1
            if t <= newest.get(stream, -math.inf):
                counts[1] += 1
            else:
                newest[stream] = t
        return [p[:3] for p in due]
