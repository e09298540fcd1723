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

**Random constants are tracked exactly.** Some errors are one random draw that stays: a driver's
stop gap at a stop, its offset in a lane. For such a constant θ (scaled to unit variance) every
vehicle keeps the sensitivity of its error to it, a column ``g`` of ``G`` (n, m): the error is
``G θ`` plus the rest, and ``G Gᵀ`` is that part of ``P``. Propagation and updates are linear in
the error, so ``G`` follows them exactly (``G ← A G``); beacons carry the position rows of ``G``.
Two vehicles' parts of the same constant are then correlated by ``g_i g_jᵀ``, known, instead of
"in any way": a follower whose error is its anchor's stop gap moved by a range sees that error
cancel in the next range to the anchor, where CI must let the two add. The update is the Kalman
update with correlated noise on that part (:meth:`SourceSplit.update`). Columns beyond
:data:`MAX_CONSTANTS`, or too small to matter, are folded into a CI component named after the
constant (conservative). A constant one side tracks exactly and the other holds in a component
is intersected for that update: the exact side folds its column, or the other side's column
joins the measurement's CI parts.

Pure numpy; no I/O.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from .fusion import OMEGA_MAX, OMEGA_MIN, fminbound
from .kalman import Measurement, UpdateResult, chi2_gate

#: the source of the GNSS error every vehicle shares (not a vehicle id: those are [A-Za-z0-9_.-])
COMMON_MODE = "~common"
#: a label that names every source (a neighbour's estimate of unknown composition)
ANY = "*"

#: components stored besides the own one; beyond, the two smallest are merged
MAX_COMPONENTS = 12
#: a component naming more sources than this is broadcast as :data:`ANY` (the codec's limit)
MAX_LABELS = 64
#: random constants tracked exactly (columns of ``G``); beyond, the smallest are folded
MAX_CONSTANTS = 16
#: a constant whose part of the position variance is below this [m²] is folded
CONSTANT_FLOOR = 1e-6
#: separates a constant's vehicle from the rest of its name (``"V1~3.21.500"``)
CONSTANT_MARK = "~"


def overlaps(a: frozenset[str], b: frozenset[str]) -> bool:
    """Whether two label sets may share a source (:data:`ANY` shares with all)."""
    return bool(a & b) or (ANY in a and bool(b)) or (ANY in b and bool(a))


#: a group of shared sources in an update: (indices of my components, 0 the own one; indices of
#: the measurement's parts; the measurement side's variance b)
_DepGroup = tuple[list[int], list[int], float]


class SourcePart(NamedTuple):
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

    Notes
    -----
    The stored components are one array, shape (k, n, n), so that propagation and the
    own-sensor transform are a few stacked matrix products whatever k; ``labels[i]`` names
    ``parts[i]``.

    Propagation and own-sensor updates are congruences, ``P_s ← A P_s Aᵀ`` for every stored
    component (plus the common-mode process noise for one of them). They happen 10-25 times a
    second and the components are needed whole far less often (a beacon, an update that is
    made), so they are composed, ``A ← A_new A``, and applied when needed (:meth:`_sync`);
    the choice of the weights needs only a few rows of ``A``.
    """

    def __init__(self, me: str, n: int, unshared: ArrayLike = (), shared_process: ArrayLike = ()) -> None:
        self.n = n
        self.own_labels: frozenset[str] = frozenset({me})
        self.labels: list[frozenset[str]] = []
        self._C = np.zeros((0, n, n))
        #: exactly tracked random constants: names, and the error's sensitivity to each (unit
        #: variance), shape (n, m) [state units]
        self.const_labels: list[str] = []
        self._G = np.zeros((n, 0))
        self._unshared = np.asarray(unshared, int)
        s = np.asarray(shared_process, int)
        self._shared_process = np.ix_(s, s) if s.size else None
        self._group_memo: dict[tuple[tuple[frozenset[str], ...], tuple[frozenset[str], ...]],
                               list[tuple[list[int], list[int]]]] = {}
        # pending: the true components are A C Aᵀ, plus Q for component k_q (see the Notes)
        self._A: np.ndarray | None = None
        self._Q: np.ndarray | None = None
        self._k_q = -1
        # every change of the components bumps the version (:meth:`_touch`); the position
        # blocks of the last version are kept: a ranging round weighs several neighbours'
        # ranges against the same components, and declined ones change nothing
        self._version = 0
        self._block_memo: tuple[int, tuple[int, ...], np.ndarray] | None = None  # (version, states, blocks)

    def _touch(self) -> None:
        """The components (or their pending congruence) are about to change."""
        self._version += 1

    def copy(self) -> SourceSplit:
        """An independent copy (e.g. to restore a filter's state)."""
        self._sync()
        out = SourceSplit.__new__(SourceSplit)
        out.__dict__.update(self.__dict__)
        out.labels = list(self.labels)
        out._C = self._C.copy()
        out.const_labels = list(self.const_labels)
        out._G = self._G.copy()
        out._block_memo = None  # it may view this object's components
        return out

    @property
    def parts(self) -> np.ndarray:
        """The stored components, shape (k, n, n) [state units²]; read them, do not write."""
        self._sync()
        self._touch()  # the caller holds the array
        return self._C

    def _sync(self) -> None:
        """Apply the pending congruence and common-mode noise to the stored components."""
        if self._A is not None or self._Q is not None:
            self._touch()
        if self._A is not None:
            C = self._A @ self._C @ self._A.T
            self._C = 0.5 * (C + C.transpose(0, 2, 1))
            if self.const_labels:
                self._G = self._A @ self._G
            self._A = None
        if self._Q is not None:
            self._C[self._k_q] += self._Q
            self._Q = None

    def _compose(self, A: np.ndarray, rank_one: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Add the congruence ``A`` (n, n) to the pending one; ``rank_one`` ``(k, h)`` says
        ``A = I - k hᵀ`` (then O(n²))."""
        self._touch()
        if rank_one is not None:
            k, h = rank_one
            self._A = A if self._A is None else self._A - np.outer(k, h @ self._A)
            if self._Q is not None:
                self._Q = _rank_one_transform(self._Q, k, h)
            return
        self._A = A if self._A is None else A @ self._A
        if self._Q is not None:
            Q = A @ self._Q @ A.T
            self._Q = 0.5 * (Q + Q.T)

    def _common_target(self) -> int | None:
        """Where the common-mode process noise goes: -1 the own component, k a stored one that
        names it, None if it would change the components (merge or create one)."""
        cm = frozenset({COMMON_MODE})
        if overlaps(self.own_labels, cm):
            return -1
        hit = [k for k, lab in enumerate(self.labels) if overlaps(lab, cm)]
        return hit[0] if len(hit) == 1 and COMMON_MODE in self.labels[hit[0]] else None

    @property
    def tracked(self) -> bool:
        """Whether anything but the own component is stored (components or constants)."""
        return bool(self.labels) or bool(self.const_labels)

    @property
    def constants(self) -> np.ndarray:
        """The sensitivities to the exactly tracked constants, shape (n, m); read only."""
        self._sync()
        self._touch()
        return self._G

    # ------------------------------------------------------------------ bookkeeping
    def own(self, P: np.ndarray) -> np.ndarray:
        """The own component, ``P`` minus the stored ones and the constants', shape (n, n)."""
        self._sync()
        out = P - self._C.sum(axis=0) if self.labels else P.copy()
        if self.const_labels:
            out -= self._G @ self._G.T
        return out

    def new_constants(self, labels: list[str], idx: ArrayLike, sigma: ArrayLike) -> None:
        """States ``idx`` were just reset to a fresh prior of σ ``sigma`` (each its own random
        constant, uncorrelated with the rest): track them exactly under ``labels``."""
        self._sync()
        self._touch()
        idx = np.atleast_1d(np.asarray(idx, int))
        sigma = np.broadcast_to(np.asarray(sigma, float), idx.shape)
        cols = np.zeros((self.n, len(idx)))
        cols[idx, np.arange(len(idx))] = sigma
        self._G = np.concatenate([self._G, cols], axis=1)
        self.const_labels = self.const_labels + list(labels)
        self._fold_constants()

    def _fold_constants(self, names: set[str] | None = None) -> None:
        """Fold constants into CI components (the total covariance is unchanged): those in
        ``names`` (:data:`ANY` in it: all) and the smallest beyond :data:`MAX_CONSTANTS`, each
        under its own name, and those whose variance is below :data:`CONSTANT_FLOOR` under
        their owner's vehicle id.

        A copy below the floor is what a range's small gain left of a neighbour's constant (a
        millimetre of the owner's 0.12 m lane offset). Named by the constant, it would make the
        owner fold its whole constant at its next range with me (a constant is exact only where
        both sides track it exactly), and CI would inflate it from then on: the stop-line fix
        could no longer pin it. Named by the owner, it is information from the owner, which CI
        pairs with the owner's own component; its correlation with the owner's exact column
        (at most √(floor)·|g|) is neglected."""
        if not self.const_labels:
            return
        self._sync()  # G must be current: its columns go into the components as they are
        G = self._G
        size = (G**2).sum(axis=0)
        order = np.argsort(size)
        floor = {int(k) for k in order if size[k] < CONSTANT_FLOOR}
        drop = set(floor)
        if names:
            drop |= {k for k, lab in enumerate(self.const_labels) if ANY in names or lab in names}
        excess = len(self.const_labels) - MAX_CONSTANTS - len(drop)
        if excess > 0:
            drop |= set([int(k) for k in order if int(k) not in drop][:excess])
        if not drop:
            return
        keep = [k for k in range(len(self.const_labels)) if k not in drop]
        folded = [(self.const_labels[k], G[:, k], k in floor) for k in sorted(drop)]
        self._G = G[:, keep]
        self.const_labels = [self.const_labels[k] for k in keep]
        for lab, g, below in folded:
            owner = lab.split(CONSTANT_MARK)[0] if below else lab
            self.add(frozenset({owner or lab}), np.outer(g, g))

    def add(self, labels: frozenset[str], M: np.ndarray | None) -> None:
        """Add covariance ``M`` (n, n) (None: nothing, only the labels) from the sources
        ``labels``. Components that share a source with it are merged with it; if the own
        component does, it takes them all (``M`` is then part of ``P`` already)."""
        self._sync()
        self._touch()
        if not overlaps(self.own_labels, labels):
            hit = [k for k, lab in enumerate(self.labels) if overlaps(lab, labels)]
            if len(hit) == 1 and labels <= self.labels[hit[0]]:  # e.g. the common mode, every step
                if M is not None:
                    self._C[hit[0]] += M
                return
        self.add_many([(labels, 1.0)], np.zeros((self.n, self.n)) if M is None else M)

    def add_many(self, items: list[tuple[frozenset[str], float]], M: np.ndarray) -> None:
        """Add ``w M`` from the sources ``labels`` for every ``(labels, w)`` of ``items``
        (``M`` (n, n), ``w`` ≥ 0), merging as :meth:`add` one item after the other would: the
        items and components that share a source become one component, and whatever shares one
        with the own component joins it. Beyond :data:`MAX_COMPONENTS` the two smallest (by
        trace) are merged, repeatedly. The merges are planned on the traces and the new
        components formed in one product."""
        self._sync()
        self._touch()
        mine = [self.own_labels] + self.labels
        k_old = len(self.labels)
        gone: set[int] = set()  # stored components merged into others or into the own one
        new: list[list[Any]] = []  # [labels, weight of M, stored components summed in]
        for gm, gp in _group(mine, [lab for lab, _ in items]):
            if not gp:
                continue
            merged = frozenset().union(*(mine[k] for k in gm), *(items[j][0] for j in gp))
            w = sum(items[j][1] for j in gp)
            if 0 in gm:  # the own component: M is part of P already
                self.own_labels = merged
            elif len(gm) == 1 and merged == mine[gm[0]]:
                self._C[gm[0] - 1] += w * M
                continue
            else:
                new.append([merged, w, [k - 1 for k in gm]])
            gone.update(k - 1 for k in gm if k > 0)
        if not gone and not new:
            return
        plan = [[self.labels[i], 0.0, [i]] for i in range(k_old) if i not in gone] + new
        if len(plan) > MAX_COMPONENTS:
            tr_old = np.trace(self._C, axis1=1, axis2=2).tolist()
            tr_m = float(np.trace(M))
            size = [w * tr_m + sum(tr_old[i] for i in idx) for _, w, idx in plan]
            while len(plan) > MAX_COMPONENTS:
                i, j = sorted(sorted(range(len(size)), key=size.__getitem__)[:2])
                lab_j, w_j, idx_j = plan.pop(j)
                plan[i] = [plan[i][0] | lab_j, plan[i][1] + w_j, plan[i][2] + idx_j]
                size[i] += size.pop(j)
        S = np.zeros((len(plan), k_old))
        for r, (_, _, idx) in enumerate(plan):
            S[r, idx] = 1.0
        weights = np.array([p[1] for p in plan])
        self._C = np.tensordot(S, self._C, axes=1) + weights[:, None, None] * M
        self.labels = [p[0] for p in plan]

    def propagate(self, phi: np.ndarray, qd: np.ndarray) -> None:
        """``P_s ← Φ P_s Φᵀ``; the process noise of the shared states (in ``qd``) goes to
        :data:`COMMON_MODE`, the rest to the own component (implicitly)."""
        self._touch()
        Q = None
        if self._shared_process is not None:
            Q = np.zeros((self.n, self.n))
            Q[self._shared_process] = qd[self._shared_process]
        target = -1 if Q is None else self._common_target()
        if target is None:  # the noise makes a component: apply everything now
            self._sync()
            C = phi @ self._C @ phi.T
            self._C = 0.5 * (C + C.transpose(0, 2, 1))
            if self.const_labels:
                self._G = phi @ self._G
            self.add(frozenset({COMMON_MODE}), Q)
            return
        if self.tracked:
            self._compose(phi)
            if target >= 0:
                self._Q = Q if self._Q is None else self._Q + Q
                self._k_q = target

    def transform(self, K: np.ndarray, H: np.ndarray) -> None:
        """Carry every stored component through an own-sensor update with gain ``K`` (n, m) and
        Jacobian ``H`` (m, n): ``(I - K H) P_s (I - K H)ᵀ``; the measurement noise ``K R Kᵀ``
        is the own component's."""
        if not self.tracked:
            return
        A = -(K @ H)
        A.flat[:: self.n + 1] += 1.0
        self._compose(A, (K[:, 0], H[0]) if H.shape[0] == 1 else None)

    def clear_states(self, idx: np.ndarray | Sequence[int]) -> None:
        """Zero the rows and columns ``idx`` of every stored component: a reset gives those states
        a fresh prior of the own kind."""
        self._sync()
        self._touch()
        self._C[:, idx, :] = 0.0
        self._C[:, :, idx] = 0.0
        self._G[idx, :] = 0.0

    def decorrelate(self, i: int) -> None:
        """Zero state ``i``'s correlations (not its variance) in every stored component."""
        self._sync()
        self._touch()
        d = self._C[:, i, i].copy()
        self._C[:, i, :] = 0.0
        self._C[:, :, i] = 0.0
        self._C[:, i, i] = d
        self._G[i, :] = 0.0  # its part of the constants joins the own component

    def blocks(self, P: np.ndarray, idx: slice) -> list[tuple[tuple[str, ...], np.ndarray]]:
        """Every component's ``idx`` block (e.g. the NED position), own first, with its sorted
        source labels: what a beacon carries. A component of more than :data:`MAX_LABELS`
        sources goes as :data:`ANY` (its receivers then pair it with everything)."""
        def named(lab: frozenset[str]) -> tuple[str, ...]:
            return tuple(sorted(lab)) if len(lab) <= MAX_LABELS else (ANY,)

        own = P[idx, idx].copy()
        if self.const_labels:
            g = self.constants[idx]
            own -= g @ g.T
        out = []
        for lab, C in zip(self.labels, self.parts):
            b = C[idx, idx].copy()
            own -= b
            out.append((named(lab), b))
        return [(named(self.own_labels), own)] + out

    def constant_rows(self, idx: slice) -> list[tuple[str, np.ndarray]]:
        """Every constant's sensitivity on the states ``idx`` (e.g. the NED position), with its
        name: what a beacon carries beside :meth:`blocks` (whose own part excludes them)."""
        if not self.const_labels:
            return []
        g = self.constants[idx]
        return [(lab, g[:, k].copy()) for k, lab in enumerate(self.const_labels)]

    def _const_rows(self, J: slice | np.ndarray) -> np.ndarray:
        """Rows ``J`` of ``G`` without applying the pending congruence, shape (m_J, m)."""
        if self._A is None:
            return self._G[J]
        return self._A[J] @ self._G

    def _block(self, J: slice | np.ndarray) -> np.ndarray:
        """Every stored component's block of the states ``J`` (a slice or an index array),
        shape (k, m, m), without applying the pending congruence to the whole matrices; read
        only (remembered until the components change)."""
        key = (J.start, J.stop) if isinstance(J, slice) else tuple(J.tolist())
        memo = self._block_memo
        if memo is not None and memo[0] == self._version and memo[1] == key:
            return memo[2]
        if self._A is None:
            CJ = self._C[:, J, J] if isinstance(J, slice) else self._C[:, J[:, None], J[None, :]]
        else:
            rows = self._A[J]
            CJ = rows @ self._C @ rows.T
        if self._Q is not None:
            CJ = CJ.copy()
            CJ[self._k_q] += self._Q[J, J] if isinstance(J, slice) else self._Q[np.ix_(J, J)]
        CJ.flags.writeable = False
        self._block_memo = (self._version, key, CJ)
        return CJ

    def _groups(self, mine: list[frozenset[str]], theirs: list[frozenset[str]]) -> list[tuple[list[int], list[int]]]:
        """:func:`_group`, remembered: the same neighbour's beacon meets the same components at
        every range until either changes."""
        key = (tuple(mine), tuple(theirs))
        g = self._group_memo.get(key)
        if g is None:
            if len(self._group_memo) >= 256:
                self._group_memo.clear()
            g = self._group_memo[key] = _group(mine, theirs)
        return g

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


def _rank_one_transform(C: np.ndarray, k: np.ndarray, h: np.ndarray, kk: np.ndarray | None = None) -> np.ndarray:
    """``(I - k hᵀ) C (I - k hᵀ)ᵀ`` for symmetric ``C`` (..., n, n), gain ``k`` (n,) and
    Jacobian row ``h`` (n,), in O(n²) per matrix; ``kk`` is ``k kᵀ`` if already formed."""
    if kk is None:
        kk = np.outer(k, k)
    c = C @ h  # (..., n)
    kc = k[:, None] * c[..., None, :]  # k cᵀ
    out = C - kc - np.swapaxes(kc, -1, -2) + (c @ h)[..., None, None] * kk
    sym: np.ndarray = 0.5 * (out + np.swapaxes(out, -1, -2))
    return sym


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
