"""The joint filter of the joint reference (:mod:`deploy.joint_reference`): an iterated EKF on
the joint bound's model (:mod:`deploy.bound`), fed with measured rows.

Per vehicle the state is position, velocity, INS acceleration error (north, east each), GNSS
multipath (2), stop-gap errors (2) and lane offset (1); then the GNSS common mode (2), shared;
then one NLOS bias per UWB link in use, a *consider* state (its estimate the link tracker's, its
covariance carried exactly). A vehicle moves as its INS says (velocity increments
from its own filter), its acceleration error a Gauss-Markov process with the covariance its own
filter holds. Rows: GNSS position (on position + multipath + common mode) and velocity, ZUPT,
stop-line fix, lane keeping, UWB range (on the two positions and the link's bias). Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from slcp.agent.methods import FilterSettings
from slcp.agent.nav.measurements.stop_line import Line2D, StopLineApproach, stop_line_fix
from slcp.agent.range_gate import NlosLinkTracker
from slcp.agent.range_geometry import STANDING_SPEED
from slcp.agent.site_updates import STOP_LINE_MAP_SIGMA
from slcp.hw_emulation.scenario import Scenario
from slcp.transport.messages import GnssFix

from .bound import map_ne

#: per vehicle: p (2), v (2), acceleration error (2), multipath (2), stop gap (2), lane offset (1)
NV = 11
P_, V_, A_, MP_, GAP_, OFF_ = 0, 2, 4, 6, 8, 10
#: the INS's horizontal acceleration error (residual accelerometer bias and tilt × g) [m/s²], τ [s]
ACC_SIGMA = 0.005
#: τ [s] of the INS acceleration error: its autocorrelation falls to a half within 1-2 s (the
#: INS of the shipped scenarios' vehicles, measured against the emulated truth)
ACC_TAU = 2.0
#: a vehicle's state starts at its first fix with these σ [m, m/s], before the fix's rows
START_SIGMA_P, START_SIGMA_V = 1000.0, 50.0
#: a range is used once the σ of its ends' relative position across the line of sight is below
#: this fraction of it (the line of sight known to about 10°: the range's linearisation holds;
#: a first fix far off otherwise pulls a vehicle towards a mirror image)
RANGE_SIGMA_MAX = 0.2
#: a vehicle's own row this many σ off its prediction re-anchors it (:meth:`JointFilter._reanchor`)
REANCHOR_D = 6.0
REANCHOR_KINDS = ("gnss", "lane", "stop", "stop_along")
#: a UWB link silent this long [s] loses its bias state
LINK_IDLE = 10.0
#: Huber's bound on a row's normalised innovation, by kind of row (the others are not robust)
HUBER_K = {"range": 2.0, "gnss": 3.0}

#: a row's model: (state, how long before the filter time [s]) -> (h (m,), H (m, n))
RowFn = Callable[[np.ndarray, float], tuple[np.ndarray, np.ndarray]]


@dataclass
class Row:
    """One measurement row block at time ``t``: ``h(x)`` and its Jacobian from ``fn``."""

    t: float
    z: np.ndarray
    R: np.ndarray
    fn: RowFn  #: (state, how long before the filter time) -> (h (m,), H (m, n))
    kind: str


class JointFilter:
    """The joint iterated EKF over the vehicles ``ids`` of scenario ``scn`` (their
    GNSS, IMU, stop-gap and lane models), with the vehicles' range and NLOS ``settings`` and
    their INS acceleration-error covariance scaled by ``acc_scale``."""

    def __init__(self, scn: Scenario, ids: list[str], t0: float, settings: FilterSettings,
                 acc_scale: float = 1.0, keep_links: bool = False) -> None:
        self.scn = scn
        self.settings = settings
        self.acc_scale = acc_scale
        self.nlos = (NlosLinkTracker(settings.uwb_nlos, settings.sigma_uwb)
                     if settings.uwb_nlos is not None and settings.nlos_link_tracking else None)
        self.specs = {v.id: v for v in scn.vehicles}
        self.ids = ids
        self.ix = {v: NV * i for i, v in enumerate(ids)}
        self.n = NV * len(ids) + 2
        self.cm = NV * len(ids)  #: first of the two common-mode states
        self.cms = slice(self.cm, self.cm + 2)
        #: per UWB link ("A|B"): the index of its NLOS bias state (appended after the common
        #: mode), the sensor time of its last range and the bias's variance then [m²]
        self.links: dict[str, list[Any]] = {}
        self.x = np.zeros(self.n)
        self.P = np.zeros((self.n, self.n))
        self.t = t0
        self.started: set[str] = set()
        self.moving = {v: True for v in ids}
        self.stop_id: dict[str, float | None] = {v: None for v in ids}
        self.lane: dict[str, str | None] = {v: None for v in ids}
        self.P[self.cms, self.cms] = np.eye(2) * scn.common_mode_sigma**2
        self.counters = {"rows": 0}
        #: every link's bias state from the start, none dropped: the state's size never changes
        #: (a window re-run over it needs that, :mod:`deploy.joint_window`)
        self.keep_links = keep_links
        #: the last prediction: (x, P, F) (F None: no time passed), kept with ``keep_links`` only
        self.last_pred: tuple[np.ndarray, np.ndarray, np.ndarray | None] = (self.x, self.P, None)
        if keep_links and settings.uwb_nlos is not None:
            for i, a in enumerate(ids):
                for c in ids[i + 1:]:
                    self._link_state(f"{min(a, c)}|{max(a, c)}", t0, None)

    # ------------------------------------------------------------------ state
    def start(self, vid: str, fix: GnssFix, origin: tuple[float, float, float]) -> None:
        b = self.ix[vid]
        g, sg = self.specs[vid].gnss, self.specs[vid]
        self.x[b:b + 2] = map_ne(np.asarray(fix.llh, float)[None], origin)[0]
        self.x[b + V_:b + V_ + 2] = fix.v_ned[:2]
        d = np.zeros(NV)
        d[P_:P_ + 2] = START_SIGMA_P**2  # the first fix is then applied as a row, like any other
        d[V_:V_ + 2] = START_SIGMA_V**2
        d[A_:A_ + 2] = ACC_SIGMA**2
        d[MP_:MP_ + 2] = g.multipath_h**2
        d[GAP_:GAP_ + 2] = (sg.stop_gap[1] ** 2, sg.lateral[1] ** 2)
        d[OFF_] = sg.lateral[1] ** 2
        self.P[b:b + NV, b:b + NV] = np.diag(d)
        self.started.add(vid)

    def relative(self, a: str, c: str) -> tuple[np.ndarray, np.ndarray]:
        """The position of ``a`` relative to ``c`` now (2,) [m] and its covariance (2, 2) [m²]."""
        i, j = self.ix[a], self.ix[c]
        P = self.P
        Pr = P[i:i + 2, i:i + 2] + P[j:j + 2, j:j + 2] - P[i:i + 2, j:j + 2] - P[j:j + 2, i:i + 2]
        return self.x[i:i + 2] - self.x[j:j + 2], Pr

    def relative_sigma(self, a: str, c: str) -> float:
        """σ [m] of the position of ``a`` relative to ``c`` across their line of sight now:
        the uncertainty of the line of sight's direction, times the range."""
        d, Pr = self.relative(a, c)
        w = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-3)
        return math.sqrt(max(float(w @ Pr @ w), 0.0))

    def reset_state(self, k: int, value: float, var: float) -> None:
        """State ``k`` drawn afresh: ``value`` with variance ``var``, uncorrelated."""
        self.x[k] = value
        self.P[k, :] = 0.0
        self.P[:, k] = 0.0
        self.P[k, k] = var

    def reset(self, vid: str, states: list[int], var: list[float]) -> None:
        """New random constants (a new stop's gap, a new lane's offset): back to their prior."""
        for s, v in zip(states, var):
            self.reset_state(self.ix[vid] + s, 0.0, v)

    def predict(self, t: float, ins: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]]) -> None:
        """To time ``t`` with each vehicle's INS over the step: its velocity increment ``dv``
        (2,) [m/s], the displacement ``dp`` (2,) [m] it makes beyond the initial velocity, and
        the covariance (2, 2) [m²/s⁴] of its acceleration error (None: :data:`ACC_SIGMA`)."""
        dt = t - self.t
        if dt <= 0.0:
            if self.keep_links:
                self.last_pred = (self.x.copy(), self.P.copy(), None)
            return
        n = self.n
        F = np.eye(n)
        Q = np.zeros((n, n))
        for vid in self.started:
            b = self.ix[vid]
            sg = self.specs[vid]
            dv, dp, sa = ins.get(vid, (np.zeros(2), np.zeros(2), None))
            qa = np.eye(2) * ACC_SIGMA**2 if sa is None else sa * self.acc_scale**2
            x = self.x
            aa = math.exp(-dt / ACC_TAU)
            a = x[b + A_:b + A_ + 2].copy()
            x[b + P_:b + P_ + 2] += x[b + V_:b + V_ + 2] * dt + dp + a * dt * dt / 2
            x[b + V_:b + V_ + 2] += dv + a * dt
            x[b + A_:b + A_ + 2] = a * aa
            tau = sg.gnss.multipath_tau_moving if self.moving[vid] else sg.gnss.multipath_tau_static
            am = math.exp(-dt / tau)
            x[b + MP_:b + MP_ + 2] *= am
            for k in range(2):
                p, v, ac, mp = b + P_ + k, b + V_ + k, b + A_ + k, b + MP_ + k
                F[p, v], F[p, ac], F[v, ac], F[ac, ac], F[mp, mp] = dt, dt * dt / 2, dt, aa, am
                q = sg.imu.vrw**2
                Q[p, p] += dt**3 / 3 * q
                Q[p, v] += dt**2 / 2 * q
                Q[v, p] += dt**2 / 2 * q
                Q[v, v] += dt * q
                Q[mp, mp] = sg.gnss.multipath_h**2 * (1 - am * am)
            ka = slice(b + A_, b + A_ + 2)
            Q[ka, ka] = qa * (1 - aa * aa)
        acm = math.exp(-dt / self.scn.common_mode_tau)
        self.x[self.cms] *= acm
        F[self.cms, self.cms] = np.eye(2) * acm
        Q[self.cms, self.cms] = np.eye(2) * self.scn.common_mode_sigma**2 * (1 - acm * acm)
        if self.links and self.settings.uwb_nlos is not None:
            nl = self.settings.uwb_nlos
            al = math.exp(-dt * nl.exit)  # an episode lasts 1/exit on average
            for li, _, bv in self.links.values():
                self.x[li] *= al
                F[li, li] = al
                Q[li, li] = bv * (1 - al * al)
        self.P = F @ self.P @ F.T + Q
        self.t = t
        if self.keep_links:  # only a window re-run reads it (:mod:`deploy.joint_window`)
            self.last_pred = (self.x.copy(), self.P.copy(), F)

    def update(self, rows: list[Row], iterations: int = 3, x0: np.ndarray | None = None) -> None:
        """An iterated EKF step on ``rows`` (Gauss-Newton about the prediction, the links' biases
        held as consider states), robust (Huber): a row whose innovation at the current
        iterate lies beyond :data:`HUBER_K` σ of its predicted spread counts with its noise
        inflated to keep its pull at that bound (an NLOS range, a multipath jump, and the first
        ranges to a vehicle whose first fixes were far off are weighed, not dropped: a hard
        gate that drops the ranges to a vehicle once kept dropping them as its σ shrank)."""
        if not rows:
            return
        self._reanchor(rows)
        P = self.P
        x_pred = self.x.copy()
        x = x_pred.copy() if x0 is None else x0.copy()
        spread = []
        for r in rows:
            _, H = r.fn(x, self.t - r.t)
            spread.append(np.linalg.inv(H @ P @ H.T + r.R))
        self.counters["rows"] += len(rows)
        # the links' biases are *consider* states (Schmidt): the ranges never move them, their
        # covariance is carried exactly, so that a link's ranges do not average its bias away
        # and a geometry error cannot hide in it
        consider = [e[0] for e in self.links.values()]
        K: np.ndarray = np.zeros((self.n, 0))
        Hs: np.ndarray = np.zeros((0, self.n))
        S: np.ndarray = np.zeros((0, 0))
        for _ in range(iterations):
            Hl: list[np.ndarray] = []
            nus: list[np.ndarray] = []
            Rl: list[np.ndarray] = []
            for r, Si in zip(rows, spread):
                h, H = r.fn(x, self.t - r.t)
                nu = r.z - h
                d = math.sqrt(max(float(nu @ Si @ nu), 0.0))
                k = HUBER_K.get(r.kind)
                w = 1.0 if k is None or d <= k else k / d
                Hl.append(H)
                nus.append(nu + H @ (x - x_pred))
                Rl.append(r.R / w)
            Hs = np.vstack(Hl)
            R = np.zeros((len(Hs), len(Hs)))
            o = 0
            for Rr in Rl:
                R[o:o + len(Rr), o:o + len(Rr)] = Rr
                o += len(Rr)
            S = Hs @ P @ Hs.T + R
            K = np.linalg.solve(S, Hs @ P).T
            if consider:
                K[consider] = 0.0
            x = x_pred + K @ np.concatenate(nus)
        self.x = x
        # any gain: P - K H P - P Hᵀ Kᵀ + K S Kᵀ
        KHP = K @ (Hs @ P)
        self.P = P - KHP - KHP.T + K @ S @ K.T
        self.P = 0.5 * (self.P + self.P.T)

    def _reanchor(self, rows: list[Row]) -> None:
        """A vehicle's own row (a fix, its lane, its stop line) far outside its predicted spread
        shows the joint estimate overconfident about that vehicle (early ranges fitted to a
        wrong geometry, a mirror image): its position and velocity are let go, decorrelated
        from the rest, before the rows are applied, so that its own rows place it again and the
        ranges then tie it in afresh."""
        for r in rows:
            if r.kind not in REANCHOR_KINDS:
                continue
            h, H = r.fn(self.x, self.t - r.t)
            nu = r.z - h
            if float(nu @ np.linalg.solve(H @ self.P @ H.T + r.R, nu)) <= REANCHOR_D**2:
                continue
            b = self._owner(H)
            k = np.r_[b + P_:b + V_ + 2]
            keep = np.diag(self.P)[k]
            self.P[k, :] = 0.0
            self.P[:, k] = 0.0
            self.P[k, k] = np.maximum(keep, np.r_[[float(nu @ nu) + 1.0] * 2, [1.0, 1.0]])
            self.counters["reanchored"] = self.counters.get("reanchored", 0) + 1

    def _owner(self, H: np.ndarray) -> int:
        """The first state of the vehicle whose position a row ``H`` observes."""
        c = int(np.flatnonzero(np.abs(H[:, :self.cm]).sum(axis=0))[0])
        return NV * (c // NV)

    # ------------------------------------------------------------------ rows
    def _pos(self, vid: str, x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
        """Position of ``vid`` ``back`` seconds before the filter time, and its Jacobian."""
        b = self.ix[vid]
        J = np.zeros((2, self.n))
        J[:, b + P_:b + P_ + 2] = np.eye(2)
        J[:, b + V_:b + V_ + 2] = -back * np.eye(2)
        return x[b + P_:b + P_ + 2] - back * x[b + V_:b + V_ + 2], J

    def gnss_rows(self, t: float, vid: str, fix: GnssFix, origin: tuple[float, float, float]) -> list[Row]:
        g = self.specs[vid].gnss
        b = self.ix[vid]
        z = map_ne(np.asarray(fix.llh, float)[None], origin)[0]

        def pos(x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
            p, J = self._pos(vid, x, back)
            J[:, b + MP_:b + MP_ + 2] += np.eye(2)
            J[:, self.cms] += np.eye(2)
            return p + x[b + MP_:b + MP_ + 2] + x[self.cms], J

        rows = [Row(t, z, np.eye(2) * max(g.white_h, 0.05) ** 2, pos, "gnss")]
        if fix.sigma_v > 0.0:
            def vel(x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
                J = np.zeros((2, self.n))
                J[:, b + V_:b + V_ + 2] = np.eye(2)
                return x[b + V_:b + V_ + 2], J
            rows.append(Row(t, np.asarray(fix.v_ned[:2], float), np.eye(2) * max(g.velocity_white, 0.02) ** 2,
                             vel, "gnss_v"))
        return rows

    def zupt_row(self, t: float, vid: str, sigma: float) -> Row:
        b = self.ix[vid]

        def vel(x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
            J = np.zeros((2, self.n))
            J[:, b + V_:b + V_ + 2] = np.eye(2)
            return x[b + V_:b + V_ + 2], J
        return Row(t, np.zeros(2), np.eye(2) * sigma**2, vel, "zupt")

    def stop_rows(self, t: float, vid: str, approach: StopLineApproach, along_only: bool, lane_kept: bool) -> Row:
        sg = self.specs[vid]
        b = self.ix[vid]
        p_fix, J = stop_line_fix(approach, sg.stop_gap[0] + sg.l0, sg.lateral[0])
        cols = [b + GAP_, b + OFF_ if lane_kept else b + GAP_ + 1]

        def fn(x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
            p, Hp = self._pos(vid, x, back)
            Hp[:, cols] -= J
            return p - J @ x[cols], Hp
        if along_only:
            ns = approach.stop_line_normal()

            def along(x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
                h, H = fn(x, back)
                return np.array([ns @ h]), (ns @ H)[None]
            return Row(t, np.array([ns @ p_fix]), np.eye(1) * STOP_LINE_MAP_SIGMA**2, along, "stop_along")
        return Row(t, p_fix, np.eye(2) * STOP_LINE_MAP_SIGMA**2, fn, "stop")

    def lane_row(self, t: float, vid: str, line: Line2D) -> Row:
        sg = self.specs[vid]
        b = self.ix[vid]
        nr = np.asarray(line.right_normal, float)

        def fn(x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
            p, Hp = self._pos(vid, x, back)
            H = (nr @ Hp)[None]
            H[0, b + OFF_] -= 1.0
            return np.array([nr @ p - x[b + OFF_]]), H
        return Row(t, np.array([nr @ np.asarray(line.point, float) + sg.lateral[0]]),
                    np.eye(1) * STOP_LINE_MAP_SIGMA**2, fn, "lane")

    def range_row(self, t: float, a: str, c: str, r: float) -> Row | None:
        """A UWB range between ``a`` and ``c`` (None: judged an outlier or NLOS). Its noise
        holds the second-order term of the linearisation, σ⊥⁴ / (2 r²) with σ⊥² the relative
        position's variance across the line of sight (what a range cannot tell while the
        geometry is uncertain). The link's NLOS bias is a consider state (:meth:`_link_state`):
        a bias repeated at 10 Hz is not noise that averages out (as noise it moved two queued
        vehicles apart by the 2.5 m of a link that started inside an episode), and estimated
        from the geometry it becomes where a geometry error goes."""
        s = self.settings
        i, j = self.ix[a], self.ix[c]
        x = self.x
        d, Pr = self.relative(a, c)
        rho = max(float(np.hypot(*d)), 1e-3)
        u = d / rho
        perp = max(float(np.trace(Pr) - u @ Pr @ u), 0.0)
        var = s.sigma_uwb**2 + perp * perp / (2.0 * max(r, 0.5) ** 2)
        li = None
        if s.uwb_nlos is not None:
            # the vehicles' NLOS handling: the link's own range series, then the innovation
            p_nlos = None
            if self.nlos is not None:
                va, vc = x[i + V_:i + V_ + 2], x[j + V_:j + V_ + 2]
                vr = va - vc
                link = self.nlos.belief(f"{a}|{c}", t, r, float(u @ vr), float(vr @ vr),
                                        standing=max(float(va @ va), float(vc @ vc)) < STANDING_SPEED**2)
                if link.outlier:
                    self.counters["range_outlier"] = self.counters.get("range_outlier", 0) + 1
                    return None
                p_nlos = link.p_nlos
                if p_nlos > s.nlos_reject_probability:
                    # the link's own series says it is in an episode: its bias, 0.3-3 m, is
                    # known to ±0.8 m at best, and each of its 10 ranges a second would carry
                    # that error again; the link waits for the episode's end (the step down)
                    self.counters["range_nlos"] = self.counters.get("range_nlos", 0) + 1
                    return None
            li = self._link_state(f"{a}|{c}", t, p_nlos)
            spread = float(u @ Pr @ u) + var + float(self.P[li, li])
            if s.uwb_nlos.classify(r - rho - float(self.x[li]), spread, s.nlos_reject_probability, p_nlos):
                # a new episode: the link's bias is drawn afresh, and the ranges, kept, tie
                # the two vehicles' relative motion from here on (dropped, a vehicle standing
                # in a queue behind a link in NLOS for 20 s lost its only tie to the queue)
                self.counters["range_nlos"] = self.counters.get("range_nlos", 0) + 1
                nl = s.uwb_nlos
                self.reset_state(li, nl.bias_mean, nl.bias_mean_square - nl.bias_mean**2)

        def fn(x: np.ndarray, back: float) -> tuple[np.ndarray, np.ndarray]:
            pa, Ja = self._pos(a, x, back)
            pc, Jc = self._pos(c, x, back)
            d = pa - pc
            rho = max(float(np.hypot(*d)), 1e-3)
            H = (d / rho @ (Ja - Jc))[None]
            if li is None:
                return np.array([rho]), H
            H[0, li] = 1.0
            return np.array([rho + x[li]]), H
        return Row(t, np.array([r]), np.eye(1) * var, fn, "range")

    def _link_state(self, link: str, t: float, p_nlos: float | None) -> int:
        """The NLOS bias state of ``link``: its mean and variance are the bias's moments when
        the link is NLOS with the probability its own range series gives (``p_nlos``,
        :class:`NlosLinkTracker`; without one the steady share): zero, or an episode's
        U(bias_min, bias_max). The variance is raised to that, never lowered (a consider
        state's covariance with the rest stays valid); a link silent for :data:`LINK_IDLE` s
        is forgotten."""
        for name in [k for k, (_, last, _) in self.links.items() if t - last > LINK_IDLE and not self.keep_links]:
            self._drop_state(self.links.pop(name)[0])
        nl = self.settings.uwb_nlos
        if nl is None:
            raise ValueError("a link's bias state needs the settings' NLOS model")
        p = nl.steady if p_nlos is None else p_nlos
        mean = p * nl.bias_mean
        var = max(p * nl.bias_mean_square - mean * mean, 1e-6)
        if link in self.links:
            entry = self.links[link]
            entry[1], entry[2] = t, var
            li = int(entry[0])
        else:
            li = self.n
            self.n += 1
            self.x = np.append(self.x, 0.0)
            self.P = np.pad(self.P, (0, 1))
            self.links[link] = [li, t, var]
        self.x[li] = mean
        self.P[li, li] = max(self.P[li, li], var)
        return li

    def _drop_state(self, k: int) -> None:
        """Marginalise state ``k`` out (a link's bias after the link went silent)."""
        keep = np.r_[0:k, k + 1:self.n]
        self.x = self.x[keep]
        self.P = self.P[np.ix_(keep, keep)]
        self.n -= 1
        for v in self.links.values():
            if v[0] > k:
                v[0] -= 1
