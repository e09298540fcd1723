"""Smoothing splines whose GCV fit is remembered, in memory and on disk.

Choosing a smoothing spline's penalty by generalised cross-validation
(:func:`hw_emulation.gcv_spline.gcv_lambda`) costs a few tenths of a second per turning route,
and every process that builds the same truth (the emulator, the launcher's evaluation, `slcp
report`, the tests) fits the same routes again. The fit is a pure function of its samples, so its
knots and coefficients are kept under a key made of the samples' bytes and the scipy version: a
spline read back is bit for bit the one the fit would give. (A run seed that redraws a driver's
lateral offset makes new samples, and a new entry of about 30 kB.)

The disk cache lives in ``$SLCP_CACHE_DIR``, else ``$XDG_CACHE_HOME/slcp``, else
``~/.cache/slcp``; ``SLCP_CACHE_DIR=none`` turns it off. A cache that cannot be read or written is
skipped (the spline is fitted), never an error.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

_MEMORY: dict[str, tuple[np.ndarray, np.ndarray]] = {}
_MEMORY_MAX = 256


def cache_dir() -> Path | None:
    """Where fitted splines are kept on disk, or None when the disk cache is off."""
    env = os.environ.get("SLCP_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "none", "off") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "slcp"


def _key(x: np.ndarray, y: np.ndarray) -> str:
    import scipy

    h = hashlib.sha256(f"gcv-smoothing-spline/2/scipy-{scipy.__version__}/{x.shape}/{y.shape}/".encode())
    h.update(np.ascontiguousarray(x, "<f8").tobytes())
    h.update(np.ascontiguousarray(y, "<f8").tobytes())
    return h.hexdigest()


def _read(path: Path, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    try:
        with np.load(path, allow_pickle=False) as z:
            t, c = np.array(z["t"], float), np.array(z["c"], float)
    except FileNotFoundError:
        return None
    except Exception as e:  # empty, truncated or corrupt (EOFError, BadZipFile, ...): never an error
        log.debug("spline cache %s unreadable (%s); fitting again", path, e)
        return None
    # a cubic spline through n samples has n + 6 knots and n + 2 coefficients
    if t.shape != (n + 6,) or c.shape != (n + 2,) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(c))):
        log.debug("spline cache %s does not fit its key; fitting again", path)
        return None
    return t, c


def _write(path: Path, t: np.ndarray, c: np.ndarray) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".npz")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, t=t, c=c)
            os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the whole new one
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:
        log.debug("spline cache %s not written (%s)", path, e)


def gcv_smoothing_spline(x: np.ndarray, y: np.ndarray):
    """The cubic smoothing spline of 1-D ``y`` whose penalty minimises the GCV criterion
    (``scipy.interpolate.make_smoothing_spline(x, y)``, to the search's tolerance), from the
    cache when these samples were fitted before."""
    from scipy.interpolate import BSpline, make_smoothing_spline

    from .gcv_spline import gcv_lambda

    x, y = np.asarray(x, float), np.asarray(y, float)
    if y.ndim != 1:
        raise ValueError(f"y must be one-dimensional, got shape {y.shape}")
    key = _key(x, y)
    hit = _MEMORY.pop(key, None)  # re-inserted below: the dict's order is the use order
    where = cache_dir()
    path = where / f"{key}.npz" if where is not None else None
    if hit is None and path is not None:
        hit = _read(path, len(x))
    if hit is None:
        spl = make_smoothing_spline(x, y, lam=gcv_lambda(x, y))
        hit = (np.array(spl.t, float), np.array(spl.c, float))
        if path is not None:
            _write(path, *hit)
    for a in hit:
        a.flags.writeable = False  # shared by every spline made from this entry
    while len(_MEMORY) >= _MEMORY_MAX:
        _MEMORY.pop(next(iter(_MEMORY)))  # the least recently used
    _MEMORY[key] = hit
    return BSpline(hit[0], hit[1], 3, extrapolate=True)
