"""Play a recorded drive onto a vehicle's sensor topics, so a live agent runs on real data.

``slcp replay rtklib PATH --publish --vehicle V`` turns the drive into the messages a vehicle
computer's sensor drivers would publish (:mod:`deploy.sensors`):

* IMU: the samples through :class:`deploy.sensors.imu.ImuAdapter` with the mounting rotation
  and IMU time-offset prior of the vehicle profile (:class:`deploy.replay.ReplayConfig`), 10 Hz
  batches;
* GNSS: one :class:`GnssFix` per epoch at the antenna, height made ellipsoidal as the profile
  says, the file's σ (north, east, down) and velocity σ (largest axis); fixes inside the outage
  protocol's windows are withheld, as in ``slcp replay``. The agent's own profile carries the
  antenna's lever arm.

Messages are published in time order, paced on the wall clock at ``speed`` × real time
(sensor time is GPST seconds, Unix-epoch convention). While publishing, the agent's estimates of
that vehicle are collected and compared with the file's fixes at their epochs (the error of the
estimate interpolated to the epoch): an honest check that the live agent works on real data.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from slcp.transport import keys
from slcp.transport.codec import CodecError, decode, encode
from slcp.transport.messages import Estimate, GnssFix, Message

from .datasets.recording import Recording
from .drive_scoring import score_estimates
from .replay import ReplayConfig
from .sensors.imu import ImuAdapter

log = logging.getLogger(__name__)


@dataclass
class PublishPlan:
    """Messages of a drive in publication order, and the fixes to score against."""

    vehicle: str
    messages: list[tuple[float, str, Message]]  #: (time [s], key, message)
    fix_t: np.ndarray  #: every epoch of the window [s]
    fix_llh: np.ndarray  #: (n, 3) rad, rad, m ellipsoidal
    withheld: np.ndarray  #: (n,) bool: inside an outage (not published)
    counts: dict[str, int] = field(default_factory=dict)


def plan_drive(drive: Recording, vehicle: str, cfg: ReplayConfig | None = None, start: float = 0.0,
               duration: float | None = None) -> PublishPlan:
    """The messages of ``drive`` from ``start`` seconds after its first GNSS epoch, for
    ``duration`` seconds (None: to the end). Outage windows follow ``cfg.outage`` on the whole
    drive, so a window keeps the outages it has in ``slcp replay``."""
    keys.check_name(vehicle)
    cfg = cfg if cfg is not None else ReplayConfig()
    imu, gnss = drive.imu, drive.gnss
    g0 = float(gnss.t[0])
    t_a = g0 + start
    t_b = float(gnss.t[-1]) if duration is None else t_a + duration
    if not t_b > t_a:
        raise ValueError("nothing to publish: the window is empty")
    prof = cfg.profile
    offset = prof.time.imu_offset_s
    adapter = ImuAdapter(vehicle, prof.imu.mount_rpy, offset)
    t_imu = imu.t + offset
    sel = np.flatnonzero((t_imu >= t_a - 1.0) & (t_imu <= t_b))  # one second of levelling before
    msgs: list[tuple[float, str, Message]] = []
    k_imu = keys.imu(vehicle)
    for b in adapter.push_many(imu.t[sel], imu.accel[sel], imu.gyro[sel]):
        msgs.append((float(b.t[-1]), k_imu, b))
    last = adapter.flush()
    if last is not None:
        msgs.append((float(last.t[-1]), k_imu, last))
    windows = cfg.outage.windows(g0, float(gnss.t[-1]))
    gi = np.flatnonzero((gnss.t >= t_a) & (gnss.t <= t_b))
    if len(gi) == 0:
        raise ValueError("no GNSS epoch in the window")
    llh = gnss.llh[gi].copy()
    llh[:, 2] += prof.gnss.height_to_ellipsoidal
    withheld = np.array([any(a <= t < b for a, b in windows) for t in gnss.t[gi]], bool)
    k_gnss = keys.gnss(vehicle)
    has_v = gnss.has_velocity
    for j, i in enumerate(gi):
        if withheld[j]:
            continue
        sig = np.maximum(gnss.sd_neu[i], 0.01)
        if has_v[i]:
            v, sv = gnss.v_ned[i].copy(), float(max(np.max(gnss.sd_v[i]), 0.01))
        else:  # a position-only epoch: σ_v = 0 on the wire
            v, sv = np.zeros(3), 0.0
        fix = GnssFix(vehicle, j, float(gnss.t[i]), llh[j], v, sig, sv, int(gnss.quality[i]))
        msgs.append((fix.t, k_gnss, fix))
    msgs.sort(key=lambda m: m[0])
    counts = {"imu_batches": int(sum(m[1] == k_imu for m in msgs)), "imu_samples": int(len(sel)),
              "gnss_fixes": int(len(gi) - withheld.sum()), "gnss_withheld": int(withheld.sum())}
    return PublishPlan(vehicle, msgs, gnss.t[gi].copy(), llh, withheld, counts)


async def publish_plan(bus, plan: PublishPlan, speed: float, stop: asyncio.Event | None = None) -> dict:
    """Publish ``plan`` paced at ``speed`` × real time; returns publication figures."""
    if not speed > 0:
        raise ValueError("speed must be > 0")
    loop = asyncio.get_running_loop()
    t0 = plan.messages[0][0]
    w0 = loop.time()
    late = 0.0
    n = 0
    for t, key, msg in plan.messages:
        if stop is not None and stop.is_set():
            break
        due = w0 + (t - t0) / speed
        now = loop.time()
        if due > now:
            await asyncio.sleep(due - now)
        else:
            late = max(late, now - due)
        await bus.publish(key, encode(msg))
        n += 1
    wall = loop.time() - w0
    return {"published": n, "wall_s": wall, "sensor_s": plan.messages[n - 1][0] - t0 if n else 0.0,
            "max_late_s": late}


class EstimateCollector:
    """Collects the estimates of one vehicle from the bus (``slcp/v1/estimate/<vehicle>/*``)."""

    def __init__(self, bus, vehicle: str) -> None:
        self.sub = bus.subscribe(f"{keys.ROOT}/estimate/{keys.check_name(vehicle)}/*", 65536)
        self.by_method: dict[str, list[Estimate]] = {}
        self.bad = 0
        self.last_arrival = -math.inf  #: event-loop time of the latest message [s]
        self._task = asyncio.ensure_future(self._run())

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        async for _key, payload in self.sub:
            self.last_arrival = loop.time()
            try:
                m = decode(payload)
            except CodecError:
                self.bad += 1
                continue
            if isinstance(m, Estimate):
                self.by_method.setdefault(m.method, []).append(m)

    async def quiet(self, settle: float, most: float, stop: asyncio.Event) -> None:
        """Return once no estimate has come for ``settle`` [s], at most ``most`` s from now or
        when ``stop`` is set: an agent on a busy machine trails the publication by more than its
        IMU hold."""
        loop = asyncio.get_running_loop()
        start = loop.time()
        while not stop.is_set() and loop.time() - start < most:
            wait = max(self.last_arrival, start) + settle - loop.time()
            if wait <= 0:
                return
            await asyncio.sleep(min(wait, 0.5) + 1e-3)

    async def close(self) -> None:
        self._task.cancel()
        try:
            await self._task
        except asyncio.CancelledError:
            pass


def score_plan(plan: PublishPlan, by_method: dict[str, list[Estimate]],
               lever_arm: tuple[float, float, float]) -> dict:
    """Each method's figures against the plan's fixes (:func:`deploy.drive_scoring.score_estimates`)."""
    return {m: score_estimates(plan.fix_t, plan.fix_llh, plan.withheld, est, lever_arm)[0]
            for m, est in sorted(by_method.items())}


async def replay_publish_main(plan: PublishPlan, zcfg, speed: float, wait_agent: float,
                              settle: float = 2.0, lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict:
    """Publish over Zenoh, collect the agent's estimates, and score them (see module doc)."""
    from slcp.transport.zenoh_bus import ZenohBus

    from .processes import _install_signals, wait_for_agent

    stop = asyncio.Event()
    _install_signals(stop)
    bus = ZenohBus(zcfg)
    try:
        bus.declare_alive(keys.alive("sensors", plan.vehicle))
        # subscribed before anything is published: declared just before, the subscription could
        # reach the agent after its first estimates, and the scoring would start epochs later
        collector = EstimateCollector(bus, plan.vehicle)
        if wait_agent > 0:
            await wait_for_agent(bus, plan.vehicle, [keys.gnss(plan.vehicle), keys.imu(plan.vehicle)], wait_agent)
            # and the agent must know the collector's subscription, which no status here shows
            await asyncio.sleep(0.5)
        wall0 = time.perf_counter()
        stats = await publish_plan(bus, plan, speed, stop)
        if not stop.is_set():  # the agent holds 0.25 s of IMU, and trails on a busy machine
            await collector.quiet(settle, max(30.0, 10.0 * settle), stop)
        await collector.close()
        stats["wall_s"] = time.perf_counter() - wall0
        return {"vehicle": plan.vehicle, "speed": speed, **plan.counts, **stats,
                "estimate_codec_errors": collector.bad,
                "methods": score_plan(plan, collector.by_method, lever_arm)}
    finally:
        await bus.close()
