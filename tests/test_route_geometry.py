"""Route geometry of the emulated world: the GCV smoothing spline read back from its cache is the
one the fit gives, a bad cache is refitted, and the body-to-NED DCMs of a trajectory agree with
scipy's Euler conversion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import make_smoothing_spline
from scipy.spatial.transform import Rotation

from slcp.hw_emulation import smoothing_cache
from slcp.hw_emulation.gcv_spline import gcv_lambda
from slcp.hw_emulation.geometry import Path as RoutePath
from slcp.hw_emulation.geometry import bezier_turn
from slcp.hw_emulation.kinematics import _dcm_bn


@pytest.fixture
def samples() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    x = np.linspace(0.0, 80.0, 161)
    return x, np.arctan(x / 20.0) + rng.normal(0.0, 0.01, x.size)


@pytest.fixture
def disk(tmp_path, monkeypatch):
    monkeypatch.setenv("SLCP_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(smoothing_cache, "_MEMORY", {})
    return tmp_path


def test_a_cached_spline_is_the_fitted_one_bit_for_bit(samples, disk) -> None:
    x, y = samples
    fresh = make_smoothing_spline(x, y, lam=gcv_lambda(x, y))
    first = smoothing_cache.gcv_smoothing_spline(x, y)
    files = list(disk.glob("*.npz"))
    assert len(files) == 1
    smoothing_cache._MEMORY.clear()  # the next one comes from the disk
    again = smoothing_cache.gcv_smoothing_spline(x, y)
    q = np.linspace(-5.0, 85.0, 997)
    for spl in (first, again):
        assert np.array_equal(spl(q), fresh(q))
        assert np.array_equal(spl.derivative(1)(q), fresh.derivative(1)(q))
    # other samples, another entry
    smoothing_cache.gcv_smoothing_spline(x, y + 1e-9)
    assert len(list(disk.glob("*.npz"))) == 2


@pytest.mark.parametrize("damage", ["garbage", "empty", "truncated", "wrong-size", "nan"])
def test_a_damaged_cache_entry_is_refitted_and_replaced(samples, disk, damage) -> None:
    x, y = samples
    smoothing_cache.gcv_smoothing_spline(x, y)
    (entry,) = disk.glob("*.npz")
    if damage == "garbage":
        entry.write_bytes(b"\x00not a numpy archive")
    elif damage == "empty":
        entry.write_bytes(b"")
    elif damage == "truncated":  # a write cut short (a power loss)
        entry.write_bytes(entry.read_bytes()[:200])
    elif damage == "wrong-size":
        np.savez(entry, t=np.zeros(3), c=np.zeros(2))
    else:
        with np.load(entry) as z:
            t, c = z["t"], z["c"].copy()
        c[5] = np.nan
        np.savez(entry, t=t, c=c)
    smoothing_cache._MEMORY.clear()
    spl = smoothing_cache.gcv_smoothing_spline(x, y)
    q = np.linspace(0.0, 80.0, 101)
    assert np.array_equal(spl(q), make_smoothing_spline(x, y, lam=gcv_lambda(x, y))(q))
    smoothing_cache._MEMORY.clear()
    assert smoothing_cache._read(entry, x.size) is not None  # rewritten whole


def test_the_disk_cache_can_be_turned_off(samples, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("SLCP_CACHE_DIR", "none")
    monkeypatch.setattr(smoothing_cache, "_MEMORY", {})
    assert smoothing_cache.cache_dir() is None
    smoothing_cache.gcv_smoothing_spline(*samples)
    monkeypatch.delenv("SLCP_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert smoothing_cache.cache_dir() == tmp_path / "slcp"


def test_an_unwritable_cache_fits_and_goes_on(samples, tmp_path, monkeypatch) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("SLCP_CACHE_DIR", str(blocker / "cache"))
    monkeypatch.setattr(smoothing_cache, "_MEMORY", {})
    x, y = samples
    q = np.linspace(0.0, 80.0, 11)
    assert np.array_equal(smoothing_cache.gcv_smoothing_spline(x, y)(q),
                          make_smoothing_spline(x, y, lam=gcv_lambda(x, y))(q))


def test_a_turn_s_heading_and_curvature_follow_the_bezier(disk) -> None:
    """A right turn of 90° joining two straight lanes: the smoothed heading starts at 0 and ends
    at 90°, and its rate integrates to the turn."""
    east = bezier_turn(np.array([0.0, 0.0]), 0.0, np.array([20.0, 20.0]), np.pi / 2)
    pts = np.vstack([[[-50.0, 0.0]], east, [[20.0, 70.0]]])
    path = RoutePath(pts)
    assert path.heading(np.array([5.0]))[0] == pytest.approx(0.0, abs=0.02)
    assert path.heading(np.array([path.length - 5.0]))[0] == pytest.approx(np.pi / 2, abs=0.02)
    s = np.linspace(0.0, path.length, 4001)
    k = path.curvature(s)
    turned = float(np.sum(0.5 * (k[1:] + k[:-1]) * np.diff(s)))
    assert turned == pytest.approx(float(path.heading(s[-1:])[0] - path.heading(s[:1])[0]), rel=1e-3)
    assert path.curvature(np.array([-1.0, path.length + 1.0])).tolist() == [0.0, 0.0]


def test_the_trajectory_dcms_are_scipys_euler_rotations() -> None:
    rng = np.random.default_rng(3)
    euler = np.column_stack([rng.uniform(-0.3, 0.3, 500), rng.uniform(-0.3, 0.3, 500),
                             rng.uniform(-np.pi, np.pi, 500)])
    ref = Rotation.from_euler("ZYX", euler[:, ::-1]).as_matrix()
    assert np.allclose(_dcm_bn(euler), ref, atol=1e-14, rtol=0)


@pytest.mark.parametrize("case", ["noisy-curve", "turn-headings"])
def test_the_fast_gcv_penalty_is_scipys(case) -> None:
    """Two ways to the GCV penalty: scipy's own search (make_smoothing_spline without lam) and
    gcv_lambda's, the same criterion with a faster inverse-band recursion. Same penalty to the
    minimiser's tolerance (the criterion is flat at its minimum: the two searches stop 1e-5
    apart), the same spline to a microradian."""
    from slcp.hw_emulation.gcv_spline import _inverse_bands

    if case == "noisy-curve":
        rng = np.random.default_rng(2)
        x = np.sort(rng.uniform(0.0, 50.0, 120))
        y = np.sin(x / 6.0) + rng.normal(0.0, 0.05, x.size)
    else:  # the chord headings of a resampled 90° turn (what a route's heading is fitted to)
        east = bezier_turn(np.array([0.0, 0.0]), 0.0, np.array([20.0, 20.0]), np.pi / 2)
        pts = np.vstack([[[-40.0, 0.0]], east, [[20.0, 60.0]]])
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        s = np.concatenate([[0.0], np.cumsum(seg)])
        ss = np.linspace(0.0, s[-1], int(np.ceil(s[-1] / 0.5)) + 1)
        xy = np.column_stack([np.interp(ss, s, pts[:, 0]), np.interp(ss, s, pts[:, 1])])
        d = np.diff(xy, axis=0)
        y = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        x = 0.5 * (ss[1:] + ss[:-1])
    import scipy.interpolate._bsplines as scipy_bsplines

    found = []
    search = scipy_bsplines.minimize_scalar

    def spy(*a, **k):  # scipy's own penalty, as its search returns it
        r = search(*a, **k)
        found.append(float(r.x))
        return r

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(scipy_bsplines, "minimize_scalar", spy)
        ref = make_smoothing_spline(x, y)
    lam = gcv_lambda(x, y)
    assert found and lam == pytest.approx(found[0], rel=1e-4)
    mine = make_smoothing_spline(x, y, lam=lam)
    q = np.linspace(x[0], x[-1], 2001)
    assert np.max(np.abs(mine(q) - ref(q))) < 1e-6
    # the inverse bands against a dense inverse
    rng = np.random.default_rng(4)
    n = 12
    a = np.zeros((n, n))
    for k in range(4):
        v = rng.uniform(-0.2, 0.2, n - k) if k else rng.uniform(3.0, 4.0, n)
        a += np.diag(v, k) + (np.diag(v, -k) if k else 0.0)
    band = np.zeros((4, n))
    for k in range(4):
        band[3 - k, k:] = np.diag(a, k)
    inv = np.linalg.inv(a)
    got = _inverse_bands(band)
    for k in range(3):
        np.testing.assert_allclose(got[3 - k, k:], np.diag(inv, k), rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="increasing"):
        gcv_lambda(x[::-1], y)


def test_a_long_route_s_spline_bands_need_no_dense_matrix() -> None:
    """The penalised spline's design matrix has four entries a row: its bands are read from the
    sparse matrix. A dense copy of it was n × (n + 2): 20 GB for the 50,000 chords of a 25 km
    route at 0.5 m, a MemoryError where the bands need a few MB."""
    import tracemalloc

    from slcp.hw_emulation.gcv_spline import _bands

    x = np.linspace(0.0, 25_000.0, 50_000)
    tracemalloc.start()
    X, wE = _bands(x)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert X.shape == wE.shape == (5, x.size) and np.all(np.isfinite(X)) and np.all(np.isfinite(wE))
    assert peak < 100e6, peak
