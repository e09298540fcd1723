"""The vehicle engine: one vehicle's estimator, synchronous and free of I/O.

Every host drives this one engine: the asyncio agent (:mod:`agent.runtime`, the code a vehicle
runs), the in-process runner of the lab and the replay. Messages go in through
:meth:`VehicleEngine.handle` (sensor data, ranges and neighbours' beacons, as decoded from the
wire); beacons (5 Hz), estimates (10 Hz) and diagnostics (1 Hz), stamped with sensor time,
come out in :attr:`VehicleEngine.outbox` for the host to send. The engine orders measurements by
sensor time against the IMU (:mod:`agent.sequencer`); runs the configured methods side by side
(CP-family filters use only beacons of the same method); decides "first stopped" from its own
data, the map and the beacons; and checks neighbours for misbehaviour. A well-formed but
unusable message is counted and dropped; nothing received can break the engine.
"""

from __future__ import annotations

import bisect
import heapq
import logging
import math
from collections import deque
from collections.abc import Callable

import numpy as np

from slcp.geo import earth
from slcp.transport.messages import (
    Beacon,
    GnssFix,
    ImuBatch,
    LaneMarkings,
    Message,
    UwbRange,
    UwbRound,
)
from slcp.transport.rate_limit import TokenBuckets

from .decision_step import first_stopped_step
from .engine_config import AgentConfig, RangeObserver
from .engine_imu import EngineImu
from .engine_neighbours import EngineNeighbours
from .engine_outputs import EngineOutputs
from .first_stopped import FirstStoppedDetector, StopTracker
from .input_checks import InputChecks
from .integrity import OWN_TWIN, check_separation
from .methods import MethodFilter, MethodSpec, initial_state
from .misbehaviour import MisbehaviourDetector
from .nav.motion import StationarityMonitor, ZuptGate
from .neighbours import NeighbourTable
from .position_course import PositionCourse, has_velocity
from .sequencer import Apply, Sequencer

log = logging.getLogger(__name__)

class VehicleEngine(EngineImu, EngineOutputs, EngineNeighbours):
    """One vehicle's methods, sequencing, first-stopped decisions and neighbour checks.

    ``handle`` takes any message; what the engine sends goes to ``outbox`` (beacons unsigned:
    signing is the host's). ``extra_counters`` (set by a host) adds host counters, such as its
    queue drops, to the diagnostics; ``range_observer`` is told every range outcome (the lab
    scores them against the injected errors).
    """

    #: the GNSS fix that starts the filters is at most this far from the IMU start [s]
    INIT_FIX_WINDOW = 1.0

    def __init__(self, cfg: AgentConfig) -> None:
        for m in cfg.methods:
            MethodSpec.of(m)
        self.cfg = cfg
        self.outbox: list[Message] = []
        self.extra_counters: Callable[[], dict[str, int]] | None = None
        self.range_observer: RangeObserver | None = None
        self.seq = Sequencer()
        self.filters: dict[str, MethodFilter] = {}
        self.tables = {m: NeighbourTable(timeout=cfg.neighbour_timeout) for m in cfg.methods}
        self.detector = FirstStoppedDetector(cfg.lanes, cfg.gap)
        self.trackers = {m: StopTracker(self.detector) for m in cfg.methods if MethodSpec.of(m).stop_line}
        self.counters: dict[str, int] = {"imu_batches": 0, "gnss": 0, "lane": 0, "uwb": 0, "beacons_rx": 0,
                                         "beacons_tx": 0, "estimates_tx": 0, "codec_errors": 0,
                                         "not_for_me": 0, "before_init": 0, "decisions": 0}
        self.decision_log: list[tuple[float, str, str]] = []
        #: stop-line method -> the reason of its latest first-stopped decision ("moving", "not
        #: near a stop line", "neighbour V3 may be ahead", "first stopped", ...), in diagnostics
        self.decision_reason: dict[str, str] = {}
        #: GNSS fixes received before the filters start (the newest few)
        self._pending_fixes: deque[GnssFix] = deque(maxlen=32)
        #: per (vehicle, method): the signature verifications a sender may cost (made when first used)
        self._verify_budget: TokenBuckets | None = None
        #: fixes waiting for the filter time of their GNSS time (time offset estimated)
        self._held_fixes: list[tuple[float, int, GnssFix]] = []
        self._deferred: list[tuple[float, str, str, float]] = []  # (t, method, neighbour, range)
        #: the earliest time among the deferred ranges of each (method, neighbour)
        self._deferred_min: dict[tuple[str, str], float] = {}
        self.rest = StationarityMonitor()
        self.zupt_gate = ZuptGate()
        self._course = PositionCourse()  # velocities of position-only fixes
        self._imu_buffer: list[ImuBatch] = []
        self.checks = InputChecks(cfg.vehicle, cfg.max_time_jump, cfg.jump_confirm, self._count)
        self._next: dict[str, float | None] = {"beacon": None, "estimate": None, "decision": None, "diag": None}
        self._timer_due = math.inf  #: earliest of ``_next`` [s sensor time]
        self._rest_checked = -math.inf  #: sensor time of the last rest/ZUPT check [s]
        self._beacon_seq = 0
        #: neighbours gone: vehicle -> (sensor time [s], "liveliness" | "silence")
        self.lost: dict[str, tuple[float, str]] = {}
        #: method -> neighbour lost -> (last llh, last covariance, time lost [s])
        self._ghosts: dict[str, dict[str, tuple[np.ndarray, np.ndarray, float]]] = {}
        #: the latest departures: (sensor time [s], vehicle, how)
        self.departures: deque = deque(maxlen=20)
        #: verified, fresh beacons received / excluded as misbehaving, per sender
        self.beacons_from: dict[str, int] = {}
        #: (sender, method) -> time of its newest verified beacon: the replay check's memory,
        #: kept when the sender leaves the tables (gone silent, its token gone), so that its
        #: last beacons replayed within the time window are still refused
        self._newest_verified: dict[tuple[str, str], float] = {}
        self.excluded_from: dict[str, int] = {}
        self.misbehaviour = (MisbehaviourDetector(nlos_bias=cfg.nlos_bias_max)
                             if cfg.misbehaviour_detection else None)
        self._handlers: dict[type, Callable[[Message], None]] = {
            ImuBatch: self._on_imu, GnssFix: self._on_own_sample, LaneMarkings: self._on_own_sample,
            UwbRange: self._on_range, UwbRound: self._on_round, Beacon: self._on_beacon}
        untested = [m for m in cfg.methods if m in OWN_TWIN and OWN_TWIN[m] not in cfg.methods]
        if untested and cfg.settings.separation_false_alarm:
            log.warning("%s: no cooperative integrity test for %s: it needs %s among the methods too",
                        cfg.vehicle, ", ".join(untested), ", ".join(OWN_TWIN[m] for m in untested))

    # ----------------------------------------------------------------- inputs
    def handle(self, msg: Message) -> None:
        """Take one decoded message; a well-formed but unusable one (e.g. a range to ourselves)
        is counted (``rejected_<type>``) and dropped."""
        handler = self._handlers.get(type(msg))
        if handler is None:
            self.counters["not_for_me"] += 1
            return
        try:
            handler(msg)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            self._count(f"rejected_{type(msg).__name__}")
            log.debug("%s: rejected %s: %s", self.cfg.vehicle, type(msg).__name__, exc)

    def finish(self) -> None:
        """End of input: process the IMU data held back, then the ranges still waiting."""
        while self._imu_buffer:
            self._imu(self._imu_buffer.pop(0))
        if self.filters:
            self._fuse_ranges(final=True)
        if self.seq.t is not None:  # the final account, after the last input
            self.outbox.append(self.diagnostics(self.seq.t))

    def take_outbox(self) -> list[Message]:
        """The messages produced since the last call, oldest first."""
        out, self.outbox = self.outbox, []
        return out

    def _on_imu(self, msg: ImuBatch) -> None:
        if msg.vehicle != self.cfg.vehicle:
            self.counters["not_for_me"] += 1
            return
        if self.checks.duplicate("imu", (msg.seq, float(msg.t[0]))) or not self.checks.imu_in_time(msg):
            return
        self.counters["imu_batches"] += 1
        # held in time order (a batch delivered late is put back in its place), processed once
        # imu_hold newer data has arrived
        bisect.insort(self._imu_buffer, msg, key=lambda b: float(b.t[-1]))
        self._release_imu()

    def _release_imu(self) -> None:
        """Process the held IMU batches that imu_hold newer data has passed. Before the filters
        start, the first batch also waits (up to ``INIT_FIX_WINDOW`` more) for a GNSS fix near
        its start: which fix starts the filters, and when, must depend on the data, not on
        whether the fix or later IMU batches were delivered first (they travel on different
        keys, and a host may hand them over in either order)."""
        newest = self.checks.imu_newest
        if newest is None:
            return
        hold = self.cfg.imu_hold
        while self._imu_buffer and float(self._imu_buffer[0].t[-1]) <= newest - hold:
            first = self._imu_buffer[0]
            if (not self.filters and self._init_fix(first) is None
                    and float(first.t[-1]) > newest - hold - self.INIT_FIX_WINDOW):
                break  # its fix may still be on its way
            self._imu(self._imu_buffer.pop(0))

    @property
    def waiting_for_fix(self) -> bool:
        """True while the filters have not started: a host should hand over a GNSS fix at once
        (it may release IMU data held for it) rather than with the next IMU batch."""
        return not self.filters

    def _on_own_sample(self, msg: GnssFix | LaneMarkings) -> None:
        """Own sensors, one sample per message."""
        kind = "gnss" if isinstance(msg, GnssFix) else "lane"
        if msg.vehicle != self.cfg.vehicle:
            self.counters["not_for_me"] += 1
            return
        if self.checks.ahead(msg.t, kind) or self.checks.duplicate(kind, (msg.seq, msg.t)):
            return
        self.counters[kind] += 1
        if isinstance(msg, GnssFix) and msg.sigma_v <= 0.0:
            msg = self._course.derive(msg)
            self._count("gnss_position_only")
        if not self.filters:
            if isinstance(msg, GnssFix):  # the filters start from these
                self._pending_fixes.append(msg)
                self._release_imu()
        elif isinstance(msg, GnssFix):
            self._push_fix(msg)
        else:
            self._apply_now(self.seq.push(msg.t, kind, msg))

    def _push_fix(self, fix: GnssFix) -> None:
        """Queue a fix. With the IMU-GNSS time offset estimated, a fix belongs at the filter time
        of its GNSS time, which the offset estimate moves: it is held until the IMU reaches
        that time by the estimate of then (:meth:`_release_fixes`), so that where it is applied
        depends on the data, not on when it arrived."""
        if self.cfg.settings.time_offset is None:
            self._apply_now(self.seq.push(fix.t, "gnss", (fix, 0.0)))
        else:
            heapq.heappush(self._held_fixes, (fix.t, fix.seq, fix))

    def _release_fixes(self, t: float) -> None:
        """Move the held fixes due by the end ``t`` of the next IMU interval into the sequencer,
        each at the filter time of its GNSS time by the current offset estimate."""
        offset = next(iter(self.filters.values())).time_offset
        while self._held_fixes and self._held_fixes[0][0] - offset <= t:
            fix = heapq.heappop(self._held_fixes)[2]
            self._apply_now(self.seq.push(fix.t - offset, "gnss", (fix, offset)))

    def _on_range(self, msg: UwbRange) -> None:
        v = self.cfg.vehicle
        if v not in (msg.a, msg.b) or msg.a == msg.b:
            self.counters["not_for_me"] += 1
            return
        if self.checks.ahead(msg.t, "uwb") or self.checks.duplicate("uwb", (msg.a, msg.b, msg.seq, msg.t)):
            return
        self.counters["uwb"] += 1
        if self.filters:
            self._apply_now(self.seq.push(msg.t, "uwb", msg))

    def _on_round(self, msg: UwbRound) -> None:
        v = self.cfg.vehicle
        if msg.vehicle != v:
            self.counters["not_for_me"] += 1
            return
        if self.checks.ahead(msg.t, "uwb") or self.checks.duplicate("uwb", (msg.seq, msg.t)):
            return
        # each range as the UwbRange of its pair would be (the same sequencer path)
        for peer, r in zip(msg.peers, msg.ranges.tolist()):
            if peer == v:
                self.counters["not_for_me"] += 1
                continue
            self.counters["uwb"] += 1
            if self.filters:
                self._apply_now(self.seq.push(msg.t, "uwb", UwbRange(v, peer, msg.seq, msg.t, r)))

    def _on_beacon(self, msg: Beacon) -> None:
        if msg.vehicle == self.cfg.vehicle or msg.method not in self.tables:
            self.counters["not_for_me"] += 1
            return
        self.counters["beacons_rx"] += 1
        # the cheap checks before the signature's: a flood of stale, future-dated or replayed
        # beacons costs no ECDSA verification (only a verified beacon enters the table, so a
        # forged one cannot make a genuine one look old)
        tab = self.tables[msg.method]
        # before the own clock runs there is no time window to hold a beacon to (and nothing
        # to fuse it with): a flood then would cost a verification per forgery
        refused = "before_clock" if self.seq.t is None else self._stale_or_future(msg)
        if refused:
            self._count(f"beacon_{refused}")
            return
        newest = self._newest_verified.get((msg.vehicle, msg.method), tab.newest_time(msg.vehicle))
        if newest is not None and msg.t <= newest:  # a duplicate or replay: not newer than the last
            tab.counters["duplicate_or_old"] += 1
            return
        if self.cfg.trust is not None:
            outcome = self.cfg.trust.precheck(msg)
            if not outcome and not self._may_verify(msg):
                outcome = "verify_budget"
            outcome = outcome or self.cfg.trust.check_signature(msg)
            if outcome != "ok":
                self._count(f"beacon_{outcome}")
                return
        self.lost.pop(msg.vehicle, None)
        for g in self._ghosts.values():
            g.pop(msg.vehicle, None)
        if msg.vehicle in self.beacons_from or len(self.beacons_from) < self.MAX_SENDERS:
            self.beacons_from[msg.vehicle] = self.beacons_from.get(msg.vehicle, 0) + 1
            self._newest_verified[(msg.vehicle, msg.method)] = msg.t
        if self._untrusted(msg):
            self.excluded_from[msg.vehicle] = self.excluded_from.get(msg.vehicle, 0) + 1
            return
        now = self.seq.t if self.seq.t is not None else msg.t
        tab.update(msg.vehicle, msg.seq, msg.t, msg.llh, msg.v_ned, msg.cov_pos, msg.method, now,
                   msg.sources, msg.constants)
        self._fuse_due(((msg.method, msg.vehicle),))
        if msg.method in self.trackers:
            self.trackers[msg.method].observe_neighbour(msg.vehicle, msg.t, float(np.hypot(*msg.v_ned[:2])),
                                                        msg.first_stopped)

    # ----------------------------------------------------------------- neighbours
    def _count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    # ----------------------------------------------------------------- processing
    def _init_fix(self, batch: ImuBatch) -> GnssFix | None:
        """The fix that would start the filters at the start of ``batch`` (None: none yet)."""
        t0 = float(batch.t[0] - batch.dt[0])
        # a position-only fix without an earlier one has no velocity yet: the next will
        near = [g for g in self._pending_fixes if abs(g.t - t0) <= self.INIT_FIX_WINDOW and math.isfinite(g.sigma_v)]
        return min(near, key=lambda g: (abs(g.t - t0), g.t)) if near else None

    def _init(self, batch: ImuBatch) -> bool:
        """Start the filters at the start of IMU ``batch`` from the GNSS fix nearest in time,
        moved to that time with its velocity (which fixes had arrived when the first batch is
        processed depends on message timing; this choice does not); later fixes are applied as
        measurements. False (nothing started) without a fix within ``INIT_FIX_WINDOW``."""
        t0 = float(batch.t[0] - batch.dt[0])
        fix = self._init_fix(batch)
        if fix is None:
            return False
        later = sorted((g for g in self._pending_fixes if g.t > t0 and g is not fix), key=lambda g: g.t)
        self._pending_fixes.clear()
        f_b = batch.dvel.sum(axis=0) / max(float(batch.dt.sum()), 1e-3)
        llh0 = earth.offset_llh(fix.llh, np.asarray(fix.v_ned, float) * (t0 - fix.t))
        st0 = initial_state(llh0, fix.v_ned, f_b)
        moving = math.hypot(fix.v_ned[0], fix.v_ned[1]) > 1.0
        for m in self.cfg.methods:
            self.filters[m] = MethodFilter(MethodSpec.of(m), st0.copy(), fix.sigma_ned, self.cfg.settings,
                                           t0, self.cfg.gap, self.cfg.origin_llh, heading_known=moving,
                                           vehicle=self.cfg.vehicle)
        self.seq.t = t0
        for name, rate in (("beacon", self.cfg.beacon_rate), ("estimate", self.cfg.estimate_rate),
                           ("decision", self.cfg.decision_rate), ("diag", 1.0)):
            self._next[name] = self.seq.t + 1.0 / rate
        self._timer_due = min(self._next.values())
        log.info("%s: initialised %s at t=%.2f", self.cfg.vehicle, ",".join(self.cfg.methods), self.seq.t)
        for g in later:
            self._push_fix(g)
        return True

    def _apply_now(self, steps: list[Apply]) -> None:
        for s in steps:
            self._apply(s)

    def _apply(self, step: Apply) -> None:
        msg = step.payload
        if step.kind == "gnss":
            fix, offset = msg
            self.zupt_gate.gnss(step.t)
            for f in self.filters.values():
                f.gnss(fix.llh, fix.v_ned, fix.sigma_ned, fix.sigma_v, fix.quality, applied_offset=offset,
                       velocity=has_velocity(fix))
        elif step.kind == "lane":
            for tr in self.trackers.values():
                tr.observe_markings(step.t, msg.left, msg.right)
        elif step.kind == "uwb":
            other = msg.b if msg.a == self.cfg.vehicle else msg.a
            mb = self.misbehaviour
            if mb is not None:
                own = self.filters.get("SP") or next(iter(self.filters.values()))  # own sensors only
                was = other in mb.flagged
                mb.range(other, step.t, msg.range_m, own.filter.state.llh, own.position_cov,
                         self.cfg.settings.sigma_uwb)
                if mb.excluded(other, step.t):
                    if not was:
                        self._exclude(other)
                    self._count("range_excluded")
                    return
            for tr in self.trackers.values():  # who stands beside me (first-stopped decisions)
                tr.observe_range(other, step.t, msg.range_m, self.cfg.settings.sigma_uwb)
            keys = []
            for m, f in self.filters.items():
                if f.spec.ranges:
                    self._deferred.append((step.t, m, other, msg.range_m))
                    keys.append((m, other))
                    self._deferred_min[(m, other)] = min(self._deferred_min.get((m, other), step.t), step.t)
            self._fuse_due(keys)

    def _fuse_due(self, keys) -> None:
        """:meth:`_fuse_ranges` if a deferred range may be due: one of (method, neighbour)
        ``keys``, whose beacons or ranges just changed, has its beacon of that time, or a range
        has waited ``range_defer``. Nothing else makes one due, so skipping the scan otherwise
        changes nothing; a fleet's agent holds dozens of ranges and hears hundreds of beacons
        and ranges a second."""
        if not self._deferred:
            return
        due = max(f.t for f in self.filters.values()) - min(self._deferred_min.values()) >= self.cfg.range_defer
        for m, other in keys:
            first, newest = self._deferred_min.get((m, other)), self.tables[m].newest_time(other)
            due = due or (first is not None and newest is not None and newest >= first)
        if due:
            self._fuse_ranges()

    def _fuse_ranges(self, final: bool = False) -> None:
        """Fuse the ranges whose neighbour beacon of that time has arrived (or that waited
        ``range_defer``); the others keep waiting."""
        keep = []
        for item in self._deferred:
            t, m, other, r = item
            f, tab = self.filters[m], self.tables[m]
            newest = tab.newest_time(other)
            if final or (newest is not None and newest >= t) or f.t - t >= self.cfg.range_defer:
                nb = tab.at(other, t)
                if nb is None:
                    continue
                try:
                    outcome = f.range(nb, r, t)
                except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
                    # an unusable range (e.g. both estimates at one point): counted, dropped
                    self._count("rejected_range")
                    log.debug("%s: range to %s dropped: %s", self.cfg.vehicle, other, exc)
                    continue
                if self.range_observer is not None:
                    self.range_observer(m, other, t, outcome)
            else:
                keep.append(item)
        self._deferred = keep
        self._deferred_min = {}
        for t, m, other, _ in keep:
            k = (m, other)
            self._deferred_min[k] = min(self._deferred_min.get(k, t), t)

    def _decide(self, t: float) -> None:
        for m, tab in self.tables.items():  # neighbours not heard for the table's timeout are gone
            last = dict(tab.entries)
            for other in tab.expire(t):
                self._ghosts.setdefault(m, {})[other] = (last[other].llh, last[other].cov, t)
                self._lose(other, "silence")
        for m, tr in self.trackers.items():
            ghosts = {}
            for o, (llh, cov, lost_at) in list(self._ghosts.get(m, {}).items()):
                age = t - lost_at
                if not age <= self.cfg.ghost_memory:  # also NaN (lost before the filter started)
                    del self._ghosts[m][o]
                    continue
                ghosts[o] = (llh, cov + np.eye(3) * (self.cfg.ghost_speed * age) ** 2)
            dec, changed = first_stopped_step(tr, self.filters[m], self.tables[m], self.cfg.lanes,
                                              self.cfg.origin_llh, t, ghosts, self.cfg.lane_map)
            self.decision_reason[m] = dec.reason
            if changed:
                self.decision_log.append((t, m, dec.reason))
                log.info("%s %s: %s at t=%.1f (%s)", self.cfg.vehicle, m,
                         "first stopped" if dec.first else "not first", t, dec.reason)
            self.counters["decisions"] += 1
        for m, f in self.filters.items():  # cooperative integrity against the own-sensor twin
            own = self.filters.get(OWN_TWIN.get(m, ""))
            if own is not None and check_separation(f, own):
                log.warning("%s %s: separated from %s beyond its integrity gate at t=%.1f; position widened",
                            self.cfg.vehicle, m, OWN_TWIN[m], t)
