"""The idealised pooling reference (`deploy/pooling.py`): closed form, Monte-Carlo consistency
and refusals."""

from __future__ import annotations

import numpy as np
import pytest

from slcp.deploy.pooling import main, pool_translation

from conftest import short_scenario


def test_two_estimates_pool_to_the_information_weighted_mean() -> None:
    """Closed form for two vehicles: (P1⁻¹ + P2⁻¹)⁻¹ (P1⁻¹ e1 + P2⁻¹ e2); equal covariances
    give the mean and half the covariance."""
    p1 = np.array([[0.09, 0.02], [0.02, 0.04]])
    p2 = np.array([[1.0, -0.3], [-0.3, 2.0]])
    e1, e2 = np.array([0.3, -0.1]), np.array([-1.0, 2.0])
    err, cov = pool_translation({"A": e1[None], "B": e2[None]}, {"A": p1[None], "B": p2[None]})
    i1, i2 = np.linalg.inv(p1), np.linalg.inv(p2)
    want_cov = np.linalg.inv(i1 + i2)
    np.testing.assert_allclose(cov[0], want_cov, rtol=1e-12)
    np.testing.assert_allclose(err[0], want_cov @ (i1 @ e1 + i2 @ e2), rtol=1e-12)
    err, cov = pool_translation({"A": e1[None], "B": e2[None]}, {"A": p1[None], "B": p1[None]})
    np.testing.assert_allclose(err[0], (e1 + e2) / 2, rtol=1e-12)
    np.testing.assert_allclose(cov[0], p1 / 2, rtol=1e-12)


def test_independent_errors_pool_consistently() -> None:
    """Seeded Monte-Carlo: 18 vehicles with independent errors drawn from their own covariances
    (decimetres to metres): the pooled NEES averages 2 over 4,000 draws (n = 2), and the pooled
    error is smaller than the best single vehicle's."""
    rng = np.random.default_rng(7)
    n, ids = 4000, [f"V{i}" for i in range(18)]
    errs, covs = {}, {}
    for v in ids:
        a = rng.normal(size=(2, 2)) * rng.uniform(0.1, 2.0)
        p = a @ a.T + np.eye(2) * 0.01
        errs[v] = rng.multivariate_normal(np.zeros(2), p, size=n)
        covs[v] = np.broadcast_to(p, (n, 2, 2)).copy()
    err, cov = pool_translation(errs, covs)
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    assert nees.mean() == pytest.approx(2.0, abs=0.12)
    best = min(np.trace(covs[v][0]) for v in ids)
    assert np.mean(np.sum(err**2, axis=1)) < best


def test_nothing_to_pool_and_bad_arguments_are_refused(capsys) -> None:
    with pytest.raises(ValueError, match="no vehicles"):
        pool_translation({}, {})
    assert main(["paper-1", "--seeds", "0,x"]) == 2
    assert "pooling: error" in capsys.readouterr().err
    assert main(["nope"]) == 2
    assert "unknown scenario" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_the_reference_on_paper_1_in_process(capsys, tmp_path) -> None:
    """paper-1 (to 25 s) seed 0: rows for the vehicles that stand (V1, V2; V0 never does), the
    pooled reference beside SL-SP and SL-CP, over the same records."""
    assert main([str(short_scenario(tmp_path, "paper-1", 25.0)), "--seeds", "0"]) == 0
    out = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line for line in out[2:]}
    assert set(rows) == {"V1", "V2"}
    assert "pooled SL-SP" in out[1] and "SL-CP" in out[1]
    for line in rows.values():
        cells = line.split()[2:]
        assert len(cells) == 3 * 5  # three "rmse / ratio / anees" cells
        assert all(float(x) > 0.0 for x in cells if x != "/")
