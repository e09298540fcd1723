"""Covariance intersection by information source ("source CI").

Split CI (:mod:`agent.nav.fusion`) counts a vehicle's own information as independent of a
neighbour's estimate. It is not, once the two have exchanged ranges: the neighbour's estimate
holds some of our own information, and our own information comes back to us through its beacon
as if it were news (a vehicle then reports a σ below the posterior Cramér-Rao bound). Plain CI
counts everything as dependent and throws most of the information away.

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

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .source_parts import (
    ANY,
    COMMON_MODE,
    CONSTANT_FLOOR,
    CONSTANT_MARK,
    MAX_COMPONENTS,
    MAX_CONSTANTS,
    MAX_LABELS,
    SourcePart,
    _combine,
    _group,
    _rank_one_transform,
    overlaps,
)
from .source_update import SourceUpdate, _PosteriorTrace

__all__ = ["ANY", "COMMON_MODE", "CONSTANT_FLOOR", "CONSTANT_MARK", "MAX_COMPONENTS", "MAX_CONSTANTS", "MAX_LABELS",
           "SourcePart", "SourceSplit", "_PosteriorTrace", "_combine", "_group", "overlaps"]


class SourceSplit(SourceUpdate):
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
            rows: np.ndarray = self._G[J]
            return rows
        rows = self._A[J] @ self._G
        return rows

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

