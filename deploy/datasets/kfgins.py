"""The i2Nav KF-GINS text formats: one IMU file and one GNSS file in a folder.

* IMU (``*imu*.txt``): one sample a line, ``t dθx dθy dθz dvx dvy dvz``: the time [s] at the
  end of the sample's interval, the angle increments [rad] and velocity increments [m/s] over
  it, in the IMU's frame; any rate. The first line only starts the first interval.
* GNSS (``*gnss*.txt``): ``t lat lon h σn σe σd`` (degrees, metres; the height is ellipsoidal
  in KF-GINS, the profile says otherwise), optionally followed by ``vn ve vd σvn σve σvd``
  [m/s]: a line of 7 values has no velocity, one of 13 has.

Fields are separated by spaces, tabs or commas; lines starting with ``#`` or ``%`` are comments.
Times are on one scale for both files (KF-GINS uses GPS seconds of the week). Example::

    # imu.txt
    357000.005  1.2e-05 -3.1e-06  2.0e-05  0.0012 -0.0004 -0.0980
    # gnss.txt
    357000.000  30.4446124 114.4718243  22.103  0.005 0.005 0.008
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import DatasetError
from .recording import GnssLog, ImuLog, Recording, gnss_log, rates_from_increments


def _table(path: Path, widths: tuple[int, ...]) -> np.ndarray:
    rows = []
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a KF-GINS text file (not UTF-8 text)") from None
    width = None
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s or s[0] in "#%":
            continue
        tok = s.replace(",", " ").split()
        if len(tok) not in widths:
            raise DatasetError(f"{path}:{lineno}: expected {' or '.join(map(str, widths))} values, got {len(tok)}")
        if width is not None and len(tok) != width:
            raise DatasetError(f"{path}:{lineno}: {len(tok)} values where earlier lines have {width}")
        width = len(tok)
        try:
            rows.append([float(x) for x in tok])
        except ValueError as exc:
            raise DatasetError(f"{path}:{lineno}: {exc}") from None
    if not rows:
        raise DatasetError(f"{path}: no data lines")
    return np.array(rows)


def read_imu(path: str | Path) -> ImuLog:
    """A KF-GINS IMU file (increments) as rates."""
    a = _table(Path(path), (7,))
    return rates_from_increments(a[:, 0], a[:, 1:4], a[:, 4:7], str(path))


def read_gnss(path: str | Path) -> GnssLog:
    """A KF-GINS GNSS file, with or without velocities."""
    a = _table(Path(path), (7, 13))
    v = (a[:, 7:10], a[:, 10:13]) if a.shape[1] == 13 else (None, None)
    sd_neu = np.column_stack([a[:, 4], a[:, 5], a[:, 6]])  # σ down is σ up
    return gnss_log(a[:, 0], a[:, 1], a[:, 2], a[:, 3], sd_neu, *v, source=str(path))


def _one(folder: Path, word: str) -> Path:
    found = [p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() == ".txt"
             and word in p.name.lower()]
    if len(found) != 1:
        raise DatasetError(f"{folder}: expected exactly one *{word}*.txt, found {len(found)}")
    return found[0]


def load(folder: str | Path) -> Recording:
    """The recording in a folder of one ``*imu*.txt`` and one ``*gnss*.txt``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: not a directory")
    return Recording(read_imu(_one(folder, "imu")), read_gnss(_one(folder, "gnss")))


def write(rec: Recording, folder: str | Path, velocity: bool = True) -> None:
    """``rec`` as KF-GINS text files ``imu.txt`` and ``gnss.txt`` in ``folder`` (the first IMU
    line starts the first interval with zero increments); ``velocity`` False leaves the GNSS
    velocities out, as do epochs without one."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    imu = rec.imu
    dt = np.diff(imu.t, prepend=imu.t[0])
    inc = np.column_stack([imu.t, imu.gyro * dt[:, None], imu.accel * dt[:, None]])
    np.savetxt(folder / "imu.txt", inc, fmt=["%.6f"] + ["%.12e"] * 6)
    g = rec.gnss
    cols = [g.t, np.degrees(g.llh[:, 0]), np.degrees(g.llh[:, 1]), g.llh[:, 2], g.sd_neu]
    fmt = ["%.6f", "%.10f", "%.10f", "%.4f", "%.4f", "%.4f", "%.4f"]
    if velocity and np.all(g.has_velocity):
        cols += [g.v_ned, g.sd_v]
        fmt += ["%.4f"] * 6
    np.savetxt(folder / "gnss.txt", np.column_stack(cols), fmt=fmt)
