"""The engine's IMU path: each batch's intervals integrated in every filter, split at the
measurements queued inside them, with rest detection and the output timers at their rates (a
mixin of :class:`agent.engine.VehicleEngine`).

Runs of intervals with nothing inside them are integrated with one mechanisation call per
filter (:meth:`agent.methods.MethodFilter.propagate_run`): the same arithmetic in the same order
as one call per interval, at a fraction of the Python overhead, which dominates at 100 Hz.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from slcp.transport.messages import GnssFix, ImuBatch

from .methods import MethodFilter
from .nav.motion import StationarityMonitor, ZuptGate, speed_sigma
from .sequencer import Apply, Propagate, Sequencer


class EngineImu:
    """The IMU stream through the filters."""

    filters: dict[str, MethodFilter]
    seq: Sequencer
    rest: StationarityMonitor
    zupt_gate: ZuptGate
    _held_fixes: list[tuple[float, int, GnssFix]]
    _rest_checked: float
    _timer_due: float
    _init: Callable[[ImuBatch], bool]
    _timers: Callable[[float], None]
    _fuse_due: Callable[..., None]
    _release_fixes: Callable[[float], None]
    _apply: Callable[[Apply], None]

    def _imu(self, msg: ImuBatch) -> None:
        if not self.filters:
            if not self._init(msg):
                self.counters["before_init"] += 1
                return
        seq = self.seq
        ts, dts = msg.t.tolist(), msg.dt.tolist()
        ths, dvs = msg.dtheta.tolist(), msg.dvel.tolist()
        rest_from = 0  # first sample not yet in the rest detector
        run: tuple[list, list, list] = ([], [], [])  # plain intervals not yet integrated
        for k in range(len(ts)):
            t = ts[k]
            if seq.t is not None and t <= seq.t:  # behind the filter: not used at all
                seq.counters["imu_out_of_order"] += 1
                continue
            if not self._plain(t, dts[k]):
                self._integrate(run)
                self._step(t, ths[k], dvs[k], dts[k])
            else:  # the common case: no measurement inside the interval
                span = seq.imu_plain(t, dts[k])
                if span is not None:
                    run[0].append(ths[k])
                    run[1].append(dvs[k])
                    run[2].append(span)
            # rest detection and ZUPT at the gate's rate, on the samples since the last check
            rest_due = k == len(ts) - 1 or t - self._rest_checked >= self.zupt_gate.interval
            if rest_due or t >= self._timer_due:
                self._integrate(run)
                if rest_due:
                    self._rest(t, msg, rest_from, k + 1)
                    rest_from = k + 1
                if t >= self._timer_due:
                    self._timers(t)
        self._integrate(run)
        self._fuse_due(())

    def _plain(self, t: float, dt: float) -> bool:
        """Whether the IMU interval ending at ``t`` needs nothing but integration: no held fix
        due, no data gap before it, no measurement queued inside it (the filters' time-offset
        estimate, which decides when a held fix is due, does not move while they integrate)."""
        if self._held_fixes and self._held_fixes[0][0] - next(iter(self.filters.values())).time_offset <= t:
            return False
        return self.seq.gap_before(t, dt) == 0.0 and not self.seq.pending_by(t)

    def _integrate(self, run: tuple[list, list, list]) -> None:
        """Integrate the plain intervals collected in ``run`` in every filter, and empty it: one
        mechanisation call per filter for the run, the same arithmetic as one per interval."""
        if run[2]:
            for f in self.filters.values():
                f.propagate_run(*run)
            for part in run:
                part.clear()

    def _step(self, t: float, dtheta: list[float], dvel: list[float], dt: float) -> None:
        """One IMU interval ending at ``t``, split at the measurements queued inside it."""
        if self._held_fixes:
            self._release_fixes(t)
        seq = self.seq
        gap = seq.gap_before(t, dt)
        if gap > 0.0:  # no IMU data for a while (a frozen process, a sensor outage)
            for f in self.filters.values():
                f.coast_gap(gap)
            seq.skip_gap(gap)
        filters = self.filters.values()
        if not seq.pending_by(t):
            span = seq.imu_plain(t, dt)
            if span is not None:
                for f in filters:
                    f.propagate(dtheta, dvel, span)
            return
        for step in seq.imu(t, dtheta, dvel, dt):
            if isinstance(step, Propagate):
                for f in filters:
                    f.propagate(step.dtheta, step.dvel, step.dt)
            else:
                self._apply(step)

    def _rest(self, t: float, msg: ImuBatch, a: int, b: int) -> None:
        """Rest detection on samples ``a:b`` of ``msg``, and a ZUPT of every filter if due."""
        self._rest_checked = t
        ref = next(iter(self.filters.values())).filter
        self.rest.push_batch(msg.dtheta[a:b], msg.dvel[a:b], msg.dt[a:b], ref.state.dcm)
        v = ref.state.v
        if self.zupt_gate.due(t, self.rest, math.hypot(v[0], v[1]),
                              lambda: speed_sigma(ref.state.v, ref.velocity_cov)):
            for f in self.filters.values():
                f.zupt()
        elif self.cfg.settings.nhc_sigma is not None or self.cfg.settings.zaru_sigma is not None:
            # at rest: the IMU shows it and the filter agrees (cruising at a steady speed looks
            # like rest to a smooth IMU)
            at_rest = math.hypot(v[0], v[1]) < self.zupt_gate.max_speed and self.rest.stationary
            for f in self.filters.values():
                if at_rest:
                    f.own.zaru()
                else:
                    f.coast(True)
