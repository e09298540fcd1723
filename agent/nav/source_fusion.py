"""Covariance intersection by information source ("source CI").

Split CI (:mod:`agent.nav.fusion`) counts a vehicle's own information as independent of a
neighbour's estimate. It is not, once the two have exchanged ranges: the neighbour's estimate
holds some of our own information, and our own information comes back to us through its beacon
as if it were news (paper-2's head vehicle reported a σ up to 4 % below the posterior Cramér-Rao
bound). Plain CI counts everything as dependent and throws most of the information away.

Source CI tracks where information came from. Every error covariance is kept as a sum of
components by *source*, the vehicle whose sensors' noise made that part of the error (a source
``s`` may also be the GNSS error all vehicles share, :data:`COMMON_MODE`):

    P = Σ_s P_s

Each component bounds the covariance of the error's part that is a linear function of source
``s``'s noise. Parts from different sources are independent, in one vehicle and across vehicles;
parts from the same source may be correlated in any way between vehicles. Beacons carry the
position blocks of the components. A range with a neighbour then pairs each source's part of our
prior with the same source's part of the neighbour's estimate, and intersects only those pairs,
each with its own weight ω_g:

    P1 = Σ_g P_g / ω_g + P_i,        R1 = Σ_g R_g / (1 - ω_g) + R_i

where ``g`` runs over groups of sources found on both sides and ``P_i``/``R_i`` are the parts
whose sources only one side holds. This bounds the joint error covariance for any correlation
within a group, so the update is consistent (Julier & Uhlmann's split-CI argument, applied group
by group). The posterior stays split by source: our part of group ``g`` becomes
``(I - K H)(P_g / ω_g)(I - K H)ᵀ`` and the neighbour's part ``K (R_g / (1 - ω_g)) Kᵀ``, both
under their source's name.

The component of the vehicle itself (its *own* part) is not stored: it is ``P`` minus the others,
so the ordinary updates with its own sensors (GNSS, stop line) need nothing but the shared
transform ``(I - K H) P_s (I - K H)ᵀ`` of the stored components.

A component may name several sources (a *merged* one, when the number of components is capped,
or when a beacon's component names several); it is then paired with every component that names
any of them. :data:`ANY` names every source (a beacon without the breakdown): that is plain CI.

Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .fusion import OMEGA_MAX, OMEGA_MIN, fminbound, naive_gain
from .kalman import Measurement, UpdateResult, chi2_gate

#: the source of the GNSS error every vehicle shares (not a vehicle id: those are [A-Za-z0-9_.-])
COMMON_MODE = "~common"
#: a label that names every source (a neighbour's estimate of unknown composition)
ANY = "*"

#: components stored besides the own one; beyond, the two smallest are merged
MAX_COMPONENTS = 12
#: a component naming more sources than this is broadcast as :data:`ANY` (the codec's limit)
MAX_LABELS = 64


def overlaps(a: frozenset[str], b: frozenset[str]) -> bool:
    """Whether two label sets may share a source (:data:`ANY` shares with all)."""
    return bool(a & b) or (ANY in a and bool(b)) or (ANY in b and bool(a))


@dataclass(frozen=True)
class SourcePart:
    """A neighbour's covariance part of known sources, projected on a measurement.

    ``labels`` the sources; ``variance`` [unit²] of the measurement error it causes;
    ``correlated`` True if it may correlate with the other parts of its group on the same side
    (e.g. an NLOS bias shared by the link's both ends), which adds standard deviations instead
    of variances.
    """

    labels: frozenset[str]
    variance: float
    correlated: bool = False


class SourceSplit:
    """A covariance split by information source; the own component is implicit.

    Parameters
    ----------
    me : str
        The vehicle's id: its own source.
    n : int
        State dimension.
    unshared : array of int
        States no cooperative measurement observes: never inflated by the intersection (their
        rows and columns keep their prior weight; see
        :meth:`agent.nav.ins_filter.InsFilter.track_independent`).
    shared_process : array of int
        States whose process noise belongs to :data:`COMMON_MODE`.
    """

    def __init__(self, me: str, n: int, unshared=(), shared_process=()) -> None:
        self.n = n
        self.own_labels: frozenset[str] = frozenset({me})
        self.labels: list[frozenset[str]] = []
        self.parts: list[np.ndarray] = []
        self._unshared = np.asarray(unshared, int)
        self._shared_process = np.asarray(shared_process, int)

    # ------------------------------------------------------------------ bookkeeping
    def own(self, P: np.ndarray) -> np.ndarray:
        """The own component, ``P`` minus the stored ones, shape (n, n)."""
        own = P.copy()
        for C in self.parts:
            own -= C
        return own

    def add(self, labels: frozenset[str], M: np.ndarray | None) -> None:
        """Add covariance ``M`` (n, n) (None: nothing, only the labels) from the sources
        ``labels``. Components that share a source with it are merged with it; if the own
        component does, it takes them all (``M`` is then part of ``P`` already)."""
        hit = [k for k, lab in enumerate(self.labels) if overlaps(lab, labels)]
        if overlaps(self.own_labels, labels):
            merged = set(self.own_labels) | set(labels)
            for k in sorted(hit, reverse=True):
                merged |= self.labels.pop(k)
                self.parts.pop(k)
            self.own_labels = frozenset(merged)
            return
        total = np.zeros((self.n, self.n)) if M is None else M.copy()
        merged = set(labels)
        for k in sorted(hit, reverse=True):
            merged |= self.labels.pop(k)
            total += self.parts.pop(k)
        self.labels.append(frozenset(merged))
        self.parts.append(total)
        self._cap()

    def _cap(self) -> None:
        while len(self.parts) > MAX_COMPONENTS:
            size = [float(np.trace(C)) for C in self.parts]
            i, j = sorted(np.argsort(size)[:2])
            self.labels[i] = self.labels[i] | self.labels.pop(j)
            self.parts[i] = self.parts[i] + self.parts.pop(j)

    def propagate(self, phi: np.ndarray, qd: np.ndarray) -> None:
        """``P_s ← Φ P_s Φᵀ``; the process noise of the shared states (in ``qd``) goes to
        :data:`COMMON_MODE`, the rest to the own component (implicitly)."""
        for k, C in enumerate(self.parts):
            C = phi @ C @ phi.T
            self.parts[k] = 0.5 * (C + C.T)
        if self._shared_process.size:
            s = self._shared_process
            Q = np.zeros((self.n, self.n))
            Q[np.ix_(s, s)] = qd[np.ix_(s, s)]
            self.add(frozenset({COMMON_MODE}), Q)

    def transform(self, K: np.ndarray, H: np.ndarray) -> None:
        """Carry every stored component through an own-sensor update with gain ``K`` (n, m) and
        Jacobian ``H`` (m, n): ``(I - K H) P_s (I - K H)ᵀ``; the measurement noise ``K R Kᵀ``
        is the own component's."""
        if H.shape[0] == 1:
            k, h = K[:, 0], H[0]
            kk = np.outer(k, k)
            self.parts = [_rank_one_transform(C, k, h, kk) for C in self.parts]
            return
        A = -(K @ H)
        A.flat[:: self.n + 1] += 1.0
        for k, C in enumerate(self.parts):
            C = A @ C @ A.T
            self.parts[k] = 0.5 * (C + C.T)

    def clear_states(self, idx) -> None:
        """Zero the rows and columns ``idx`` of every stored component: a reset gives those states
        a fresh prior of the own kind."""
        for C in self.parts:
            C[idx, :] = 0.0
            C[:, idx] = 0.0

    def decorrelate(self, i: int) -> None:
        """Zero state ``i``'s correlations (not its variance) in every stored component."""
        for C in self.parts:
            d = C[i, i]
            C[i, :] = 0.0
            C[:, i] = 0.0
            C[i, i] = d

    def blocks(self, P: np.ndarray, idx: slice) -> list[tuple[tuple[str, ...], np.ndarray]]:
        """Every component's ``idx`` block (e.g. the NED position), own first, with its sorted
        source labels: what a beacon carries. A component of more than :data:`MAX_LABELS`
        sources goes as :data:`ANY` (its receivers then pair it with everything)."""
        def named(lab: frozenset[str]) -> tuple[str, ...]:
            return tuple(sorted(lab)) if len(lab) <= MAX_LABELS else (ANY,)

        own = P[idx, idx].copy()
        out = []
        for lab, C in zip(self.labels, self.parts):
            b = C[idx, idx].copy()
            own -= b
            out.append((named(lab), b))
        return [(named(self.own_labels), own)] + out

    # ------------------------------------------------------------------ the update
    def update(self, P: np.ndarray, meas: Measurement, parts: list[SourcePart], idx: np.ndarray,
               noise_labels: frozenset[str], gate_probability: float | None = None,
               min_gain: float = 0.0) -> tuple[np.ndarray, np.ndarray, UpdateResult]:
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
        idx : ndarray of int
            States whose posterior variance chooses the weights (the horizontal position).
        noise_labels : frozenset of str
            The source under which ``meas.R``'s share of the posterior is kept (for a range, the
            same at both ends of the link).
        gate_probability : float, optional
            χ² gate on the NIS with the inflated covariances.
        min_gain : float
            Node selection: skip the update (``result.skipped``) unless it reduces the variance
            of ``idx`` by at least this fraction.

        Returns
        -------
        dx, P_post, result
            As :func:`agent.nav.kalman.kalman_update`; the components are updated in place when
            the update is applied. ``result.omega`` is the smallest group weight (1 if none).
        """
        if meas.dim != 1 or len(idx) != 2:
            raise ValueError("source CI takes scalar measurements and two states to minimise")
        n = self.n
        h = meas.H[0]
        r_ind = float(meas.R[0, 0])
        own = self.own(P)
        mine = [(self.own_labels, own)] + list(zip(self.labels, self.parts))
        groups = _group([lab for lab, _ in mine], [p.labels for p in parts])
        shared = np.ones(n, bool)
        if self._unshared.size:
            shared[self._unshared] = False
        # per group: my side (components) and the measurement side (variance b); projections
        # first (O(n²) per component), the group's matrices only once the weights are chosen
        Ch = [C @ h for _, C in mine]
        i0, i1 = int(idx[0]), int(idx[1])
        dep: list[tuple[list[int], list[int], float]] = []
        terms: list[tuple[float, ...]] = []
        # a part's share of its group's variance (more than its own when it may correlate)
        share = [0.0] * len(parts)
        for gm, gp in groups:
            b = _combine([parts[j] for j in gp])
            tot = sum(parts[j].variance for j in gp)
            for j in gp:
                share[j] = parts[j].variance * (b / tot if tot > 0.0 else 0.0)
            if not gm or b <= 0.0:
                r_ind += b
                continue
            Ah = sum(Ch[k] for k in gm)
            a = float(h @ Ah)
            T = sum(float(mine[k][1][i0, i0] + mine[k][1][i1, i1]) for k in gm)
            dep.append((gm, gp, b))
            terms.append((math.sqrt(max(a, 1e-9 * T, 1e-300)), math.sqrt(b), T, a, b, float(Ah[i0]), float(Ah[i1])))
        Ph = P @ h
        hPh = float(h @ Ph)
        tr0 = float(P[i0, i0] + P[i1, i1])
        ph0, ph1 = float(Ph[i0]), float(Ph[i1])

        def weights(s: float) -> list[float]:
            return [min(max(s * sa / (s * sa + (1.0 - s) * sb), OMEGA_MIN), OMEGA_MAX)
                    for sa, sb, *_ in terms]

        def posterior_trace(s: float) -> float:
            tr, hph, r, v0, v1 = tr0, hPh, r_ind, ph0, ph1
            for sa, sb, T, a, b, c0, c1 in terms:
                w = s * sa / (s * sa + (1.0 - s) * sb)
                w = OMEGA_MIN if w < OMEGA_MIN else OMEGA_MAX if w > OMEGA_MAX else w
                x = 1.0 / w - 1.0
                tr += x * T
                hph += x * a
                v0 += x * c0
                v1 += x * c1
                r += b / (1.0 - w)
            return tr - (v0 * v0 + v1 * v1) / (hph + r)

        skip = UpdateResult(np.zeros(n), float("nan"), 1, False, meas.name, None, float("nan"), skipped=True)
        if min_gain > 0.0:
            r_all = r_ind + sum(t[4] for t in terms)
            if naive_gain(P, meas.H, np.array([[r_all]]), idx) < min_gain * tr0:
                return np.zeros(n), P, skip
        s = float(fminbound(posterior_trace, OMEGA_MIN, OMEGA_MAX, xatol=1e-3)) if terms else 0.5
        if min_gain > 0.0 and tr0 - posterior_trace(s) < min_gain * tr0:
            return np.zeros(n), P, skip
        w = weights(s)
        mask = np.outer(shared, shared) if self._unshared.size else None
        P1 = P.copy()
        r1 = r_ind
        for wg, (gm, _, b) in zip(w, dep):
            A = sum(mine[k][1] for k in gm)
            P1 += (1.0 / wg - 1.0) * (A if mask is None else A * mask)
            r1 += b / (1.0 - wg)
        P1h = P1 @ h
        S = float(h @ P1h) + r1
        z = float(meas.z[0])
        nis = z * z / S
        omega = min(w) if w else 1.0
        if gate_probability is not None and nis > chi2_gate(1, gate_probability):
            return np.zeros(n), P, UpdateResult(np.zeros(n), nis, 1, False, meas.name, None, omega)
        K = P1h / S
        dx = K * z
        P_post = P1 - np.outer(K, K) * S
        P_post = 0.5 * (P_post + P_post.T)
        # the components: carried through the update, mine inflated in their groups
        scale = {}
        for wg, (gm, gp, _) in zip(w, dep):
            for k in gm:
                scale[k] = 1.0 / wg
            for j in gp:
                scale[("p", j)] = 1.0 / (1.0 - wg)
        KK = np.outer(K, K)
        for k in range(1, len(mine)):
            C = self.parts[k - 1]
            if k in scale:
                C = C + (scale[k] - 1.0) * (C if mask is None else C * mask)
            self.parts[k - 1] = _rank_one_transform(C, K, h, KK)
        for j, p in enumerate(parts):
            var = share[j] * scale.get(("p", j), 1.0)
            if var > 0.0:
                self.add(p.labels, KK * var)
        self.add(noise_labels, KK * float(meas.R[0, 0]))
        return dx, P_post, UpdateResult(dx, nis, 1, True, meas.name, K[:, None], omega)


def _rank_one_transform(C: np.ndarray, k: np.ndarray, h: np.ndarray, kk: np.ndarray) -> np.ndarray:
    """``(I - k hᵀ) C (I - k hᵀ)ᵀ`` for a symmetric ``C`` (n, n), gain ``k`` (n,) and
    Jacobian row ``h`` (n,), in O(n²); ``kk`` is ``k kᵀ``."""
    c = C @ h
    kc = np.outer(k, c)
    out = C - kc - kc.T + float(h @ c) * kk
    return 0.5 * (out + out.T)


def _combine(parts: list[SourcePart]) -> float:
    """Variance [unit²] of a sum of parts: variances add for independent parts; standard
    deviations add for a part that may correlate with the others."""
    ind = sum(p.variance for p in parts if not p.correlated)
    cor = [p.variance for p in parts if p.correlated]
    if not cor:
        return ind
    return (math.sqrt(max(ind, 0.0)) + sum(math.sqrt(max(v, 0.0)) for v in cor)) ** 2


def _group(mine: list[frozenset[str]], theirs: list[frozenset[str]]) -> list[tuple[list[int], list[int]]]:
    """Connected groups of label sets that may share a source: ``(my indices, their indices)``."""
    labels = list(mine) + list(theirs)
    parent = list(range(len(labels)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    first: dict[str, int] = {}  # a label's first node: every other node naming it joins it
    wild = [i for i, lab in enumerate(labels) if ANY in lab]
    for i, lab in enumerate(labels):
        for x in lab:
            j = first.setdefault(x, i)
            if j != i:
                parent[find(i)] = find(j)
    if wild:  # ANY shares a source with every non-empty set
        for i, lab in enumerate(labels):
            if lab:
                parent[find(i)] = find(wild[0])
    out: dict[int, tuple[list[int], list[int]]] = {}
    n_mine = len(mine)
    for i in range(len(labels)):
        g = out.setdefault(find(i), ([], []))
        (g[0] if i < n_mine else g[1]).append(i if i < n_mine else i - n_mine)
    return list(out.values())
