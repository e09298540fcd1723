"""Vehicle profiles: one TOML file per vehicle type with its installation and sensor models.

A profile says what a vehicle *is*: how its IMU is mounted and how noisy it is, where its GNSS
antenna sits, what heights its receiver reports, how its IMU clock relates to GNSS time, and which
vehicle constraints hold. The agent (``[agent] profile``), the sensor driver and the replay
(``--vehicle``) and the emulator (a scenario vehicle's ``profile``) read the same file.

Units are the datasheet's at this edge (named in each field) and SI with radians inside: the
``*_si`` helpers convert. Example (``deploy/vehicles/`` holds complete ones)::

    [vehicle]
    name = "my car"

    [imu]
    rate_hz = 100
    mount_rpy_deg = [180.0, 0.0, 180.0]   # sensor-to-body rotation (roll, pitch, yaw)
    gyro_noise_dps_rthz = 0.0038          # datasheet rate noise density
    accel_noise_ug_rthz = 70

    [time]
    imu_offset_s = -0.125                 # prior of the IMU time offset, added to its stamps

    [gnss]
    lever_arm_m = [0.0, -0.05, 0.0]       # antenna from the IMU, body frame (forward, right, down)
    height = "msl"                        # the receiver reports mean-sea-level heights
    geoid_undulation_m = -16.8

Every field has a default: an empty profile is a generic consumer-grade MEMS IMU mounted with its
axes on the body's (forward, right, down), a GNSS antenna at the IMU, ellipsoidal heights and no
time offset. Unknown sections or fields and wrong types raise :class:`ProfileError` naming the
file and the field.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

G0 = 9.80665  #: standard gravity [m/s²], the "g" of accelerometer datasheets


class ProfileError(ValueError):
    """A vehicle profile is invalid; the message names the file and the field."""


def _check(cond: bool, name: str, reason: str) -> None:
    if not cond:
        raise ProfileError(f"{name}: {reason}")


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _numbers(obj: Any, *names: str, positive: bool = False) -> None:
    """Each field a finite number (>= 0, or > 0 with ``positive``), stored as a float."""
    for n in names:
        v = getattr(obj, n)
        _check(_finite(v), n, f"must be a finite number, got {v!r}")
        _check(v > 0 if positive else v >= 0, n, f"must be {'>' if positive else '>='} 0, got {v!r}")
        object.__setattr__(obj, n, float(v))


def _triple(obj: Any, name: str, positive: bool = False) -> None:
    v = getattr(obj, name)
    ok = isinstance(v, (list, tuple)) and len(v) == 3 and all(_finite(x) for x in v)
    _check(ok, name, f"must be three finite numbers, got {v!r}")
    if positive:
        _check(all(x > 0 for x in v), name, f"must be three numbers > 0, got {v!r}")
    object.__setattr__(obj, name, tuple(float(x) for x in v))


def _flags(obj: Any, *names: str) -> None:
    for n in names:
        v = getattr(obj, n)
        _check(isinstance(v, bool), n, f"must be true or false, got {v!r}")


@dataclass(frozen=True)
class ImuSpec:
    """``[imu]``: the IMU's mounting and stochastic model (datasheet units)."""

    #: nominal sample rate [Hz]
    rate_hz: float = 100.0
    #: sensor-to-body rotation as roll, pitch, yaw [deg] (Groves' Euler_to_CTM convention; the
    #: body frame is forward, right, down)
    mount_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: gyro rate noise density [deg/s/√Hz] (angle random walk)
    gyro_noise_dps_rthz: float = 0.007
    #: accelerometer noise density [µg/√Hz] (velocity random walk)
    accel_noise_ug_rthz: float = 60.0
    #: factor on both noise densities for vibration and unmodelled errors in the vehicle
    noise_inflation: float = 1.0
    #: in-run gyro bias σ (a Gauss-Markov process) [deg/h]
    gyro_bias_dph: float = 8.0
    #: in-run accelerometer bias σ [µg]
    accel_bias_ug: float = 15.0
    #: correlation time of the in-run biases [s]
    bias_correlation_s: float = 600.0
    #: turn-on gyro bias σ [deg/s]
    gyro_turn_on_dps: float = 0.05
    #: turn-on accelerometer bias σ [mg]
    accel_turn_on_mg: float = 2.0
    #: per-axis scale-factor error σ [ppm] (emulated; the filter does not estimate it)
    scale_factor_ppm: float = 1000.0

    def __post_init__(self) -> None:
        _triple(self, "mount_rpy_deg")
        _numbers(self, "rate_hz", "noise_inflation", "bias_correlation_s", positive=True)
        _numbers(self, "gyro_noise_dps_rthz", "accel_noise_ug_rthz", "gyro_bias_dph", "accel_bias_ug",
                 "gyro_turn_on_dps", "accel_turn_on_mg", "scale_factor_ppm")

    @property
    def mount_rpy(self) -> tuple[float, float, float]:
        """The mounting rotation [rad]."""
        r, p, y = (math.radians(x) for x in self.mount_rpy_deg)
        return (r, p, y)

    @property
    def arw(self) -> float:
        """Gyro white noise the filter assumes [rad/s/√Hz]."""
        return self.noise_inflation * math.radians(self.gyro_noise_dps_rthz)

    @property
    def vrw(self) -> float:
        """Accelerometer white noise the filter assumes [m/s²/√Hz]."""
        return self.noise_inflation * self.accel_noise_ug_rthz * 1e-6 * G0

    @property
    def gyro_bias(self) -> float:
        """In-run gyro bias σ [rad/s]."""
        return math.radians(self.gyro_bias_dph) / 3600.0

    @property
    def accel_bias(self) -> float:
        """In-run accelerometer bias σ [m/s²]."""
        return self.accel_bias_ug * 1e-6 * G0

    @property
    def gyro_turn_on(self) -> float:
        """Turn-on gyro bias σ [rad/s]."""
        return math.radians(self.gyro_turn_on_dps)

    @property
    def accel_turn_on(self) -> float:
        """Turn-on accelerometer bias σ [m/s²]."""
        return self.accel_turn_on_mg * 1e-3 * G0


@dataclass(frozen=True)
class TimeSpec:
    """``[time]``: the IMU's clock against GNSS time."""

    #: prior of the IMU time offset, added to the IMU's stamps by the sensor driver [s]
    imu_offset_s: float = 0.0
    #: estimate the remaining offset online (a filter state, while motion makes it observable)
    estimate: bool = True
    #: σ of the remaining offset around the prior [s]
    sigma_s: float = 0.05
    #: random walk of the offset [s/√s]
    random_walk: float = 1e-3
    #: the estimate stays within this distance of the prior [s]
    bound_s: float = 1.0

    def __post_init__(self) -> None:
        _flags(self, "estimate")
        _check(_finite(self.imu_offset_s), "imu_offset_s", f"must be a finite number, got {self.imu_offset_s!r}")
        object.__setattr__(self, "imu_offset_s", float(self.imu_offset_s))
        _numbers(self, "sigma_s", "random_walk", "bound_s", positive=True)


HEIGHTS = ("ellipsoidal", "msl")


@dataclass(frozen=True)
class GnssSpec:
    """``[gnss]``: the receiver and its antenna."""

    #: the antenna's position from the IMU in the body frame: forward, right, down [m]
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: the heights the receiver reports: ``ellipsoidal`` or ``msl`` (mean sea level)
    height: str = "ellipsoidal"
    #: geoid undulation added to mean-sea-level heights [m] (with ``height = "msl"``)
    geoid_undulation_m: float = 0.0
    #: nominal fix rate [Hz]
    rate_hz: float = 1.0
    #: factors on the receiver's reported σ for a fixed RTK, a float RTK and any other solution
    quality_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    #: floor of the reported position σ [m]
    min_sigma_m: float = 0.0
    #: floor of the reported velocity σ [m/s]
    min_sigma_mps: float = 0.0

    def __post_init__(self) -> None:
        _triple(self, "lever_arm_m")
        _triple(self, "quality_scale", positive=True)
        _check(self.height in HEIGHTS, "height", f"must be one of {', '.join(HEIGHTS)}, got {self.height!r}")
        _check(_finite(self.geoid_undulation_m) and abs(self.geoid_undulation_m) < 120.0, "geoid_undulation_m",
               f"must be a finite number of metres within ±120, got {self.geoid_undulation_m!r}")
        object.__setattr__(self, "geoid_undulation_m", float(self.geoid_undulation_m))
        _numbers(self, "rate_hz", positive=True)
        _numbers(self, "min_sigma_m", "min_sigma_mps")

    @property
    def height_to_ellipsoidal(self) -> float:
        """Added to the receiver's heights to make them ellipsoidal [m]."""
        return self.geoid_undulation_m if self.height == "msl" else 0.0


@dataclass(frozen=True)
class ConstraintSpec:
    """``[constraints]``: what the vehicle's motion allows (a road vehicle's by default)."""

    #: non-holonomic constraint: no sideways or vertical velocity while driving
    nhc: bool = True
    #: its lateral σ [m/s]
    nhc_sigma_mps: float = 0.1
    #: its vertical σ [m/s]
    nhc_vertical_sigma_mps: float = 0.1
    #: the unknown distance from the IMU to the rear axle (widens the lateral σ by the yaw rate and
    #: the vertical σ by the pitch rate) [m]
    nhc_lever_uncertainty_m: float = 1.0
    #: without a fix for this long, the constraint is applied on its own [s]
    nhc_coast_after_s: float = 1.0
    #: zero-velocity update at rest
    zupt: bool = True
    #: its σ [m/s]
    zupt_sigma_mps: float = 0.02
    #: zero angular rate at rest
    zaru: bool = True
    #: its σ on the mean rate of the last 10 samples [deg/s]; 0: twice the white noise of that mean
    zaru_sigma_dps: float = 0.0

    def __post_init__(self) -> None:
        _flags(self, "nhc", "zupt", "zaru")
        _numbers(self, "nhc_sigma_mps", "nhc_vertical_sigma_mps", "nhc_lever_uncertainty_m", "nhc_coast_after_s",
                 "zupt_sigma_mps", positive=True)
        _numbers(self, "zaru_sigma_dps")


@dataclass(frozen=True)
class InitialSpec:
    """``[initial]``: the filter's uncertainty at start (the heading comes from the GNSS course)."""

    #: attitude σ: roll, pitch, yaw [deg]
    att_sigma_deg: tuple[float, float, float] = (2.0, 2.0, 60.0)
    #: velocity σ [m/s]
    vel_sigma_mps: float = 0.1

    def __post_init__(self) -> None:
        _triple(self, "att_sigma_deg", positive=True)
        _numbers(self, "vel_sigma_mps", positive=True)


@dataclass(frozen=True)
class VehicleProfile:
    """A vehicle type's installation and sensor models (see the module doc)."""

    name: str = "generic"
    description: str = ""
    imu: ImuSpec = field(default_factory=ImuSpec)
    time: TimeSpec = field(default_factory=TimeSpec)
    gnss: GnssSpec = field(default_factory=GnssSpec)
    constraints: ConstraintSpec = field(default_factory=ConstraintSpec)
    initial: InitialSpec = field(default_factory=InitialSpec)
    #: the file it was read from ("" for one built in code)
    source: str = ""


#: profile sections -> their dataclasses
SECTIONS: dict[str, type] = {"imu": ImuSpec, "time": TimeSpec, "gnss": GnssSpec, "constraints": ConstraintSpec,
                             "initial": InitialSpec}


def parse_profile(data: dict[str, Any], source: str = "<profile>") -> VehicleProfile:
    """A profile from a parsed TOML document; :class:`ProfileError` names ``source`` and the field."""
    known = {"vehicle", *SECTIONS}
    for k in data:
        if k not in known:
            raise ProfileError(f"{source}: [{k}]: unknown section (known: {', '.join(sorted(known))})")
    head = _table(data, "vehicle", source)
    for k in head:
        if k not in ("name", "description"):
            raise ProfileError(f"{source}: vehicle.{k}: unknown field (known: description, name)")
        if not isinstance(head[k], str):
            raise ProfileError(f"{source}: vehicle.{k}: must be a string, got {head[k]!r}")
    parts = {name: _section(cls, _table(data, name, source), name, source) for name, cls in SECTIONS.items()}
    return VehicleProfile(name=head.get("name") or Path(source).stem, description=head.get("description", ""),
                          source=source, **parts)


def load_profile(path: str | Path) -> VehicleProfile:
    """The profile in TOML file ``path``."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as exc:
        raise ProfileError(f"{p}: cannot read the vehicle profile ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise ProfileError(f"{p}: not a vehicle profile (not UTF-8 text)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{p}: not valid TOML ({exc})") from None
    return parse_profile(data, str(p))


def _table(data: dict[str, Any], key: str, source: str) -> dict[str, Any]:
    v = data.get(key, {})
    if not isinstance(v, dict):
        raise ProfileError(f"{source}: [{key}]: must be a table")
    return v


def _section(cls: type, d: dict[str, Any], name: str, source: str) -> Any:
    fields = {f.name for f in dataclasses.fields(cls)}
    for k in d:
        if k not in fields:
            raise ProfileError(f"{source}: {name}.{k}: unknown field (known: {', '.join(sorted(fields))})")
    try:
        return cls(**d)
    except ProfileError as exc:
        raise ProfileError(f"{source}: {name}.{exc}") from None
