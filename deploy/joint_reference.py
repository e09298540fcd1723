"""A reference for the joint fusion: the fleet's measurements processed jointly over time, on the
joint bound's own model.

The joint bound (:mod:`deploy.bound`) is a covariance recursion on the joint state of all
vehicles. The joint reference runs that model as an estimator (:mod:`deploy.joint_filter`), fed
with what the vehicles of an in-process run (:func:`deploy.inprocess.run_inprocess`) measure and
decide, as each would share it (:func:`sharing`):

- its motion as its own INS propagates it: the velocity increments of its own-sensor filter's
  mechanisation (updates left out), with the covariance of its acceleration error that filter
  holds (attitude error times specific force, accelerometer bias);
- its GNSS fixes and ZUPTs; its stop-line fixes while its detector claims first stopped and
  its lane-keeping rows, as its SL-CP filter applies them;
- every UWB range once (both ends receive it), with the vehicles' NLOS link tracking.

It is what *multi-centralized* estimation (Nerurkar and Roumeliotis, IROS 2010: every vehicle
shares its measurement rows and runs the joint filter of its neighbourhood) achieves when every
packet arrives: the yardstick of a distributed rule that shares measurements instead of
intersecting estimates (docs/decisions/0003-joint-fusion.md).

``python -m slcp.deploy.joint_reference paper-1 --seeds 0,1,2 [--relinearise 10]`` prints per
vehicle and window the RMSE, RMSE over the SL-CP bound and ANEES (normalised: 1 when consistent)
of the joint reference beside SL-SP and SL-CP in the same runs; ``--relinearise`` re-runs a
sliding window at the smoothed estimates (:mod:`deploy.joint_window`).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slcp.agent.methods import MethodFilter
from slcp.agent.nav.ins_filter import InsFilter
from slcp.agent.nav.kalman import UpdateResult
from slcp.agent.nav.measurements.stop_line import Line2D, StopLineApproach
from slcp.agent.nav.state import ATT, BA
from slcp.agent.site_updates import SiteUpdates
from slcp.hw_emulation.truth import ScenarioTruth
from slcp.transport.messages import GnssFix, Message, UwbRange, UwbRound

from .agent_configs import agent_config
from .bound import map_ne
from .joint_filter import GAP_, OFF_, RANGE_SIGMA_MAX, JointFilter, Row
from .joint_window import relinearised


@dataclass
class Shared:
    """What the vehicles of one run measured and decided, as they would share it."""

    #: per vehicle and IMU sample: (t, dv_n, dv_e, dt, acceleration error covariance nn, ne, ee)
    ins: dict[str, list[tuple[float, ...]]] = field(default_factory=dict)
    gnss: list[tuple[float, str, GnssFix]] = field(default_factory=list)
    zupt: list[tuple[float, str]] = field(default_factory=list)
    stop: list[tuple[float, str, StopLineApproach, bool, float | None, str | None]] = field(default_factory=list)
    lane: list[tuple[float, str, str, Line2D | None]] = field(default_factory=list)
    ranges: dict[tuple[float, str, str], float] = field(default_factory=dict)

    def on_message(self, vid: str, msg: Message) -> None:
        """What engine ``vid`` was handed: its GNSS fixes and the UWB ranges (once per pair)."""
        if isinstance(msg, GnssFix) and msg.vehicle == vid:
            self.gnss.append((msg.t, vid, msg))
        elif isinstance(msg, UwbRange):
            a, b = sorted((msg.a, msg.b))
            self.ranges[(msg.t, a, b)] = msg.range_m
        elif isinstance(msg, UwbRound):
            for peer, r in zip(msg.peers, msg.ranges):
                a, b = sorted((msg.vehicle, str(peer)))
                self.ranges[(msg.t, a, b)] = float(r)


@contextlib.contextmanager
def sharing(shared: Shared, ins_method: str = "SL-SP", decision_method: str = "SL-CP") -> Iterator[Shared]:
    """Record, while in the block, what every engine's filters would share: the INS velocity
    increments of ``ins_method``'s filter, its ZUPTs, and the stop-line and lane rows of
    ``decision_method``'s. (The engine does not share them yet: its methods are wrapped here,
    and restored on leaving the block.)"""
    prop, run, zupt = MethodFilter.propagate, MethodFilter.propagate_run, MethodFilter.zupt
    stop_line, lane_line = SiteUpdates.stop_line, SiteUpdates.lane_line

    def propagate(self: MethodFilter, dtheta: Any, dvel: Any, dt: float) -> None:
        if self.spec.name != ins_method:
            prop(self, dtheta, dvel, dt)
            return
        v0 = self.filter.state.v
        n0, e0 = float(v0[0]), float(v0[1])
        prop(self, dtheta, dvel, dt)
        f = self.filter
        v1 = f.state.v
        sa = _acceleration_error(f, np.asarray(dvel, float) / dt)
        shared.ins.setdefault(self.vehicle, []).append((f.t, float(v1[0]) - n0, float(v1[1]) - e0, dt,
                                                        sa[0, 0], sa[0, 1], sa[1, 1]))

    def propagate_run(self: MethodFilter, dtheta: Any, dvel: Any, dt: Any) -> None:
        if self.spec.name != ins_method:
            run(self, dtheta, dvel, dt)
            return
        for k in range(len(dt)):  # interval by interval (the same arithmetic): one shared row each
            propagate(self, dtheta[k], dvel[k], dt[k])

    def zupt_(self: MethodFilter) -> UpdateResult | None:
        res = zupt(self)
        if self.spec.name == ins_method and res is not None and res.accepted:
            shared.zupt.append((self.t, self.vehicle))
        return res

    def stop_(self: MethodFilter, approach: StopLineApproach, along_only: bool = False,
              stop_id: float | None = None, lane: str | None = None) -> UpdateResult | None:
        res = stop_line(self, approach, along_only, stop_id, lane)
        if self.spec.name == decision_method and res is not None:
            shared.stop.append((self.t, self.vehicle, approach, along_only, stop_id,
                                lane if self._lane is not None else None))
        return res

    def lane_(self: MethodFilter, ln: str | None, left_line: Line2D | None = None) -> UpdateResult | None:
        res = lane_line(self, ln, left_line)
        if self.spec.name == decision_method and res is not None and res.accepted and ln is not None:
            shared.lane.append((self.t, self.vehicle, ln, left_line))
        return res

    patched = ((MethodFilter, "propagate", propagate, prop), (MethodFilter, "propagate_run", propagate_run, run),
               (MethodFilter, "zupt", zupt_, zupt),
               (SiteUpdates, "stop_line", stop_, stop_line), (SiteUpdates, "lane_line", lane_, lane_line))
    for cls, name, new, _ in patched:
        setattr(cls, name, new)
    try:
        yield shared
    finally:
        for cls, name, _, old in patched:
            setattr(cls, name, old)


def _acceleration_error(f: InsFilter, f_b: np.ndarray) -> np.ndarray:
    """The covariance (2, 2) [m²/s⁴] of the horizontal acceleration error of INS filter ``f``
    (:class:`agent.nav.ins_filter.InsFilter`) at body specific force ``f_b``: its attitude
    error times the specific force and its accelerometer bias error, as its own covariance
    holds them (the velocity rows of :func:`agent.nav.error_model.system_matrix`)."""
    c = f.state.dcm
    fn, fe, fd = (c @ f_b).tolist()
    M = np.zeros((2, 6))
    M[0, 1], M[0, 2], M[1, 0], M[1, 2] = -fd, fe, fd, -fn
    M[:, 3:] = -c[:2]
    k = np.r_[ATT.start:ATT.stop, BA.start:BA.stop]
    out: np.ndarray = M @ f.P[np.ix_(k, k)] @ M.T
    return out


#: one step of the joint reference: (sensor time [s], the vehicles' INS increments up to it,
#: the shared events of that instant or None, the output index or None)
Step = tuple[float, dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]], list[tuple[Any, ...]] | None,
             int | None]


def run_joint(truth: ScenarioTruth, shared: Shared, step: float = 0.1, acc_scale: float = 1.0,
              use_ranges: bool = True, use_site: bool = True, relinearise: float = 0.0,
              ) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The joint reference over a run's shared data: output times (n,) every ``step`` s, per
    vehicle the position estimates (n, 2) [map north, east; m] and covariances (n, 2, 2) [m²]
    (NaN before its start), each as the filter had it at that time. ``acc_scale`` scales the σ
    of the vehicles' INS acceleration error that their own filters report; ``use_ranges`` and
    ``use_site`` leave out the UWB ranges or the stop-line and lane rows; ``relinearise`` > 0
    re-runs, once a second, the last that many seconds with every row linearised at the
    smoothed estimates (:func:`deploy.joint_window.relinearised`)."""
    scn = truth.scenario
    origin = scn.origin_llh
    ids = sorted(truth.vehicles)
    t0 = float(truth.vehicles[ids[0]].truth.t[0])
    ts, steps = _schedule(truth, shared, step, use_ranges, use_site)
    # the vehicles' own range models and NLOS link tracking, as an agent of the fleet carries them
    settings = agent_config(scn, ids[0], ("SL-CP",)).settings
    zupt_sigma = settings.zupt_sigma or 0.02
    jf = JointFilter(scn, ids, t0, settings, acc_scale, keep_links=relinearise > 0.0)
    est = {v: np.full((len(ts), 2), np.nan) for v in ids}
    cov = {v: np.full((len(ts), 2, 2), np.nan) for v in ids}

    def do(f: JointFilter, st: Step, x0: np.ndarray | None) -> None:
        t, incr, evs, _ = st
        f.predict(t, incr)
        if evs:
            rows: list[Row] = []
            for ev in evs:
                rows += _rows_of(f, ev, t, origin, zupt_sigma)
            f.update(rows, iterations=3 if x0 is None else 1, x0=x0)

    def output(f: JointFilter, k: int) -> None:
        for v in f.started:
            b = f.ix[v]
            est[v][k] = f.x[b:b + 2]
            cov[v][k] = f.P[b:b + 2, b:b + 2]

    if relinearise > 0.0:
        relinearised(jf, steps, do, output, relinearise)
    else:
        for st in steps:
            do(jf, st, None)
            if st[3] is not None:
                output(jf, st[3])
    return ts, est, cov


def _schedule(truth: ScenarioTruth, shared: Shared, step: float, use_ranges: bool, use_site: bool,
              ) -> tuple[np.ndarray, list[Step]]:
    """The output times and the steps of the joint reference: every instant with shared events
    and every output time, in time order, each with the INS increments since the last."""
    ids = sorted(truth.vehicles)
    t0 = float(truth.vehicles[ids[0]].truth.t[0])
    t1 = float(truth.vehicles[ids[0]].truth.t[-1])
    ts = np.arange(t0 + step, t1 + 1e-9, step)
    events: list[tuple[float, int, tuple[Any, ...]]] = []
    for t, vid, fix in shared.gnss:
        events.append((t, 0, ("gnss", vid, fix)))
    for t, vid in shared.zupt:
        events.append((t, 1, ("zupt", vid)))
    if use_site:
        for t, vid, appr, along, sid, ln in shared.stop:
            events.append((t, 2, ("stop", vid, appr, along, sid, ln)))
        for t, vid, ln, line in shared.lane:
            events.append((t, 3, ("lane", vid, ln, line)))
    if use_ranges:
        for (t, a, c), r in shared.ranges.items():
            events.append((t, 4, ("range", a, c, r)))
    events.sort(key=lambda e: (e[0], e[1]))
    ins = {v: np.array(shared.ins.get(v, []), float).reshape(-1, 7) for v in ids}
    ins_k = {v: 0 for v in ids}

    def increments(t: float) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
        """The INS increments of every sample ending after the last step and by ``t``."""
        incr: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}
        for v in ids:
            arr, i = ins[v], ins_k[v]
            j = int(np.searchsorted(arr[:, 0], t + 1e-9, side="right"))
            if j > i:
                dv = arr[i:j, 1:3]
                cum = np.cumsum(dv, axis=0)
                # displacement beyond the initial velocity: the mid-sample velocity change
                dp = ((cum - dv / 2) * arr[i:j, 3:4]).sum(axis=0)
                s = arr[j - 1, 4:7]
                incr[v] = (cum[-1], dp, np.array([[s[0], s[1]], [s[1], s[2]]]))
            ins_k[v] = j
        return incr

    steps: list[Step] = []
    e_i, k = 0, 0
    while k < len(ts):
        # the events of one instant, or the next output time, whichever comes first
        if e_i < len(events) and events[e_i][0] <= ts[k] + 1e-9:
            te = events[e_i][0]
            evs = []
            while e_i < len(events) and events[e_i][0] <= te + 1e-9:
                evs.append(events[e_i][2])
                e_i += 1
            steps.append((te, increments(te), evs, None))
            continue
        steps.append((float(ts[k]), increments(float(ts[k])), None, k))
        k += 1
    return ts, steps


def _rows_of(jf: JointFilter, ev: tuple[Any, ...], te: float, origin: tuple[float, float, float],
             zupt_sigma: float) -> list[Row]:
    """The rows of one shared event at time ``te`` (a vehicle's first fix starts it instead)."""
    kind, vid = ev[0], ev[1]
    if kind == "gnss":
        fix = ev[2]
        jf.moving[vid] = math.hypot(fix.v_ned[0], fix.v_ned[1]) >= 0.5
        if vid not in jf.started:
            jf.start(vid, fix, origin)
        return jf.gnss_rows(te, vid, fix, origin)
    if vid not in jf.started:
        return []
    if kind == "zupt":
        return [jf.zupt_row(te, vid, zupt_sigma)]
    if kind == "stop":
        _, _, appr, along, sid, ln = ev
        if sid != jf.stop_id[vid]:
            sg = jf.specs[vid]
            jf.stop_id[vid] = sid
            jf.reset(vid, [GAP_, GAP_ + 1], [sg.stop_gap[1] ** 2, sg.lateral[1] ** 2])
        if ln is not None:
            _enter_lane(jf, vid, ln)
        return [jf.stop_rows(te, vid, appr, along, ln is not None)]
    if kind == "lane":
        _, _, ln, line = ev
        _enter_lane(jf, vid, ln)
        return [jf.lane_row(te, vid, line)]
    _, a, c, r = ev  # a range: once both ends are known well enough for its linearisation
    if c not in jf.started or jf.relative_sigma(a, c) > r * RANGE_SIGMA_MAX:
        return []
    row = jf.range_row(te, a, c, r)
    return [] if row is None else [row]


def _enter_lane(jf: JointFilter, vid: str, ln: str) -> None:
    if ln != jf.lane[vid]:
        jf.lane[vid] = ln
        jf.reset(vid, [OFF_], [jf.specs[vid].lateral[1] ** 2])


def score(truth: ScenarioTruth, seed: int, step: float = 0.1, acc_scale: float = 1.0,
          relinearise: float = 0.0) -> dict[str, Any]:
    """One seed: per vehicle and window, sums of squared error, NEES and squared bound, and
    counts, for the joint reference and for SL-CP and SL-SP of the same in-process run."""
    from slcp.hw_emulation.events import window_bounds

    from .bound import posterior_crlb
    from .inprocess import run_inprocess

    shared = Shared()
    with sharing(shared):
        res = run_inprocess(truth, seed, methods=("SL-SP", "SL-CP"), on_message=shared.on_message)
    ts, est, cov = run_joint(truth, shared, step, acc_scale, relinearise=relinearise)
    bound = posterior_crlb(truth, ("SL-CP",))
    origin = truth.scenario.origin_llh
    out: dict[str, Any] = {}
    for w, (wa, wb) in window_bounds(truth).items():
        for v, vt in truth.vehicles.items():
            rows = {}
            sel = (ts >= wa) & (ts <= wb) & np.isfinite(est[v][:, 0])
            tru = map_ne(vt.truth.llh[vt.samples_over(ts[sel])], origin)
            rows["joint"] = (est[v][sel] - tru, cov[v][sel], ts[sel])
            sel2 = (res.t >= wa) & (res.t <= wb)
            for m in ("SL-SP", "SL-CP"):
                e = res.err_ne[(v, m)][sel2]
                ok = np.isfinite(e[:, 0])
                rows[m] = (e[ok], res.cov_ne[(v, m)][sel2][ok], res.t[sel2][ok])
            for name, (e, c, tt) in rows.items():
                if not len(e):
                    continue
                q = np.einsum("ni,ni->n", e, np.linalg.solve(c, e[..., None])[..., 0])
                b = bound.at("SL-CP", v, tt)
                out.setdefault(w, {}).setdefault(v, {})[name] = {
                    "se": float(np.sum(e**2)), "nees": float(np.sum(q)), "b2": float(np.sum(b**2)), "n": len(e)}
    return out


def main(argv: list[str] | None = None) -> int:
    from .pooling import seeded_sums

    def options(ap: argparse.ArgumentParser) -> None:
        ap.add_argument("--step", type=float, default=0.1, help="output step [s] (default 0.1)")
        ap.add_argument("--acc-scale", type=float, default=1.0,
                        help="scale of the σ of the INS acceleration error the vehicles' filters report (default 1)")
        ap.add_argument("--relinearise", type=float, default=0.0, metavar="SECONDS",
                        help="re-run the last SECONDS once a second, every row linearised at the smoothed "
                             "estimates (default 0: a plain iterated EKF)")

    got = seeded_sums("joint_reference", (__doc__ or "").split("\n\n")[0], argv,
                      lambda truth, seed, a: score(truth, seed, a.step, a.acc_scale, a.relinearise), options)
    if got is None:
        return 2
    args, scn, total = got
    print(f"{scn.name}, seeds {args.seeds}: RMSE [m] / RMSE over the SL-CP bound / ANEES (1 when consistent)")
    for w, per_v in total.items():
        print(f"window {w}")
        for v, rows in sorted(per_v.items()):
            first = next(iter(rows.values()))
            b = math.sqrt(first["b2"] / first["n"])
            cells = [f"{name} {math.sqrt(r['se'] / r['n']):6.3f} / {math.sqrt(r['se'] / r['n']) / b:5.2f} / "
                     f"{r['nees'] / r['n'] / 2:5.2f}" for name, r in rows.items()]
            print(f"  {v:6s} bound {b:6.3f}  " + "   ".join(cells))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
