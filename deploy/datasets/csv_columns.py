"""The ``csv`` format: two CSV files with a header row whose column names declare their units.

A folder holds ``imu.csv`` and ``gnss.csv``. Columns may come in any order; others are ignored.

``imu.csv``: ``t_s`` and either rates or increments, in the IMU's frame:

* rates: ``ax_U ay_U az_U`` with U one of ``mps2``, ``g``, ``mg``, and ``gx_U gy_U gz_U`` with
  U one of ``radps``, ``dps``;
* increments over the interval ending at ``t_s``: ``dvx_mps dvy_mps dvz_mps`` and
  ``dthx_U dthy_U dthz_U`` with U one of ``rad``, ``deg`` (the first row only starts the first
  interval).

``gnss.csv``: ``t_s lat_deg lon_deg h_m`` and the σ ``sdn_m sde_m sdu_m`` (or one ``sdh_m``
for both horizontal axes and ``sdu_m``); optionally ``vn_mps ve_mps vd_mps`` with ``sdv_mps``
(or ``sdvn_mps sdve_mps sdvd_mps``), ``quality`` (1 fixed RTK, 2 float RTK, other: a code
solution) and ``n_sat``. An empty velocity cell means the epoch has no velocity. Example::

    t_s,ax_g,ay_g,az_g,gx_dps,gy_dps,gz_dps
    1752003261.864,0.1177,0.0307,1.0054,0.02,-0.11,0.05

    t_s,lat_deg,lon_deg,h_m,sdn_m,sde_m,sdu_m,vn_mps,ve_mps,vd_mps,sdv_mps,quality
    1752003258.499,40.0966120,-105.1474310,1601.82,0.010,0.010,0.012,0.00,0.01,0.00,0.04,1
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from . import DatasetError
from .recording import GnssLog, ImuLog, Recording, gnss_log, imu_log, rates_from_increments

G0 = 9.80665
ACCEL_UNITS = {"mps2": 1.0, "g": G0, "mg": 1e-3 * G0}
RATE_UNITS = {"radps": 1.0, "dps": math.pi / 180.0}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180.0}


def _read(path: Path) -> tuple[list[str], np.ndarray]:
    """Header and values (empty cells NaN) of a CSV file."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise DatasetError(f"{path}: not a CSV text file ({exc})") from None
    if len(rows) < 2:
        raise DatasetError(f"{path}: needs a header row and data rows")
    head = [h.strip() for h in rows[0]]
    out = np.full((len(rows) - 1, len(head)), np.nan)
    for i, row in enumerate(rows[1:]):
        if len(row) != len(head):
            raise DatasetError(f"{path}:{i + 2}: {len(row)} cells, the header has {len(head)}")
        for j, cell in enumerate(row):
            if cell.strip():
                try:
                    out[i, j] = float(cell)
                except ValueError:
                    raise DatasetError(f"{path}:{i + 2}: column {head[j]}: not a number: {cell!r}") from None
    return head, out


def _triple(path: Path, head: list[str], a: np.ndarray, stems: tuple[str, str, str],
            units: dict[str, float]) -> np.ndarray | None:
    """Three columns ``stem_U`` in one unit of ``units``, converted to SI (None if absent)."""
    for unit, scale in units.items():
        names = [f"{s}_{unit}" for s in stems]
        if all(n in head for n in names):
            return np.column_stack([a[:, head.index(n)] for n in names]) * scale
    if any(h.split("_")[0] in stems for h in head):
        raise DatasetError(f"{path}: columns {', '.join(stems)} need one unit of {', '.join(units)} "
                           f"(e.g. {stems[0]}_{next(iter(units))})")
    return None


def _col(head: list[str], a: np.ndarray, name: str) -> np.ndarray | None:
    return a[:, head.index(name)] if name in head else None


def read_imu(path: str | Path) -> ImuLog:
    """``imu.csv``: rates or increments (see the module doc)."""
    path = Path(path)
    head, a = _read(path)
    t = _col(head, a, "t_s")
    if t is None:
        raise DatasetError(f"{path}: no t_s column")
    acc = _triple(path, head, a, ("ax", "ay", "az"), ACCEL_UNITS)
    rate = _triple(path, head, a, ("gx", "gy", "gz"), RATE_UNITS)
    if acc is not None and rate is not None:
        return imu_log(t, acc, rate, str(path))
    dv = _triple(path, head, a, ("dvx", "dvy", "dvz"), {"mps": 1.0})
    dth = _triple(path, head, a, ("dthx", "dthy", "dthz"), ANGLE_UNITS)
    if dv is not None and dth is not None:
        return rates_from_increments(t, dth, dv, str(path))
    raise DatasetError(f"{path}: needs rates (ax_U.. and gx_U..) or increments (dvx_mps.. and dthx_U..)")


def read_gnss(path: str | Path) -> GnssLog:
    """``gnss.csv`` (see the module doc)."""
    path = Path(path)
    head, a = _read(path)
    need = ("t_s", "lat_deg", "lon_deg", "h_m", "sdu_m")
    missing = [n for n in need if n not in head]
    if missing:
        raise DatasetError(f"{path}: missing column(s) {', '.join(missing)}")
    c = {n: a[:, head.index(n)] for n in head}
    if "sdn_m" in c and "sde_m" in c:
        sd = np.column_stack([c["sdn_m"], c["sde_m"], c["sdu_m"]])
    elif "sdh_m" in c:
        sd = np.column_stack([c["sdh_m"], c["sdh_m"], c["sdu_m"]])
    else:
        raise DatasetError(f"{path}: needs sdn_m and sde_m, or sdh_m")
    v = sv = None
    if all(n in c for n in ("vn_mps", "ve_mps", "vd_mps")):
        v = np.column_stack([c["vn_mps"], c["ve_mps"], c["vd_mps"]])
        if all(n in c for n in ("sdvn_mps", "sdve_mps", "sdvd_mps")):
            sv = np.column_stack([c["sdvn_mps"], c["sdve_mps"], c["sdvd_mps"]])
        elif "sdv_mps" in c:
            sv = np.repeat(c["sdv_mps"][:, None], 3, axis=1)
        else:
            raise DatasetError(f"{path}: velocities need sdv_mps (or sdvn_mps, sdve_mps, sdvd_mps)")
    q = c.get("quality")
    if q is not None and not np.all(np.isfinite(q)):
        raise DatasetError(f"{path}: empty quality cells")
    ns = c.get("n_sat")
    return gnss_log(c["t_s"], c["lat_deg"], c["lon_deg"], c["h_m"], sd, v, sv, q,
                    None if ns is None else np.nan_to_num(ns), str(path))


def load(folder: str | Path) -> Recording:
    """The recording in a folder holding ``imu.csv`` and ``gnss.csv``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: not a directory")
    return Recording(read_imu(folder / "imu.csv"), read_gnss(folder / "gnss.csv"))


def write(rec: Recording, folder: str | Path, increments: bool = False, velocity: bool = True) -> None:
    """``rec`` as ``imu.csv`` (rates in m/s² and rad/s, or ``increments``) and ``gnss.csv``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    imu = rec.imu
    if increments:
        dt = np.diff(imu.t, prepend=imu.t[0])[:, None]
        head = "t_s,dvx_mps,dvy_mps,dvz_mps,dthx_rad,dthy_rad,dthz_rad"
        cols = np.column_stack([imu.t, imu.accel * dt, imu.gyro * dt])
    else:
        head = "t_s,ax_mps2,ay_mps2,az_mps2,gx_radps,gy_radps,gz_radps"
        cols = np.column_stack([imu.t, imu.accel, imu.gyro])
    np.savetxt(folder / "imu.csv", cols, fmt=["%.6f"] + ["%.12e"] * 6, delimiter=",", header=head, comments="")
    g = rec.gnss
    lines = ["t_s,lat_deg,lon_deg,h_m,sdn_m,sde_m,sdu_m,vn_mps,ve_mps,vd_mps,sdvn_mps,sdve_mps,sdvd_mps,quality,n_sat"]
    has_v = g.has_velocity & velocity
    for i in range(len(g.t)):
        v = ",".join(f"{x:.4f}" for x in (*g.v_ned[i], *g.sd_v[i])) if has_v[i] else ",,,,,"
        lines.append(f"{g.t[i]:.6f},{math.degrees(g.llh[i, 0]):.10f},{math.degrees(g.llh[i, 1]):.10f},"
                     f"{g.llh[i, 2]:.4f},{g.sd_neu[i, 0]:.4f},{g.sd_neu[i, 1]:.4f},{g.sd_neu[i, 2]:.4f},{v},"
                     f"{int(g.quality[i])},{int(g.n_sat[i])}")
    (folder / "gnss.csv").write_text("\n".join(lines) + "\n")
