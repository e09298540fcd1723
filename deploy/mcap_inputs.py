"""A run's inputs in its ROS 2 bag (``slcp run --bag-inputs``, ``slcp record --bag-inputs``):
what the vehicles' sensors measured and what they broadcast, beside their estimates.

=====================================  ====================================================
``/slcp/V/imu``                        ``sensor_msgs/msg/Imu`` per IMU sample, in ``V/imu``
                                       (x forward, y left, z up, as ROS has a body): angular
                                       rate [rad/s] and specific force [m/s²] (the sample's
                                       increments over its interval); no orientation
``/slcp/V/gnss``                       ``sensor_msgs/msg/NavSatFix``: the receiver's fix with its
                                       reported σ (east, north, up; type DIAGONAL_KNOWN)
``/slcp/V/gnss_velocity``              ``geometry_msgs/msg/TwistWithCovarianceStamped`` in ``map``
                                       (east, north, up) [m/s], when the receiver gives one
``/slcp/V/uwb``                        ``slcp_msgs/msg/UwbRound``: the ranges [m] of one round
``/slcp/V/beacon``                     ``slcp_msgs/msg/Beacon``: what the vehicle broadcast
=====================================  ====================================================

The two ``slcp_msgs`` types travel in the bag with their definitions (:data:`CUSTOM_TYPES`), as
MCAP keeps every schema, so Foxglove and the MCAP readers decode them without slcp.
"""

from __future__ import annotations

import math

from slcp.transport import keys
from slcp.transport.messages import Beacon, GnssFix, ImuBatch, Message, UwbRound

from . import ros2_cdr
from .mcap_recording import log_time_ns, ros_name

IMU, FIX, TWIST = "sensor_msgs/msg/Imu", "sensor_msgs/msg/NavSatFix", "geometry_msgs/msg/TwistWithCovarianceStamped"
UWB_ROUND, BEACON = "slcp_msgs/msg/UwbRound", "slcp_msgs/msg/Beacon"
CUSTOM_TYPES = {
    UWB_ROUND: "std_msgs/Header header\nstring vehicle\nuint32 seq\nstring[] peers\nfloat64[] ranges\n",
    BEACON: ("std_msgs/Header header\nstring vehicle\nuint32 seq\nstring method\nfloat64 latitude\n"
             "float64 longitude\nfloat64 altitude\nfloat64[3] velocity_ned\nfloat64[9] position_covariance_ned\n"
             "bool first_stopped\nbool signed\n"),
}
#: the bus keys of the inputs
INPUT_KEYS = (keys.ROOT + "/sensor/*/imu", keys.ROOT + "/sensor/*/gnss", keys.ROOT + "/uwb/*",
              keys.ROOT + "/radio/tx/*")
#: the last part of an input's topic
INPUT_TOPICS = frozenset({"imu", "gnss", "gnss_velocity", "uwb", "beacon"})


def register_types(ts) -> None:
    """Add the ``slcp_msgs`` types to a rosbags typestore."""
    from rosbags.typesys import get_types_from_msg

    for name, text in CUSTOM_TYPES.items():
        ts.register(get_types_from_msg(text, name))


def _topic(vehicle: str, what: str) -> str:
    return f"/slcp/{ros_name(vehicle)}/{what}"


class InputWriter:
    """Writes the inputs through a :class:`deploy.mcap_recording.McapSink` (its ``_raw``,
    ``_put``, typestore ``T`` and ``_header``)."""

    def __init__(self, sink) -> None:
        self.sink = sink

    def write(self, m: Message) -> None:
        if isinstance(m, ImuBatch):
            self._imu(m)
        elif isinstance(m, GnssFix):
            self._gnss(m)
        elif isinstance(m, UwbRound):
            self._uwb(m)
        elif isinstance(m, Beacon):
            self._beacon(m)

    def _imu(self, m: ImuBatch) -> None:
        topic, frame = _topic(m.vehicle, "imu"), f"{m.vehicle}/imu"
        for t, dt, th, dv in zip(m.t.tolist(), m.dt.tolist(), m.dtheta.tolist(), m.dvel.tolist()):
            if not dt > 0:
                continue
            ns = log_time_ns(t)
            # body FRD -> ROS's x forward, y left, z up
            self.sink._raw(topic, IMU, ns, ros2_cdr.imu(ns, frame, (th[0] / dt, -th[1] / dt, -th[2] / dt),
                                                        (dv[0] / dt, -dv[1] / dt, -dv[2] / dt)))

    def _gnss(self, m: GnssFix) -> None:
        ns = log_time_ns(m.t)
        sn, se, sd = (float(x) for x in m.sigma_ned)
        lat, lon, h = (float(x) for x in m.llh)
        self.sink._raw(_topic(m.vehicle, "gnss"), FIX, ns, ros2_cdr.nav_sat_fix(
            ns, f"{m.vehicle}/gnss", math.degrees(lat), math.degrees(lon), h,
            [se * se, 0.0, 0.0, 0.0, sn * sn, 0.0, 0.0, 0.0, sd * sd], 2, status=0 if m.quality > 0 else -1))
        if m.sigma_v > 0:
            s = self.sink
            T = s.T
            vn, ve, vd = (float(x) for x in m.v_ned)
            var = float(m.sigma_v) ** 2
            cov = [0.0] * 36
            for i in range(3):
                cov[7 * i] = var
            V3 = T["geometry_msgs/msg/Vector3"]
            s._put(_topic(m.vehicle, "gnss_velocity"), TWIST, ns, T[TWIST](
                header=s._header(ns, "map"), twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=V3(x=ve, y=vn, z=-vd), angular=V3(x=0.0, y=0.0, z=0.0)),
                    covariance=_array(cov))))

    def _uwb(self, m: UwbRound) -> None:
        s = self.sink
        ns = log_time_ns(m.t)
        s._put(_topic(m.vehicle, "uwb"), UWB_ROUND, ns, s.T[UWB_ROUND](
            header=s._header(ns, f"{m.vehicle}/uwb"), vehicle=m.vehicle, seq=int(m.seq) & 0xFFFFFFFF,
            peers=list(m.peers), ranges=_array(m.ranges)))

    def _beacon(self, b: Beacon) -> None:
        s = self.sink
        ns = log_time_ns(b.t)
        s._put(_topic(b.vehicle, "beacon"), BEACON, ns, s.T[BEACON](
            header=s._header(ns, "map"), vehicle=b.vehicle, seq=int(b.seq) & 0xFFFFFFFF, method=b.method,
            latitude=math.degrees(float(b.llh[0])), longitude=math.degrees(float(b.llh[1])), altitude=float(b.llh[2]),
            velocity_ned=_array(b.v_ned), position_covariance_ned=_array(b.cov_pos),
            first_stopped=bool(b.first_stopped), signed=bool(b.auth)))


def _array(x):
    import numpy as np

    return np.ascontiguousarray(x, dtype=np.float64).ravel()
