"""Reader for RTKLIB-style logs as in rtklibexplorer's GNSS_IMU drive data.

* ``imu_*.csv``: no header; accelerometer x, y, z [g], gyro x, y, z [deg/s], device tick [ms].
  The first and last lines may be partial and are skipped.
* ``imu_*.csv.tag``: RTKLIB (demo5) binary time tags, little-endian: a 60-byte ASCII header,
  uint32 tick_f, uint32 start time (integer GPST seconds, Unix-epoch convention), float64
  fractional second, then 8-byte blocks ``(uint32 tick_ms, uint32 file_pos)``. Device ticks are
  mapped to GPST by stretching them linearly onto ``[start, start + last_tick/1000]``.
* ``*.pos``: RTKLIB solution text. Heights are u-blox ``hMSL`` (mean sea level), velocities are
  north, east, **up**.

All times returned are GPST seconds in the Unix-epoch convention. Units are converted to SI
(m/s², rad/s, radians) here, at the edge.
"""

from __future__ import annotations

import calendar
import math
import struct
from datetime import datetime
from pathlib import Path

import numpy as np

from . import DatasetError
from .recording import GnssLog, ImuLog, Recording, gnss_log, imu_log

G0 = 9.80665  #: standard gravity used by the IMU's "g" unit [m/s²]
TAG_HEADER_LEN = 60


def read_time_tag(path: str | Path) -> tuple[float, float]:
    """Start and end time [s GPST] of a log from its RTKLIB ``.tag`` file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read time-tag file ({exc.strerror})") from exc
    if len(data) < TAG_HEADER_LEN + 16 + 8 or not data.startswith(b"TIMETAG"):
        raise DatasetError(f"{path}: not an RTKLIB time-tag file (bad header or too short)")
    _tick_f, t_int = struct.unpack_from("<II", data, TAG_HEADER_LEN)
    (t_frac,) = struct.unpack_from("<d", data, TAG_HEADER_LEN + 8)
    body = data[TAG_HEADER_LEN + 16:]
    n_blocks = len(body) // 8
    last_tick, _ = struct.unpack_from("<II", body, (n_blocks - 1) * 8)
    start = t_int + t_frac
    if not math.isfinite(start) or last_tick <= 0:
        raise DatasetError(f"{path}: invalid start time or tick span in time tags")
    return start, start + last_tick / 1000.0


def read_imu_csv(path: str | Path, tag_path: str | Path | None = None) -> ImuLog:
    """Read a raw IMU CSV and map its device ticks to GPST with the ``.tag`` file. The first and
    last lines are dropped unread (a logger started or stopped mid-line); any other malformed
    line is an error naming it."""
    path = Path(path)
    start, end = read_time_tag(tag_path if tag_path is not None else Path(str(path) + ".tag"))
    try:
        lines = path.read_bytes().decode("ascii", errors="replace").splitlines()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read IMU file ({exc.strerror})") from exc
    body = lines[1:-1]
    try:
        raw = np.loadtxt(body, delimiter=",", dtype=float, ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"{path}: malformed IMU CSV ({exc}; the first line is line 2)") from exc
    if raw.size == 0:
        raise DatasetError(f"{path}: only {len(body)} IMU samples")
    if raw.shape[1] != 7:
        raise DatasetError(f"{path}: expected 7 columns (acc xyz g, gyro xyz deg/s, tick ms), got {raw.shape[1]}")
    if len(raw) < 100:
        raise DatasetError(f"{path}: only {len(raw)} IMU samples")
    if not np.all(np.isfinite(raw)):
        raise DatasetError(f"{path}: non-finite values in IMU data")
    ticks = raw[:, 6] - raw[0, 6]
    if np.any(np.diff(ticks) <= 0):
        raise DatasetError(f"{path}: device ticks are not strictly increasing")
    t = start + ticks * (end - start) / ticks[-1]
    return imu_log(t, raw[:, 0:3] * G0, np.radians(raw[:, 3:6]), str(path))


def _gpst_seconds(date: str, clock: str) -> float:
    dt = datetime.strptime(f"{date} {clock}", "%Y/%m/%d %H:%M:%S.%f")
    return calendar.timegm(dt.timetuple()) + dt.microsecond * 1e-6


def read_pos(path: str | Path) -> GnssLog:
    """Read an RTKLIB ``.pos`` solution in latitude/longitude/height format: 15 fields, or 21
    with velocities (north, east, up and their σ); a file of either kind, epochs of both kinds
    may mix."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read solution file ({exc.strerror})") from exc
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not an RTKLIB solution file (not UTF-8 text)") from None
    rows = []
    for lineno, line in enumerate(lines, 1):
        if not line.strip() or line.startswith("%"):
            continue
        tok = line.split()
        if len(tok) < 15:
            raise DatasetError(f"{path}:{lineno}: expected 15 fields (21 with velocities), got {len(tok)}")
        try:
            nums = [float(x) for x in tok[2:21]]
            rows.append([_gpst_seconds(tok[0], tok[1]), *nums, *[math.nan] * (19 - len(nums))])
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: {exc}") from exc
    if len(rows) < 2:
        raise DatasetError(f"{path}: no solution epochs")
    a = np.array(rows)
    v_ned = np.column_stack([a[:, 14], a[:, 15], -a[:, 16]])
    return gnss_log(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 6:9], v_ned, a[:, 17:20], a[:, 4], a[:, 5], str(path))


def load_drive(folder: str | Path) -> Recording:
    """Load a drive folder holding one ``imu_*.csv`` with its ``.tag`` and one ``*.pos`` (other
    ``imu_*.csv`` files, such as a converted copy without time tags, are not the raw log)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: not a directory")
    imus = [p for p in sorted(folder.glob("imu_*.csv")) if Path(f"{p}.tag").is_file()]
    poss = sorted(folder.glob("*.pos"))
    if len(imus) != 1 or len(poss) != 1:
        raise DatasetError(f"{folder}: expected exactly one imu_*.csv with its .tag and one *.pos, "
                           f"found {len(imus)} and {len(poss)}")
    return Recording(read_imu_csv(imus[0]), read_pos(poss[0]))
