"""A run's recording as a ROS 2 bag in MCAP storage, with standard ROS 2 message types (written
and read with the rosbags package: no ROS install). Foxglove opens it; ``ros2 bag play`` plays it.

Topics, per vehicle ``V`` and method ``M`` (``-`` in a method's name becomes ``_``: ROS names
take letters, digits and ``_``):

=====================================  ====================================================
``/slcp/V/M/fix``                      ``sensor_msgs/msg/NavSatFix``: latitude and longitude
                                       [deg], height above the WGS-84 ellipsoid [m], position
                                       covariance in east, north, up [m²] (type KNOWN)
``/slcp/V/M/odom``                     ``nav_msgs/msg/Odometry`` in ``map``, the local ENU frame
                                       at the scenario's origin: position [m], attitude (body
                                       x forward, y left, z up), position covariance (ENU);
                                       velocity in the body frame, as ROS has it [m/s]
``/slcp/V/M/first_stopped``            ``std_msgs/msg/Bool``: the vehicle's first-stopped claim,
                                       written when it changes (and first)
``/slcp/diagnostics``                  ``diagnostic_msgs/msg/DiagnosticArray``: one status per
                                       message, its name the source, its values the counters,
                                       its message the status as JSON
``/slcp/map_origin``                   ``sensor_msgs/msg/NavSatFix``: the origin of ``map``, once
``/slcp/site``                         ``visualization_msgs/msg/MarkerArray``, once: the lanes'
                                       centre lines and the stop lines in ``map`` (Foxglove's
                                       3D panel draws them)
``/slcp/V/truth/{fix,odom,...}``       in emulated runs, the vehicle's true trajectory at 10 Hz
                                       (as an estimate's topics, with a zero covariance)
=====================================  ====================================================

Every message is stamped, in its header and its log time, with the sensor time of the run [s]
(an estimate's GNSS time). :func:`read_recording` gives the estimates and diagnostics back as the
JSON lines recording has them, so a run's report can be made from either.
"""

from __future__ import annotations

import functools
import json
import logging
import math
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from slcp.transport.messages import Diagnostics, Estimate, Message

from . import ros2_cdr
from .site_shapes import lane_shapes

log = logging.getLogger(__name__)

FIX, ODOM, BOOL, DIAG = ("sensor_msgs/msg/NavSatFix", "nav_msgs/msg/Odometry", "std_msgs/msg/Bool",
                         "diagnostic_msgs/msg/DiagnosticArray")
#: NED <-> ENU (its own inverse)
_P = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_SIGN = np.array([[1.0, 1.0, -1.0], [1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])
#: the Odometry covariances' constant parts: attitude and twist are not in the recording
_POSE_COV_REST = np.diag([0.0, 0.0, 0.0, 1e6, 1e6, 1e6]).ravel()[18:].tolist()  #: its last three rows
_TWIST_COV = (np.eye(6) * 1e6).ravel().tolist()


def ned_to_enu_cov(c: np.ndarray) -> np.ndarray:
    """P C Pᵀ for the NED <-> ENU permutation P (its own inverse)."""
    return np.asarray(c, float)[[1, 0, 2]][:, [1, 0, 2]] * _SIGN


def log_time_ns(t: float) -> int:
    """A sensor time [s] as a log time [ns]: whole nanoseconds, 0 for a time before 0 or not
    finite (the log times of MCAP and of Foxglove's protocol are unsigned)."""
    return max(0, int(round(t * 1e9))) if math.isfinite(t) else 0


def ros_name(name: str) -> str:
    """A vehicle's or method's name as a ROS topic part (letters, digits and ``_``)."""
    return name.replace("-", "_").replace(".", "_")


def topic_name(vehicle: str, method: str, what: str) -> str:
    return f"/slcp/{ros_name(vehicle)}/{ros_name(method)}/{what}"


@functools.lru_cache(maxsize=4096)
def _topics(vehicle: str, method: str) -> tuple[str, str, str]:
    """The fix, odometry and first-stopped topics of a vehicle's method."""
    return tuple(topic_name(vehicle, method, w) for w in ("fix", "odom", "first_stopped"))  # type: ignore[return-value]


def _quat_zyx(yaw: float, pitch: float, roll: float) -> tuple[float, float, float, float]:
    cy, sy, cp, sp = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)  # x, y, z, w


def _rot_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """The rotation (body -> frame) of ZYX Euler angles."""
    cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch), math.cos(roll),
                              math.sin(roll))
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def enu_attitude(rpy_ned: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of a body in x forward, y left, z up, in ENU, from the roll, pitch and
    yaw of the body in x forward, y right, z down, in NED [rad]."""
    r, p, y = (float(a) for a in rpy_ned)
    return r, -p, math.pi / 2 - y


class McapSink:
    """Writes estimates and diagnostics to a ROS 2 bag (MCAP storage) at ``path`` (a new
    directory). ``origin_llh`` [rad, rad, m] is the origin of the ``map`` frame (default: the
    first estimate's position). ``counts``: messages written per topic. With ``inputs`` it also
    records the vehicles' inputs (:mod:`deploy.mcap_inputs`), which a recorder gives it through
    :attr:`observe_keys` and :meth:`observe`."""

    def __init__(self, path: Path, origin_llh: tuple[float, float, float] | None = None,
                 inputs: bool = False) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        from .mcap_inputs import INPUT_KEYS, InputWriter, register_types

        self.path = Path(path)
        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T = self.ts.types
        self.observe_keys: tuple[str, ...] = ()
        self._inputs: InputWriter | None = None
        if inputs:
            register_types(self.ts)
            self.observe_keys, self._inputs = INPUT_KEYS, InputWriter(self)
        self._w = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._w.open()
        self._conns: dict[str, Any] = {}
        self._claim: dict[str, bool] = {}
        self.origin: tuple[float, float, float] | None = None
        self.counts: Counter[str] = Counter()
        if origin_llh is not None:
            self._set_origin(origin_llh, 0)

    def _conn(self, topic: str, msgtype: str):
        c = self._conns.get(topic)
        if c is None:
            c = self._conns[topic] = self._w.add_connection(topic, msgtype, typestore=self.ts)
        return c

    def _put(self, topic: str, msgtype: str, ns: int, msg) -> None:
        self._raw(topic, msgtype, ns, self.ts.serialize_cdr(msg, msgtype))

    def _raw(self, topic: str, msgtype: str, ns: int, data) -> None:
        self._w.write(self._conn(topic, msgtype), ns, data)
        self.counts[topic] += 1

    def _header(self, ns: int, frame: str):
        T = self.T
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame)

    def _fix(self, ns: int, frame: str, llh, cov_enu: np.ndarray, cov_type: int):
        T = self.T
        return T[FIX](header=self._header(ns, frame), status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                      latitude=math.degrees(float(llh[0])), longitude=math.degrees(float(llh[1])),
                      altitude=float(llh[2]), position_covariance=np.ascontiguousarray(cov_enu, float).ravel(),
                      position_covariance_type=cov_type)

    def _set_origin(self, llh, ns: int) -> None:
        self.origin = (float(llh[0]), float(llh[1]), float(llh[2]))
        self._enu = ros2_cdr.LocalEnu(self.origin)
        self._put("/slcp/map_origin", FIX, ns, self._fix(ns, "map", llh, np.zeros((3, 3)), 0))

    def write(self, m: Message) -> None:
        """Record one estimate or diagnostics message (others are ignored). A message stamped
        before sensor time 0 is stamped 0 in the log (MCAP's times are unsigned)."""
        if isinstance(m, Estimate):
            self._estimate(m)
        elif isinstance(m, Diagnostics):
            self._diagnostics(m)

    def _estimate(self, e: Estimate) -> None:
        T = self.T
        ns = log_time_ns(e.t)
        if self.origin is None:
            self._set_origin(e.llh, ns)
        fix_topic, odom_topic, claim_topic = _topics(e.vehicle, e.method)
        if self._claim.get(claim_topic) != bool(e.first_stopped):
            self._claim[claim_topic] = bool(e.first_stopped)
            self._put(claim_topic, BOOL, ns, T[BOOL](data=bool(e.first_stopped)))
        # the two messages of every estimate, laid out by hand (ros2_cdr): a fleet's recorder
        # writes thousands a second, and rosbags' generic serialiser costs several times more
        lat, lon, h = (float(x) for x in e.llh)
        c = e.cov_pos.tolist()
        cov = [c[1][1], c[1][0], -c[1][2], c[0][1], c[0][0], -c[0][2], -c[2][1], -c[2][0], c[2][2]]  # ENU
        self._raw(fix_topic, FIX, ns,
                  ros2_cdr.nav_sat_fix(ns, "map", math.degrees(lat), math.degrees(lon), h, cov, 3))
        roll, pitch, yaw = enu_attitude(e.rpy)
        vn, ve, vd = (float(x) for x in e.v_ned)
        v_body = _rot_zyx(yaw, pitch, roll).T @ np.array([ve, vn, -vd])
        pcov = [*cov[0:3], 0.0, 0.0, 0.0, *cov[3:6], 0.0, 0.0, 0.0, *cov[6:9], 0.0, 0.0, 0.0, *_POSE_COV_REST]
        self._raw(odom_topic, ODOM, ns, ros2_cdr.odometry(
            ns, "map", f"{e.vehicle}/{e.method}", self._enu(lat, lon, h), _quat_zyx(yaw, pitch, roll), pcov,
            (float(v_body[0]), float(v_body[1]), float(v_body[2])), (0.0, 0.0, 0.0), _TWIST_COV))

    def write_site(self, lanes) -> None:
        """The site's lanes (``centerline``: north, east [m] in ``map``; ``width`` [m];
        ``stop_line``: whether it ends at one) as markers, stamped 0."""
        T = self.T
        P3 = T["geometry_msgs/msg/Point"]
        markers = []
        for k, ln in enumerate(lane_shapes(lanes)):
            markers.append(self._marker(k, "lanes", 4, 0.15, (0.6, 0.6, 0.6),
                                        [P3(x=float(e), y=float(n), z=0.0) for n, e in ln.centre]))
            if ln.stop_line is not None:
                markers.append(self._marker(k, "stop_lines", 5, 0.4, (1.0, 1.0, 1.0),
                                            [P3(x=float(e), y=float(n), z=0.0) for n, e in ln.stop_line]))
        self._put("/slcp/site", "visualization_msgs/msg/MarkerArray", 0,
                  T["visualization_msgs/msg/MarkerArray"](markers=markers))

    def _marker(self, k: int, ns: str, kind: int, width: float, rgb, points):
        T = self.T
        V3 = T["geometry_msgs/msg/Vector3"]
        return T["visualization_msgs/msg/Marker"](
            header=self._header(0, "map"), ns=ns, id=k, type=kind, action=0,
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                             orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
            scale=V3(x=width, y=0.0, z=0.0), color=T["std_msgs/msg/ColorRGBA"](r=rgb[0], g=rgb[1], b=rgb[2], a=1.0),
            lifetime=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0), frame_locked=False, points=points,
            colors=[], texture_resource="", texture=T["sensor_msgs/msg/CompressedImage"](
                header=self._header(0, ""), format="", data=np.zeros(0, np.uint8)),
            uv_coordinates=[], text="", mesh_resource="",
            mesh_file=T["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
            mesh_use_embedded_materials=False)

    def write_truth(self, vehicle: str, t: np.ndarray, llh: np.ndarray, v_ned: np.ndarray, rpy: np.ndarray,
                    first_stopped: np.ndarray, rate: float = 10.0) -> None:
        """A vehicle's true trajectory (arrays over ``t`` [s]), ``rate`` samples a second."""
        step = max(1, int(round(1.0 / (rate * float(np.median(np.diff(t)))))))
        zero = np.zeros((3, 3))
        for k in range(0, len(t), step):
            self._estimate(Estimate(vehicle, "truth", float(t[k]), llh[k], v_ned[k], rpy[k], zero,
                                    bool(first_stopped[k])))

    def _diagnostics(self, d: Diagnostics) -> None:
        T = self.T
        ns = log_time_ns(d.t)
        kv = T["diagnostic_msgs/msg/KeyValue"]
        status = T["diagnostic_msgs/msg/DiagnosticStatus"](
            level=0, name=d.source, message=json.dumps(d.status, default=str), hardware_id=d.source,
            values=[kv(key=k, value=str(v)) for k, v in d.counters.items()])
        self._put("/slcp/diagnostics", DIAG, ns, T[DIAG](header=self._header(ns, ""), status=[status]))

    def observe(self, m: Message) -> None:
        """Record one of the vehicles' inputs (with ``inputs``; others are ignored)."""
        if self._inputs is not None:
            self._inputs.write(m)

    def close(self) -> None:
        self._w.close()


def read_recording(path: Path) -> tuple[dict[tuple[str, str], list[dict]], dict[str, dict], Counter[str]]:
    """The estimates per (vehicle, method) and the last diagnostics counters per source of a bag
    written by :class:`McapSink`, as the JSON lines recording has them, and the messages per topic."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    est: dict[tuple[str, str], list[dict]] = {}
    diags: dict[str, dict] = {}
    counts: Counter[str] = Counter()
    claims: dict[str, bool] = {}
    fixes: dict[tuple[str, int], Any] = {}
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for conn in reader.connections:
            counts[conn.topic] += conn.msgcount
        # the estimates, claims and diagnostics: not the inputs, the site, the origin or the truth
        wanted = [c for c in reader.connections if c.msgtype == DIAG or (
            c.topic.count("/") == 4 and c.topic.rsplit("/", 1)[1] in ("fix", "odom", "first_stopped")
            and "/truth/" not in c.topic)]
        for conn, _, raw in reader.messages(connections=wanted) if wanted else ():  # none: rosbags reads all
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == DIAG:
                for s in msg.status:
                    diags[s.name] = {kv.key: int(kv.value) for kv in s.values}
                continue
            stem, what = conn.topic.rsplit("/", 1)
            ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec if what != "first_stopped" else 0
            if what == "first_stopped":
                claims[stem] = bool(msg.data)
            elif what == "fix":
                fixes[(stem, ns)] = (msg, claims.get(stem, False))
            elif what == "odom":
                fix, claim = fixes.pop((stem, ns))
                vehicle, method = msg.child_frame_id.rsplit("/", 1)
                est.setdefault((vehicle, method), []).append(_estimate_record(vehicle, method, ns, fix, msg, claim))
    return est, diags, counts


def _estimate_record(vehicle: str, method: str, ns: int, fix, odom, claim: bool) -> dict:
    q = odom.pose.pose.orientation
    roll = math.atan2(2 * (q.w * q.x + q.y * q.z), 1 - 2 * (q.x * q.x + q.y * q.y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (q.w * q.y - q.z * q.x))))
    yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    v = odom.twist.twist.linear
    v_ned = _P @ (_rot_zyx(yaw, pitch, roll) @ np.array([v.x, v.y, v.z]))
    cov = ned_to_enu_cov(np.asarray(fix.position_covariance, float).reshape(3, 3))
    return {"type": "Estimate", "vehicle": vehicle, "method": method, "t": ns / 1e9,
            "llh": [math.radians(fix.latitude), math.radians(fix.longitude), fix.altitude],
            "v_ned": v_ned.tolist(), "rpy": [roll, -pitch, math.remainder(math.pi / 2 - yaw, 2 * math.pi)],
            "cov_pos": cov.tolist(),
            "first_stopped": claim}
