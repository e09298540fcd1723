"""Closed forms that replace scipy in the agent process, checked against scipy, and the check
that an agent process imports no scipy at all (its memory budget, issue #7)."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from slcp.agent.nav.fusion import fminbound
from slcp.agent.nav.kalman import chi2_gate, chi2_survival
from slcp.agent.nav.rotation import dcm_to_quat, euler_to_dcm, euler_to_quat, quat_to_dcm


def test_euler_and_quaternion_conversions_equal_scipys(rng) -> None:
    angles = np.column_stack([rng.uniform(-math.pi, math.pi, 300), rng.uniform(-1.55, 1.55, 300),
                              rng.uniform(-math.pi, math.pi, 300)])
    angles = np.vstack([angles, [[0, 0, 0], [math.pi, 0, 0], [0, 0, math.pi], [0.3, math.pi / 2, 0.2]]])
    for r, p, y in angles:
        ref = Rotation.from_euler("ZYX", [y, p, r])
        np.testing.assert_allclose(euler_to_dcm(r, p, y), ref.as_matrix(), atol=1e-14)
        x, yq, z, w = ref.as_quat()
        q = euler_to_quat(r, p, y)
        np.testing.assert_allclose(q, np.sign(w or 1.0) * np.array([w, x, yq, z]), atol=1e-14)
        np.testing.assert_allclose(quat_to_dcm(q), ref.as_matrix(), atol=1e-14)


def test_dcm_to_quaternion_is_accurate_for_every_rotation(rng) -> None:
    rots = list(Rotation.random(500, random_state=1)) + [Rotation.from_rotvec(a * np.array(v)) for a in
                                                          (math.pi, math.pi - 1e-9, 1e-12)
                                                          for v in ([1, 0, 0], [0, 1, 0], [0, 0, 1], [0.6, 0.8, 0])]
    for r in rots:
        c = r.as_matrix()
        q = dcm_to_quat(c)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-14
        np.testing.assert_allclose(quat_to_dcm(q), c, atol=1e-13)


def test_chi_square_quantile_and_survival_equal_scipys() -> None:
    for dof, p in itertools.product(range(1, 16), (0.5, 0.9, 0.95, 0.99, 0.999, 0.9999, 1 - 1e-7)):
        assert chi2_gate(dof, p) == pytest.approx(chi2.ppf(p, dof), rel=1e-10)
    for dof, x in itertools.product(range(1, 12), (0.01, 0.5, 3.0, 11.3, 40.0)):
        assert chi2_survival(x, dof) == pytest.approx(chi2.sf(x, dof), rel=1e-10, abs=1e-300)
    for bad in ((0, 0.9), (2, 1.0), (2, 0.0), (1.5, 0.9)):
        with pytest.raises(ValueError):
            chi2_gate(*bad)


@pytest.mark.parametrize("lo, hi", [(0.01, 0.99), (-3.0, -0.5), (-2.0, 5.0)])
def test_bounded_minimiser_takes_scipys_steps(rng, lo: float, hi: float) -> None:
    """The same iterates as ``minimize_scalar(method="bounded")``: identical minimisers on
    smooth, kinked and flat functions, including minima on the bounds, on intervals on either
    side of zero (the fusion rules search [0, 1])."""
    for _ in range(500):
        c, a, k = rng.uniform(lo - 0.5, hi + 0.5), rng.uniform(0.1, 10.0), rng.uniform(1.1, 4.0)
        b = rng.uniform(-2, 2)
        for f in (lambda x, a=a, b=b, c=c, k=k: a * abs(x - c) ** k + b * x,
                  lambda x, a=a, c=c: math.cosh(a * (x - c)), lambda x: 1.0):
            ours = fminbound(f, lo, hi, xatol=1e-3)
            ref = minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3}).x
            assert ours == ref


@pytest.mark.fleet
def test_an_agent_process_imports_no_scipy() -> None:
    """Loading an agent's configuration (scenario site map and sensors) and its runtime pulls in
    no scipy module: scipy's packages would take an agent past its 80 MB memory budget."""
    code = ("import sys, tempfile, pathlib\n"
            "from slcp.deploy.processes import load_agent_config\n"
            "p = pathlib.Path(tempfile.mkdtemp()) / 'a.toml'\n"
            "p.write_text('[agent]\\nvehicle = \"V1\"\\nscenario = \"paper-1\"\\n')\n"
            "load_agent_config(p, None)\n"
            "import slcp.agent.runtime, slcp.transport.zenoh_bus, slcp.transport.security, slcp.deploy.processes\n"
            "print(sorted(m for m in sys.modules if m == 'scipy' or m.startswith('scipy.')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
