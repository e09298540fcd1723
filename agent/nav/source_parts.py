"""The vocabulary of covariance intersection by source (:mod:`agent.nav.source_fusion`): the
source labels, a measurement's parts by source, and the small pure functions the update uses."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

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
