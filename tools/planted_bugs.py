"""Plant known bugs one at a time and check that the tests close to the code catch each.

These are the bugs a hand-run mutation study found surviving, or caught only by a test far from
the code; each is a realistic slip (a sign, a factor, a forgotten term). For each bug the script
copies the working tree to a temporary folder, applies the one edit, runs the named tests there,
and expects them to fail; the unmodified copy must pass first. Not part of the test suite (it
runs the selected tests once per bug); run it after touching the code it names::

    python tools/planted_bugs.py            # all bugs
    python tools/planted_bugs.py bound-sign # one
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Bug:
    name: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...]
    count: int = 1  #: occurrences of ``old`` to replace (all of them must exist)


BUGS = (
    Bug("bound-sign", "deploy/bound.py", "-= uu", "+= uu", ("tests/test_bound_batch.py",), count=2),
    Bug("bound-ranges-per-step", "deploy/bound.py", "uwb.rate / (1.0 / (ts[1] - ts[0]))",
        "(1.0 / (ts[1] - ts[0])) / uwb.rate", ("tests/test_bound_batch.py",)),
    Bug("gauss-markov-drive", "agent/nav/error_model.py", "2.0 * sigma**2 / tau", "sigma**2 / tau",
        ("tests/test_error_model.py",)),
    Bug("along-only-sigma", "agent/nav/measurements/stop_line.py", "np.array([[gap.sigma_xb**2]])",
        "np.array([[gap.sigma_yb**2]])", ("tests/test_measurements.py",)),
    Bug("signature-without-velocity", "transport/security.py",
        'encode(dataclasses.replace(beacon, auth=b""))',
        'encode(dataclasses.replace(beacon, auth=b"", v_ned=beacon.v_ned * 0.0))', ("tests/test_security.py",)),
    Bug("misbehaviour-range-own-covariance", "agent/misbehaviour.py",
        "u @ (np.asarray(own_cov_ned) + b.cov) @ u", "u @ b.cov @ u", ("tests/test_misbehaviour.py",)),
    Bug("uwb-outliers-positive", "hw_emulation/sensors/uwb.py", "rng.choice([-1.0, 1.0], n)",
        "np.abs(rng.choice([-1.0, 1.0], n))", ("tests/test_sensor_models.py",)),
    Bug("ned-offset-radius", "geo/earth.py", "(lon - lon0) * (rn + h0) * math.cos(lat0)",
        "(lon - lon0) * rn * math.cos(lat0)", ("tests/test_error_model.py",)),
    Bug("ned-offset-radius-north", "geo/earth.py", "[(lat - lat0) * (rm + h0),", "[(lat - lat0) * rm,",
        ("tests/test_error_model.py",)),
    Bug("codec-row-count", "transport/codec.py", "if n_lead is not None and n != n_lead:",
        "if False and n_lead is not None and n != n_lead:", ("tests/test_transport.py",)),
    Bug("misbehaviour-eigenvalue", "agent/misbehaviour.py",
        "eig_min = 0.5 * (c00 + c11) - math.hypot(0.5 * (c00 - c11), c01)", "eig_min = min(c00, c11)",
        ("tests/test_misbehaviour.py",)),
    Bug("joseph-noise-term", "agent/nav/kalman.py", "P_post = IKH @ P @ IKH.T + K @ R @ K.T",
        "P_post = IKH @ P", ("tests/test_measurements.py",)),
    Bug("gap-accel-cross-term", "agent/nav/error_model.py", "qd[a, b] = qd[b, a] = sa * sa * gap**3 / 2.0",
        "qd[a, b] = qd[b, a] = sa * gap**3 / 2.0", ("tests/test_error_model.py",)),
    Bug("coriolis-position-sign", "agent/nav/error_model.py", "F[3, 6] = -2.0 * ve", "F[3, 6] = +2.0 * ve",
        ("tests/test_error_model.py",)),
    Bug("normal-lower-tail-sign", "agent/range_gate.py",
        "return 0.5 * (math.erfc(-b / _SQRT2) - math.erfc(-a / _SQRT2))",
        "return 0.5 * (math.erfc(-b / _SQRT2) - math.erfc(a / _SQRT2))", ("tests/test_nlos.py",)),
    Bug("link-rate-uncertainty-sign", "agent/range_gate.py", "/ 3.0) + self.rate_sigma * dt",
        "/ 3.0) - self.rate_sigma * dt", ("tests/test_nlos.py",)),
    Bug("codec-sources-dtype", "transport/codec.py",
        'np.ascontiguousarray(c, dtype="<f8").tobytes()] for lab, c in val',
        "np.ascontiguousarray(c).tobytes()] for lab, c in val", ("tests/test_transport.py",)),
    Bug("imu-misalignment-not-skew", "hw_emulation/sensors/imu.py", "[-m[1], m[0], 0.0]]", "[m[1], m[0], 0.0]]",
        ("tests/test_sensor_models.py",)),
)


def _copy_tree(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT, check=True,
                           capture_output=True, text=True).stdout.split()
    for f in files:
        src = ROOT / f
        if src.is_file():
            (dest / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / f)


def _pytest(tree: Path, tests: tuple[str, ...], timeout: float) -> tuple[int, float]:
    t0 = time.monotonic()
    rc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests],
                        cwd=tree, capture_output=True, timeout=timeout).returncode
    return rc, time.monotonic() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bugs", nargs="*", help=f"bug names (default: all): {', '.join(b.name for b in BUGS)}")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per test run (default 900)")
    args = ap.parse_args(argv)
    unknown = set(args.bugs) - {b.name for b in BUGS}
    if unknown:
        ap.error(f"unknown bugs: {', '.join(sorted(unknown))}")
    bugs = [b for b in BUGS if not args.bugs or b.name in args.bugs]
    survivors = []
    with tempfile.TemporaryDirectory(prefix="slcp-planted-") as tmp:
        tree = Path(tmp)
        _copy_tree(tree)
        for tests in sorted({b.tests for b in bugs}):
            rc, secs = _pytest(tree, tests, args.timeout)
            if rc != 0:
                print(f"the unmodified tree fails {' '.join(tests)} (exit {rc}): fix that first")
                return 2
        for b in bugs:
            target = tree / b.path
            original = target.read_text()
            if original.count(b.old) != b.count:
                print(f"{b.name}: expected {b.count} occurrence(s) of {b.old!r} in {b.path}, "
                      f"found {original.count(b.old)}: update the bug list")
                return 2
            target.write_text(original.replace(b.old, b.new))
            try:
                rc, secs = _pytest(tree, b.tests, args.timeout)
            finally:
                target.write_text(original)
            caught = rc != 0
            print(f"{b.name:36s} {'caught' if caught else 'SURVIVED'} by {' '.join(b.tests)} ({secs:.1f} s)")
            if not caught:
                survivors.append(b.name)
    print(f"{len(bugs) - len(survivors)} of {len(bugs)} planted bugs caught")
    return 1 if survivors else 0


if __name__ == "__main__":
    sys.exit(main())
