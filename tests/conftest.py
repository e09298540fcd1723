"""Shared fixtures and helpers for the slcp test-suite."""

from __future__ import annotations

# first, before numpy loads: the test processes run BLAS as slcp's own processes do
# (deploy/blas_threads.py), and their children inherit it
from slcp.deploy import blas_threads  # noqa: F401

# isort: split
import atexit
import contextlib
import math
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from slcp.agent.nav.error_model import ImuNoise
from slcp.agent.nav.rotation import euler_to_quat
from slcp.agent.nav.state import NavState

REPO = Path(__file__).resolve().parents[1]

# The emulator's fitted route splines (hw_emulation.smoothing_cache) are kept for the session, for
# the processes the tests start too, and never in the user's own cache. pytest-xdist's workers
# inherit the folder from the process that made it, which removes it at its exit.
if not (os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get("SLCP_TEST_CACHE_OWNER")):
    _SPLINE_CACHE = tempfile.mkdtemp(prefix="slcp-test-cache-")
    os.environ["SLCP_CACHE_DIR"] = _SPLINE_CACHE
    os.environ["SLCP_TEST_CACHE_OWNER"] = str(os.getpid())
    atexit.register(shutil.rmtree, _SPLINE_CACHE, ignore_errors=True)
    # The processes the tests start (some 250 agents, emulators and commands) import slcp and
    # its dependencies; with PYTHONDONTWRITEBYTECODE set, each compiled slcp anew, a third of
    # its import time. They keep their bytecode where Python keeps it (__pycache__, ignored by
    # git): a session folder for it (PYTHONPYCACHEPREFIX) would also hide the bytecode that pip
    # wrote for the dependencies, which every session then compiled again (about 2.5 s of CPU
    # for an agent's imports, in each worker and process that got there first).
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
SHARED_DRIVE = REPO.parent / "shared" / "data" / "rtklibexplorer_drive_0708"
#: the vehicle profile of the shared drive's car
DRIVE_PROFILE = REPO / "deploy" / "vehicles" / "rtklibexplorer-drive.toml"


def drive_config(outage=None, nhc: bool = True, estimate_time_offset: bool = True):
    """The replay configuration of the shared drive: its car's profile (with the non-holonomic
    constraint and the time-offset estimation as given) and ``outage`` (default: the protocol)."""
    import dataclasses

    from slcp.deploy.replay import OutageProtocol, ReplayConfig
    from slcp.vehicles.profile import load_profile

    p = load_profile(DRIVE_PROFILE)
    p = dataclasses.replace(p, constraints=dataclasses.replace(p.constraints, nhc=nhc),
                            time=dataclasses.replace(p.time, estimate=estimate_time_offset))
    return ReplayConfig(profile=p, outage=outage or OutageProtocol())


def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto``: two workers more than the cores this process may use. A good part of the
    suite's time is spent waiting on processes, sockets and paced playback, which spare workers
    fill with CPU-bound tests (on two cores, four workers keep them busier than three or five)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores + 2


def short_scenario(folder: Path, name: str = "paper-1", duration: float = 25.0) -> Path:
    """A copy of the shipped scenario ``name`` in ``folder`` that ends after ``duration`` s of
    sensor time (for tests of mechanisms that need the fleet running, not the whole drive)."""
    from slcp.hw_emulation.scenario import scenario_lasting

    return scenario_lasting(name, duration, Path(folder))


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for_port(port: int, timeout: float = 20.0) -> None:
    """Until something listens on 127.0.0.1:``port`` (TimeoutError after ``timeout`` s)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise TimeoutError(f"nothing listens on 127.0.0.1:{port}")


def run_group(cmd: list[str], timeout: float) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, capture_output=True, text=True)`` in a new process group, which is
    killed whole (the launcher and every process it started) on a timeout or an interrupt."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        # a hung slcp process dumps its threads' stacks on SIGUSR1 (deploy.cli): keep them
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGUSR1)
        time.sleep(1.0)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        raise AssertionError(f"{' '.join(cmd[-4:])} timed out after {timeout:g} s\n--- stdout (end) ---\n"
                             f"{out[-1500:]}\n--- stderr (end) ---\n{err[-6000:]}") from None
    except BaseException:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        raise
    return subprocess.CompletedProcess(cmd, p.returncode, out, err)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)


def moving_state(yaw: float = 0.6, lat_deg: float = 39.95) -> NavState:
    """A representative moving, tilted vehicle state with non-zero biases."""
    return NavState(
        math.radians(lat_deg), math.radians(116.32), 55.0,
        np.array([8.0, -5.0, 0.3]), euler_to_quat(0.05, -0.03, yaw),
        np.array([1e-4, -2e-4, 3e-4]), np.array([0.02, -0.01, 0.03]),
    )


MEMS_NOISE = ImuNoise(
    arw=math.radians(0.1) / 60, vrw=0.05 / 60,
    gyro_bias_sigma=math.radians(10) / 3600, gyro_bias_tau=3600.0,
    accel_bias_sigma=5e-3, accel_bias_tau=3600.0,
)


def numerical_jacobian(fun, n: int, eps: np.ndarray | float) -> np.ndarray:
    """Central-difference Jacobian of ``fun(dx)`` at ``dx = 0`` with per-state step ``eps``."""
    eps = np.broadcast_to(np.asarray(eps, float), (n,))
    cols = []
    for k in range(n):
        e = np.zeros(n)
        e[k] = eps[k]
        cols.append((np.asarray(fun(e)) - np.asarray(fun(-e))) / (2 * eps[k]))
    return np.stack(cols, axis=-1)


#: perturbation sizes per error state: attitude, velocity, position, gyro bias, accel bias
EPS = np.repeat([1e-4, 1e-3, 1e-2, 1e-6, 1e-4], 3)


def mechanization_drift(truth, n: int | None = None, every: int = 100):
    """Integrate a truth's IMU increments with the mechanisation from the true initial state.

    Returns ``(final_state, worst_position_error_m)`` over the first ``n`` intervals (all by
    default), checking the position every ``every`` samples and at the end.
    """
    from slcp.agent.nav.mechanization import mechanize
    from slcp.geo import earth as _earth

    n = len(truth.t) - 1 if n is None else min(n, len(truth.t) - 1)
    s = NavState(*truth.llh[0], truth.v_ned[0].copy(), euler_to_quat(*truth.euler[0]))
    pth = pdv = None
    worst = 0.0
    for k in range(n):
        s = mechanize(s, truth.dtheta[k], truth.dvel[k], truth.t[k + 1] - truth.t[k], pth, pdv)
        pth, pdv = truth.dtheta[k], truth.dvel[k]
        if (k + 1) % every == 0 or k == n - 1:
            e = _earth.ned_offset(s.lat, s.lon, s.h, *truth.llh[k + 1])
            worst = max(worst, float(np.linalg.norm(e)))
    return s, worst


def count_verifications(trust) -> dict:
    """Wrap ``trust.check_signature`` so that every signature verification is counted in the
    returned dict's ``"n"``."""
    calls = {"n": 0}
    real = trust.check_signature

    def counting(b):
        calls["n"] += 1
        return real(b)

    trust.check_signature = counting
    return calls
