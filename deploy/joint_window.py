"""Re-linearising the joint reference over a sliding window (:func:`relinearised`).

An EKF linearises each range once, at the estimate of its time; a range whose line of sight is
off by the estimate's own error then adds information across the line of sight that no range
holds, and over hundreds of ranges the filter becomes sure of a geometry that is wrong
(decision 3). A fixed-lag smoother re-linearises the past as the estimate improves. Here, once
every ``every`` seconds, the last ``window`` seconds are smoothed (Rauch-Tung-Striebel) and run
again from the filter as it was at the window's start, every row linearised at the smoothed
estimate of its time (one Gauss-Newton step); the filter then goes on from the re-run. The
outputs stay causal: each is the filter's estimate when its time came. Pure numpy.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .joint_filter import JointFilter

#: one step's record: (x predicted, P predicted, F of the prediction or None, x after, P after)
_Record = tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]


def relinearised(jf: JointFilter, steps: Sequence[Any], do: Callable[[JointFilter, Any, np.ndarray | None], None],
                 output: Callable[[JointFilter, int], None], window: float, every: float = 1.0) -> JointFilter:
    """Run ``steps`` (each a tuple whose first item is its time [s] and last its output index
    or None) through ``jf`` with ``do(filter, step, x0)`` (``x0``: the state to linearise the
    step's rows at, None for the filter's own iterations), calling ``output(filter, index)`` at
    each output step, and re-linearising the last ``window`` s every ``every`` s. ``jf`` must
    keep its state's size (``JointFilter.keep_links``). Returns the filter at the end."""
    if not jf.keep_links:
        raise ValueError("a re-linearised run needs a filter that keeps its links (keep_links)")
    hist: dict[int, _Record] = {}
    anchor_i, anchor = 0, copy.deepcopy(jf)
    last = float(steps[0][0]) if steps else 0.0
    for i, st in enumerate(steps):
        do(jf, st, None)
        hist[i] = _record(jf)
        if st[-1] is not None:
            output(jf, st[-1])
        t = float(st[0])
        if t - last < every or i <= anchor_i:
            continue
        last = t
        lin = smoothed(hist, anchor_i, i)
        f, new_anchor = copy.deepcopy(anchor), None
        for j in range(anchor_i, i + 1):
            if new_anchor is None and float(steps[j][0]) >= t - window:
                new_anchor = (j, copy.deepcopy(f))
            do(f, steps[j], lin.get(j))
            hist[j] = _record(f)
        jf = f
        anchor_i, anchor = new_anchor if new_anchor is not None else (i, copy.deepcopy(f))
        for j in [j for j in hist if j < anchor_i]:
            del hist[j]
    return jf


def smoothed(hist: dict[int, _Record], first: int, last: int) -> dict[int, np.ndarray]:
    """Rauch-Tung-Striebel over the records ``first`` to ``last``: the smoothed state of each
    (the last one's is its filtered state). A step whose prediction covered no time passes the
    smoothed state back unchanged."""
    xs = hist[last][3]
    out = {last: xs}
    for j in range(last - 1, first - 1, -1):
        x_pred, P_pred, F = hist[j + 1][0], hist[j + 1][1], hist[j + 1][2]
        if F is None:
            xs = hist[j][3] + (xs - x_pred)
        else:
            # C = P_j Fᵀ P_pred⁻¹ (pseudo-inverse: a vehicle not started yet has a zero block)
            C = hist[j][4] @ F.T @ np.linalg.pinv(P_pred, hermitian=True)
            xs = hist[j][3] + C @ (xs - x_pred)
        out[j] = xs
    return out


def _record(f: JointFilter) -> _Record:
    x_pred, P_pred, F = f.last_pred
    return x_pred, P_pred, F, f.x.copy(), f.P.copy()
