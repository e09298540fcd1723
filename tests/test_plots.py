"""The run's pictures: σ ellipses in closed form, and a map with estimated tracks."""

from __future__ import annotations

import numpy as np

from slcp.deploy.plots import plot_scenario, sigma_ellipse
from slcp.hw_emulation.scenario import load_scenario
from slcp.hw_emulation.truth import build_truth


def test_a_sigma_ellipse_has_the_covariance_s_axes_and_orientation() -> None:
    """A north/east covariance with σ 3 m along a 30° bearing and 1 m across: the 2σ ellipse's
    farthest points are 6 m from its centre along that bearing, its nearest 2 m across it, and
    every point x satisfies xᵀ C⁻¹ x = 4."""
    b = np.radians(30.0)
    u = np.array([np.cos(b), np.sin(b)])  # north, east
    v = np.array([-np.sin(b), np.cos(b)])
    cov = 9.0 * np.outer(u, u) + 1.0 * np.outer(v, v)
    pts = sigma_ellipse(cov, k=2.0, n=3601)  # (east, north)
    ne = pts[:, ::-1]
    q = np.einsum("ni,ij,nj->n", ne, np.linalg.inv(cov), ne)
    np.testing.assert_allclose(q, 4.0, rtol=1e-9)
    r = np.hypot(*ne.T)
    far = ne[np.argmax(r)]
    assert abs(r.max() - 6.0) < 1e-3 and abs(r.min() - 2.0) < 1e-3
    assert abs(abs(far @ u) - 6.0) < 1e-3  # along the 30° bearing


def test_the_map_draws_estimates_beside_the_truth(tmp_path) -> None:
    truth = build_truth(load_scenario("paper-1"))
    est = {}
    for vid, vt in truth.vehicles.items():
        t = vt.truth.t[::50]
        ne = np.column_stack([np.linspace(-100.0, 0.0, t.size), np.full(t.size, 1.75)])
        est[vid] = (t, ne + 0.5, np.tile(np.diag([4.0, 1.0]), (t.size, 1, 1)))
    plot_scenario(truth, tmp_path / "map.png", {"t_0": 0.0}, est, "SL-CP")
    plot_scenario(truth, tmp_path / "truth.png", {"t_0": 0.0})
    data = (tmp_path / "map.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    assert data != (tmp_path / "truth.png").read_bytes()  # the estimates and ellipses are drawn
