"""One source-CI update (:class:`SourceUpdate`, the update part of
:class:`agent.nav.source_fusion.SourceSplit`): the blocks the weights are chosen on, the groups
of shared sources, the weights that minimise the posterior variance, and the update itself."""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from .fusion import OMEGA_MAX, OMEGA_MIN, fminbound
from .kalman import Measurement, UpdateResult, chi2_gate
from .source_parts import ANY, SourcePart, _combine, _DepGroup, _rank_one_transform


class SourceUpdate:
    """The update of :class:`agent.nav.source_fusion.SourceSplit` (whose state it uses)."""

    n: int
    labels: list[frozenset[str]]
    own_labels: frozenset[str]
    const_labels: list[str]
    _C: np.ndarray
    _G: np.ndarray
    _unshared: np.ndarray

    if TYPE_CHECKING:  # SourceSplit's, which this part of it calls
        def _touch(self) -> None: ...
        def own(self, P: np.ndarray) -> np.ndarray: ...
        def _fold_constants(self, names: set[str] | None = None) -> None: ...
        def add_many(self, items: list[tuple[frozenset[str], float]], M: np.ndarray) -> None: ...
        def _const_rows(self, J: slice | np.ndarray) -> np.ndarray: ...
        def _block(self, J: slice | np.ndarray) -> np.ndarray: ...
        def _groups(self, mine: list[frozenset[str]],
                    theirs: list[frozenset[str]]) -> list[tuple[list[int], list[int]]]: ...

    # ------------------------------------------------------------------ the update
    def update(self, P: np.ndarray, meas: Measurement, parts: list[SourcePart], idx: np.ndarray,
               noise_labels: frozenset[str], gate_probability: float | None = None,
               min_gain: float = 0.0, constants: Sequence[tuple[str, float]] = (),
               consider: np.ndarray | None = None,
               idx_weight: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, UpdateResult]:
        """One source-CI update with a scalar measurement.

        Parameters
        ----------
        P : ndarray, shape (n, n)
            Prior covariance (the sum of the components).
        meas : Measurement
            ``z`` (1,), ``H`` (1, n), and ``R`` (1, 1): the measurement's own white noise,
            independent of both estimates (e.g. UWB noise and the second-order term).
        parts : list of SourcePart
            The rest of the measurement error, by source (the neighbour's components projected
            on the measurement, an NLOS bias).
        idx : ndarray of int, shape (m,)
            States whose posterior variance chooses the weights (the horizontal position, and
            the horizontal velocity if ``idx_weight`` weighs it).
        noise_labels : frozenset of str
            The source under which ``meas.R``'s share of the posterior is kept (for a range, the
            same at both ends of the link).
        gate_probability : float, optional
            χ² gate on the NIS with the inflated covariances.
        min_gain : float
            Node selection: skip the update (``result.skipped``) unless it reduces the variance
            of ``idx`` by at least this fraction.
        constants : sequence of (str, float)
            The measurement error's sensitivity to exactly tracked constants [unit per unit
            σ of the constant], by name (for a range, the neighbour's position rows of its
            ``G`` projected on its side of the line of sight); the parts of ``parts`` exclude
            them.
        consider : ndarray of int, optional
            Consider states (as :func:`agent.nav.kalman.kalman_update`): zero rows of the gain.
        idx_weight : ndarray, shape (m,), optional
            The weights w_i of the minimised sum Σ w_i P_ii (default 1) [their unit⁻² times
            the first state's unit²], e.g. τ² for a velocity whose error τ seconds on becomes
            position error. Node selection measures its gain on the same sum.

        Returns
        -------
        dx, P_post, result
            As :func:`agent.nav.kalman.kalman_update`; the components are updated in place when
            the update is applied. ``result.omega`` is the smallest group weight (1 if none).
        """
        if meas.dim != 1 or len(idx) == 0:
            raise ValueError("source CI takes scalar measurements and at least one state to minimise")
        if idx_weight is not None and (len(idx_weight) != len(idx) or not np.all(np.asarray(idx_weight) >= 0.0)):
            raise ValueError("idx_weight needs one weight >= 0 per minimised state")
        n = self.n
        if constants or self.const_labels:
            parts, constants = self._split_constants(parts, constants)
        blk = self._blocks(P, meas.H[0], idx, idx_weight, constants)
        r_ind, dep, terms, share = self._group_terms(blk, parts, float(meas.R[0, 0]))
        s = self._choose_weights(blk, terms, r_ind, min_gain)
        if s is None:
            skip = UpdateResult(np.zeros(n), float("nan"), 1, False, meas.name, None, float("nan"), skipped=True)
            return np.zeros(n), P, skip
        w = [min(max(s * sa / (s * sa + (1.0 - s) * sb), OMEGA_MIN), OMEGA_MAX) for sa, sb, *_ in terms]
        return self._apply(P, meas, parts, w, dep, share, r_ind, blk, noise_labels, gate_probability, consider)

    def _blocks(self, P: np.ndarray, h: np.ndarray, idx: np.ndarray, idx_weight: np.ndarray | None,
                constants: Sequence[tuple[str, float]]) -> _Blocks:
        """The blocks of the components on the states the measurement and ``idx`` touch, and
        the exactly tracked constants' part (:meth:`update`, first step)."""
        # The weights depend on the states the measurement and idx touch only (for a range, the
        # horizontal position and velocity): they are chosen on those blocks of the components,
        # and the whole matrices are formed only for an update that is made (a few % of ranges).
        idx_list = [int(i) for i in idx]
        wd = np.ones(len(idx_list)) if idx_weight is None else np.asarray(idx_weight, float)
        J = sorted(set(np.flatnonzero(h).tolist()) | set(idx_list))
        if J[-1] - J[0] < 2 * len(J):  # (nearly) contiguous (a range: position, velocity): views
            Jx: slice | np.ndarray = slice(J[0], J[-1] + 1)
            jj = [i - J[0] for i in idx_list]
            PJ = P[Jx, Jx]
        else:
            Jx = np.array(J)
            jj = [J.index(i) for i in idx_list]
            PJ = P[np.ix_(Jx, Jx)]
        b = _Blocks(Jx, jj, wd, np.sqrt(wd), PJ, h[Jx], self._block(Jx))
        b.ownJ = PJ - b.CJ.sum(axis=0)
        # the exactly tracked constants: my sensitivities G, the measurement's b; they add the
        # known cross-covariance G b and variance b·b, and are never inflated
        m_c = len(self.const_labels)
        if m_c or constants:
            at = {lab: k for k, lab in enumerate(self.const_labels)}
            b.b_mine = np.zeros(m_c)
            for lab, bv in constants:
                k = at.get(lab)
                if k is None:
                    b.new_labels.append(lab)
                    b.b_new.append(float(bv))
                else:
                    b.b_mine[k] += bv
            b.bb = float(b.b_mine @ b.b_mine) + sum(x * x for x in b.b_new)
            GJ = self._const_rows(Jx)
            b.gbJ = GJ @ b.b_mine
            b.ownJ = b.ownJ - GJ @ GJ.T
        return b

    def _group_terms(self, blk: _Blocks, parts: list[SourcePart], r_ind: float,
                     ) -> tuple[float, list[_DepGroup], list[tuple[float, ...]], list[float]]:
        """Per group of shared sources, my side (components) and the measurement's side
        (variance b): ``(r_ind, dep, terms, share)``, the independent noise grown by the parts
        no component of mine shares (:meth:`update`, second step)."""
        mineJ = np.concatenate([blk.ownJ[None], blk.CJ])  # own first, (k+1, m, m)
        ChJ = mineJ @ blk.hJ
        jj = blk.jj
        a_k = (ChJ @ blk.hJ).tolist()
        T_k = (mineJ[:, jj, jj] @ blk.wd).tolist()
        c_k = (ChJ[:, jj] * blk.sw).tolist()  # per component, the m scaled covariances
        groups = self._groups([self.own_labels] + self.labels, [p.labels for p in parts])
        dep: list[_DepGroup] = []
        terms: list[tuple[float, ...]] = []
        # a part's share of its group's variance (more than its own when it may correlate)
        share = [p.variance for p in parts]
        for gm, gp in groups:
            if len(gp) == 1:  # the usual case: one part, its own variance
                b = share[gp[0]]
            else:
                b = _combine([parts[j] for j in gp])
                tot = sum(share[j] for j in gp)
                for j in gp:
                    share[j] *= b / tot if tot > 0.0 else 0.0
            if not gm or b <= 0.0:
                r_ind += b
                continue
            if len(gm) == 1:
                k = gm[0]
                a, T, c = a_k[k], T_k[k], c_k[k]
            else:
                a, T = sum(a_k[k] for k in gm), sum(T_k[k] for k in gm)
                c = [sum(v) for v in zip(*(c_k[k] for k in gm))]
            dep.append((gm, gp, b))
            terms.append((math.sqrt(max(a, 1e-9 * T, 1e-300)), math.sqrt(b), T, a, b, *c))
        return r_ind, dep, terms, share

    def _choose_weights(self, blk: _Blocks, terms: list[tuple[float, ...]], r_ind: float,
                        min_gain: float) -> float | None:
        """The weight parameter minimising the posterior trace of the chosen states, or None when
        node selection declines the update (:meth:`update`, third step)."""
        PJ, hJ, jj, wd = blk.PJ, blk.hJ, blk.jj, blk.wd
        Ph = PJ @ hJ
        hPh = float(hJ @ Ph)
        tr0 = float(PJ[jj, jj] @ wd)
        if blk.b_mine is not None:  # the innovation's variance and cross-covariance, exact part
            hPh += 2.0 * float(hJ @ blk.gbJ) + blk.bb
            Ph = Ph + blk.gbJ
        ph = (Ph[jj] * blk.sw).tolist()
        posterior_trace = _PosteriorTrace(terms, tr0, hPh, r_ind, *ph)
        if min_gain > 0.0:
            # the plain Kalman gain, an upper bound (as :func:`agent.nav.fusion.naive_gain`)
            r_all = r_ind + sum(t[4] for t in terms)
            if hPh + r_all <= 0.0 or sum(v * v for v in ph) / (hPh + r_all) < min_gain * tr0:
                return None
        s = float(fminbound(posterior_trace, OMEGA_MIN, OMEGA_MAX, xatol=1e-3)) if terms else 0.5
        if min_gain > 0.0 and tr0 - posterior_trace(s) < min_gain * tr0:
            return None
        return s

    def _apply(self, P: np.ndarray, meas: Measurement, parts: list[SourcePart], w: list[float],
               dep: list[_DepGroup], share: list[float], r_ind: float, blk: _Blocks, noise_labels: frozenset[str],
               gate_probability: float | None,
               consider: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, UpdateResult]:
        """The update with whole matrices, my side of each group inflated by 1/ω_g; the
        components carried through it (:meth:`update`, last step)."""
        n = self.n
        h = meas.H[0]
        b_mine = blk.b_mine
        infl = np.ones(len(self.labels) + 1)  # own first
        for wg, (gm, _, _) in zip(w, dep):
            infl[gm] = 1.0 / wg
        mask = None
        if self._unshared.size:
            shared = np.ones(n, bool)
            shared[self._unshared] = False
            mask = np.outer(shared, shared)
        own = self.own(P)
        D = (infl[0] - 1.0) * own + np.tensordot(infl[1:] - 1.0, self._C, axes=1)
        P1 = P + (D if mask is None else D * mask)
        r1 = r_ind + sum(b / (1.0 - wg) for wg, (_, _, b) in zip(w, dep))
        P1h = P1 @ h
        S = float(h @ P1h) + r1
        if b_mine is not None:
            gb = self._G @ b_mine  # (own() above applied the pending congruence)
            S += 2.0 * float(h @ gb) + blk.bb
            P1h = P1h + gb
        z = float(meas.z[0])
        nis = z * z / S
        omega = min(w) if w else 1.0
        if gate_probability is not None and nis > chi2_gate(1, gate_probability):
            return np.zeros(n), P, UpdateResult(np.zeros(n), nis, 1, False, meas.name, None, omega)
        K = P1h / S
        if consider is not None and consider.size:
            # any gain: P1 - K cᵀ - c Kᵀ + S K Kᵀ with c = P1h the cross-covariance
            K = K.copy()
            K[consider] = 0.0
            KK = np.outer(K, K)
            Kc = np.outer(K, P1h)
            P_post = P1 - Kc - Kc.T + KK * S
        else:
            KK = np.outer(K, K)
            P_post = P1 - KK * S
        dx = K * z
        P_post = 0.5 * (P_post + P_post.T)
        # the components: carried through the update, mine inflated in their groups, the
        # neighbour's parts and the noise added under their sources
        self._touch()
        if self.labels:
            g = (infl[1:] - 1.0)[:, None, None]
            C = self._C + g * (self._C if mask is None else self._C * mask)
            self._C = _rank_one_transform(C, K, h, KK)
        if b_mine is not None:
            # G ← (I - K h)G - K b (the constants reach me through the measurement's error)
            self._G = self._G - np.outer(K, h @ self._G + b_mine)
            if blk.new_labels:
                self._G = np.concatenate([self._G, -np.outer(K, blk.b_new)], axis=1)
                self.const_labels = self.const_labels + blk.new_labels
        scale_p = [1.0] * len(parts)
        for wg, (_, gp, _) in zip(w, dep):
            for j in gp:
                scale_p[j] = 1.0 / (1.0 - wg)
        self.add_many([(p.labels, share[j] * scale_p[j]) for j, p in enumerate(parts) if share[j] > 0.0]
                      + [(noise_labels, float(meas.R[0, 0]))], KK)
        if b_mine is not None:
            self._fold_constants()
        return dx, P_post, UpdateResult(dx, nis, 1, True, meas.name, K[:, None], omega)

    def _split_constants(self, parts: list[SourcePart], constants: Sequence[tuple[str, float]],
                         ) -> tuple[list[SourcePart], Sequence[tuple[str, float]]]:
        """A constant is exact in an update only if both sides track it exactly: my columns
        that the measurement's parts name (or that :data:`ANY` may hold) are folded first, and
        the measurement's constants that my components name join its parts (variance b²)."""
        theirs: set[str] = set()
        for p in parts:
            theirs |= p.labels
        if self.const_labels and theirs and (ANY in theirs or not theirs.isdisjoint(self.const_labels)):
            self._fold_constants(theirs)
        if constants:
            mine = set(self.own_labels).union(*self.labels)
            held = [(lab, b) for lab, b in constants if ANY in mine or lab in mine]
            if held:
                parts = parts + [SourcePart(frozenset({lab}), b * b) for lab, b in held]
                constants = [(lab, b) for lab, b in constants if not (ANY in mine or lab in mine)]
        return parts, constants


class _Blocks:
    """One source-CI update's working blocks (:meth:`SourceSplit._blocks`)."""

    __slots__ = ("Jx", "jj", "wd", "sw", "PJ", "hJ", "CJ", "ownJ", "b_mine", "new_labels", "b_new", "bb", "gbJ")

    def __init__(self, Jx: slice | np.ndarray, jj: list[int], wd: np.ndarray, sw: np.ndarray, PJ: np.ndarray,
                 hJ: np.ndarray, CJ: np.ndarray) -> None:
        self.Jx, self.jj, self.wd, self.sw, self.PJ, self.hJ, self.CJ = Jx, jj, wd, sw, PJ, hJ, CJ
        self.ownJ = PJ
        self.b_mine: np.ndarray | None = None
        self.new_labels: list[str] = []
        self.b_new: list[float] = []
        self.bb = 0.0
        self.gbJ: np.ndarray | None = None


class _PosteriorTrace:
    """The weighted posterior variance of the minimised states [their unit²] as a function of
    the weight parameter ``s`` (the objective of :meth:`SourceSplit.update`), in O(log G + m)
    per evaluation for G groups and m minimised states.

    Group ``g``'s weight ω_g = s√a_g/(s√a_g + (1 - s)√b_g) makes its inflation
    x_g = 1/ω_g - 1 = ρ q_g with ρ = (1 - s)/s and q_g = √b_g/√a_g: every group's terms scale
    with the same ρ, except those whose ω_g is clipped to [OMEGA_MIN, OMEGA_MAX], which keep
    a constant x. With the groups sorted by q, the clipped ones are a prefix and a suffix, found
    by bisection, and every sum is a difference of prefix sums.

    ``terms``: per group (√a, √b, T, a, b, c_1, …, c_m) with T my side's weighted variance of the
    minimised states (Σ w_i P_ii), a its variance along the measurement, b the other side's,
    c_i my side's covariance of state i with the measurement, times √w_i; ``tr0``, ``hph``, ``r``,
    ``ph`` the same of the whole prior and the independent noise (``ph`` the m covariances).
    """

    X_LO = 1.0 / OMEGA_MAX - 1.0  #: the inflation of a group whose weight is clipped high
    X_HI = 1.0 / OMEGA_MIN - 1.0  #: ... clipped low

    def __init__(self, terms: list[tuple[float, ...]], tr0: float, hph: float, r: float, *ph: float):
        self.base = (tr0, hph, r)
        self.ph = ph
        m = len(ph)
        rows = sorted([(t[1] / t[0], *t[2:]) for t in terms])
        self.q = [t[0] for t in rows]
        # prefix sums of (T, a, c…, b), of q·(T, a, c…) and of b/q: one row of 2m + 6 sums
        acc = [0.0] * (2 * m + 6)
        self.cum = [tuple(acc)]
        for q, T, a, b, *c in rows:
            plain = (T, a, *c, b)
            for k, v in enumerate(plain):
                acc[k] += v
            for k, v in enumerate(plain[:-1]):
                acc[m + 3 + k] += q * v
            acc[-1] += b / q
            self.cum.append(tuple(acc))

    def __call__(self, s: float) -> float:
        tr, hph, r = self.base
        if not self.q:
            return tr - sum(v * v for v in self.ph) / (hph + r)
        m = len(self.ph)
        rho = (1.0 - s) / s
        lo = bisect.bisect_left(self.q, self.X_LO / rho)  # ρq < X_LO: ω clipped at OMEGA_MAX
        hi = bisect.bisect_right(self.q, self.X_HI / rho)  # ρq > X_HI: ω clipped at OMEGA_MIN
        c, L, H = self.cum[-1], self.cum[lo], self.cum[hi]
        x_lo, x_hi = self.X_LO, self.X_HI
        o = m + 3  # where the q-weighted sums start

        def inflated(k: int) -> float:
            return x_lo * L[k] + rho * (H[o + k] - L[o + k]) + x_hi * (c[k] - H[k])

        tr += inflated(0)
        hph += inflated(1)
        vv = 0.0
        for i, v in enumerate(self.ph):
            v += inflated(2 + i)
            vv += v * v
        # b/(1 - ω) = b (1 + 1/x)
        b = m + 2
        r += c[b] + L[b] / x_lo + (H[-1] - L[-1]) / rho + (c[b] - H[b]) / x_hi
        return tr - vv / (hph + r)
