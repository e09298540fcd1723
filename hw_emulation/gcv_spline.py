"""The generalised cross-validation (GCV) choice of a cubic smoothing spline's penalty, fast.

``scipy.interpolate.make_smoothing_spline(x, y)`` without ``lam`` minimises the GCV criterion
(Wahba 1990) over the penalty; each of the minimiser's ~40 evaluations needs the central bands of
a banded matrix's inverse (Hutchinson & de Hoog 1985), which scipy computes in an interpreted
double loop: about 60 ms for a route of 1,600 samples, two to three seconds a turning route.
:func:`gcv_lambda` is the same criterion, the same minimiser and the same recursion with its
inner loop on plain floats and the residual term vectorised: about ten times faster, and the
same penalty to the minimiser's tolerance (the floating-point sums run in another order).

The construction follows scipy 1.17's ``_bsplines.py`` (BSD-3-Clause, the SciPy developers):
natural-spline design matrix X and penalty W⁻¹E in LAPACK band storage, criterion
``GCV(λ) = n ‖λ W⁻¹E c‖² / (n - tr A(λ))²`` with ``(X + λ W⁻¹E) c = y``.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import BSpline
from scipy.linalg import cholesky_banded, solve_banded
from scipy.optimize import minimize_scalar


def _divided_difference_coefficients(x: np.ndarray) -> np.ndarray:
    """Coefficients of the divided difference over the points ``x``: 1 / Π_{k≠i} (x_i − x_k)."""
    d = x[:, None] - x[None, :]
    np.fill_diagonal(d, 1.0)
    return 1.0 / np.prod(d, axis=1)


def _bands(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """X (the natural-spline design matrix) and W⁻¹E (the penalty, unit weights), 5 bands each."""
    n = x.size
    t = np.r_[[x[0]] * 3, x, [x[-1]] * 3]
    # sparse (4 entries a row): a dense n × (n + 2) copy is 3 GB at n = 20,000
    xb = BSpline.design_matrix(x, t, 3).tocsr()
    X = np.zeros((5, n))
    for i in range(1, 4):  # xb[i + k, 3 + k], k = 0 … n − 5: its diagonal at offset 3 − i
        X[i, 2:-2] = xb.diagonal(3 - i)[i:i + n - 4]
    X[1, 1] = xb[0, 0]
    X[2, :2] = ((x[2] + x[1] - 2 * x[0]) * xb[0, 0], xb[1, 1] + xb[1, 2])
    X[3, :2] = ((x[2] - x[0]) * xb[1, 1], xb[2, 2])
    X[1, -2:] = (xb[-3, -3], (x[-1] - x[-3]) * xb[-2, -2])
    X[2, -2:] = (xb[-2, -3] + xb[-2, -2], (2 * x[-1] - x[-2] - x[-3]) * xb[-1, -1])
    X[3, -2] = xb[-1, -1]
    wE = np.zeros((5, n))
    wE[2:, 0] = _divided_difference_coefficients(x[:3])
    wE[1:, 1] = _divided_difference_coefficients(x[:4])
    for j in range(2, n - 2):
        wE[:, j] = (x[j + 2] - x[j - 2]) * _divided_difference_coefficients(x[j - 2:j + 3])
    wE[:-1, -2] = -_divided_difference_coefficients(x[-4:])
    wE[:-2, -1] = _divided_difference_coefficients(x[-3:])
    wE *= 6
    return X, wE


def _xt_y(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """The 4 unique bands of the symmetric 7-band product Xᵀ Y of two 5-band matrices."""
    n = X.shape[1]
    res = np.zeros((4, n))
    for i in range(n):
        for j in range(min(n - i, 4)):
            res[-j - 1, i + j] = np.sum(X[j:, i] * Y[:5 - j, i + j])
    return res


def _inverse_bands(A: np.ndarray) -> np.ndarray:
    """The 4 central bands (upper band storage) of the inverse of the symmetric positive definite
    7-band matrix ``A`` (upper band storage, shape (4, n)): Hutchinson & de Hoog's recursion from
    the last row up, on the unit upper triangular factor of A = Uᵀ D⁻¹ U."""
    U = cholesky_banded(A)
    for i in range(2, 5):
        U[-i, i - 1:] /= U[-1, :-i + 1]
    d = (1.0 / U[-1] ** 2).tolist()
    n = U.shape[1]
    u = [None, U[-2].tolist(), U[-3].tolist(), U[-4].tolist()]  # u[k][c]: row c - k, column c
    b = [[0.0] * n for _ in range(4)]  # b[k][c]: the inverse at row c - k, column c
    u1, u2, u3 = u[1], u[2], u[3]
    b0, b1, b2, b3 = b
    for i in range(n - 1, n - 4, -1) if n > 3 else range(n - 1, -1, -1):  # the last rows: shorter sums
        r = min(3, n - i - 1)
        for j in range(r, 0, -1):
            s = 0.0
            for k in range(1, r + 1):
                s -= u[k][i + k] * b[abs(k - j)][i + max(k, j)]
            b[j][i + j] = s
        s = d[i]
        for k in range(1, r + 1):
            s -= u[k][i + k] * b[k][i + k]
        b[0][i] = s
    for i in range(n - 4, -1, -1):  # the same sums written out for three bands (most of the rows)
        p1, p2, p3 = u1[i + 1], u2[i + 2], u3[i + 3]
        b3[i + 3] = -p1 * b2[i + 3] - p2 * b1[i + 3] - p3 * b0[i + 3]
        b2[i + 2] = -p1 * b1[i + 2] - p2 * b0[i + 2] - p3 * b1[i + 3]
        b1[i + 1] = -p1 * b0[i + 1] - p2 * b1[i + 2] - p3 * b2[i + 3]
        b0[i] = d[i] - p1 * b1[i + 1] - p2 * b2[i + 2] - p3 * b3[i + 3]
    B = np.array([b3, b2, b1, b0])
    B[0] = 0.0  # the first row of the storage is outside the matrix
    return B


def gcv_lambda(x: np.ndarray, y: np.ndarray) -> float:
    """The penalty λ that minimises the GCV criterion of the cubic smoothing spline of the
    samples ``y`` (1-D) at the strictly increasing abscissae ``x`` (at least 5), with unit
    weights: ``make_smoothing_spline(x, y, lam=gcv_lambda(x, y))`` is the spline that
    ``make_smoothing_spline(x, y)`` fits."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.ndim != 1 or y.shape != x.shape or x.size < 5:
        raise ValueError(f"x and y must be 1-D of one length of at least 5, got {x.shape} and {y.shape}")
    if np.any(np.diff(x) <= 0):
        raise ValueError("x must be strictly increasing")
    n = x.size
    X, wE = _bands(x)
    XtWX, XtE = _xt_y(X, X), _xt_y(X, wE)
    cols = np.arange(n)

    def gcv(lam: float) -> float:
        c = solve_banded((2, 2), X + lam * wE, y)
        tmp = wE * c
        res = np.zeros(n)
        for j in range(5):  # res[i] = Σ_j tmp[j, i + 2 - j] over the columns inside the matrix
            src = cols + 2 - j
            ok = (src >= 0) & (src < n)
            res[ok] += tmp[j, src[ok]]
        numer = np.linalg.norm(lam * res) ** 2 / n
        tr = _inverse_bands(XtWX + lam * XtE) * XtWX
        tr[:-1] *= 2
        return numer / (1.0 - tr.sum() / n) ** 2

    est = minimize_scalar(gcv, bounds=(0, n), method="Bounded")
    if not est.success:
        raise ValueError(f"GCV found no penalty: {est.message}")
    return float(est.x)
