"""The recording formats ``slcp replay FORMAT PATH`` reads."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from .recording import Recording


def _rtklib(path: Path) -> Recording:
    from .rtklib import load_drive

    return load_drive(path)


def _kf_gins(path: Path) -> Recording:
    from .kfgins import load

    return load(path)


def _csv(path: Path) -> Recording:
    from .csv_columns import load

    return load(path)


def _ros2(path: Path) -> Recording:
    from .ros2_bag import load

    return load(path)


#: format name -> (reader, what PATH is)
FORMATS: dict[str, tuple[Callable[[Path], Recording], str]] = {
    "rtklib": (_rtklib, "a folder with imu_*.csv, its .tag and a *.pos (rtklibexplorer's logs)"),
    "kf-gins": (_kf_gins, "a folder with *imu*.txt (increments) and *gnss*.txt (KF-GINS text)"),
    "csv": (_csv, "a folder with imu.csv and gnss.csv, columns named with their units"),
    "ros2": (_ros2, "a ROS 2 bag folder (sqlite3 or MCAP): sensor_msgs/Imu and NavSatFix"),
}


def load_recording(fmt: str, path: str | Path) -> Recording:
    """The recording at ``path`` in format ``fmt`` (:data:`FORMATS`)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown recording format {fmt!r} (known: {', '.join(FORMATS)})")
    return FORMATS[fmt][0](Path(path))
