"""ROS 2 bags (sqlite3 or MCAP storage, read with the rosbags package, no ROS needed).

Topics are found by message type (one topic of each; give ``imu_topic``/``fix_topic`` when a
bag has several):

* ``sensor_msgs/msg/Imu``: ``angular_velocity`` [rad/s] and ``linear_acceleration`` [m/s²] in
  the message's frame (the profile's mount turns it into the body frame);
* ``sensor_msgs/msg/NavSatFix``: latitude, longitude [deg], altitude [m above the WGS 84
  ellipsoid, as the message defines it], the σ from the diagonal of ``position_covariance``
  (east, north, up); ``status.status`` 2 (GBAS, as RTK receivers' drivers report a fixed
  solution) maps to quality 1, anything else to a code solution; fixes with status −1 (no fix)
  are left out;
* optionally ``geometry_msgs/msg/TwistWithCovarianceStamped``: the GNSS velocity in east,
  north, up (REP 103), matched to the fix of the same stamp; without it the fixes are
  position-only.

Times are the messages' header stamps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import DatasetError
from .recording import Recording, gnss_log, imu_log

IMU = "sensor_msgs/msg/Imu"
FIX = "sensor_msgs/msg/NavSatFix"
TWIST = "geometry_msgs/msg/TwistWithCovarianceStamped"


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _topic(conns, msgtype: str, wanted: str | None, path: Path, required: bool = True):
    found = [c for c in conns if c.msgtype == msgtype and (wanted is None or c.topic == wanted)]
    if len(found) == 1:
        return found[0]
    if not found and not required:
        return None
    names = sorted({c.topic for c in conns if c.msgtype == msgtype})
    raise DatasetError(f"{path}: expected one {msgtype} topic{f' named {wanted}' if wanted else ''}, "
                       f"found {len(found)} ({', '.join(names) or 'none'})")


def load(path: str | Path, imu_topic: str | None = None, fix_topic: str | None = None) -> Recording:
    """The recording in the ROS 2 bag at ``path`` (its folder)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such bag")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        raise DatasetError(f"{path}: not a ROS 2 bag folder (no metadata.yaml in it)")
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            conns = reader.connections
            ci = _topic(conns, IMU, imu_topic, path)
            cf = _topic(conns, FIX, fix_topic, path)
            ct = _topic(conns, TWIST, None, path, required=False)
            imu, fix, twist = [], [], {}
            for conn, _t, raw in reader.messages(connections=[c for c in (ci, cf, ct) if c is not None]):
                m = reader.deserialize(raw, conn.msgtype)
                if conn is ci:
                    a, w = m.linear_acceleration, m.angular_velocity
                    imu.append((_stamp(m), a.x, a.y, a.z, w.x, w.y, w.z))
                elif conn is cf:
                    if m.status.status >= 0:
                        c = m.position_covariance
                        fix.append((_stamp(m), m.latitude, m.longitude, m.altitude, c[4], c[0], c[8],
                                    1 if m.status.status == 2 else 5))
                else:
                    v, c = m.twist.twist.linear, m.twist.covariance
                    twist[round(_stamp(m), 6)] = (v.y, v.x, -v.z, c[7], c[0], c[14])
    except DatasetError:
        raise
    except Exception as exc:  # rosbags raises its own errors for damaged bags
        raise DatasetError(f"{path}: not a readable ROS 2 bag ({type(exc).__name__}: {exc})") from None
    if not fix:
        raise DatasetError(f"{path}: no NavSatFix with a fix")
    a = np.array(sorted(imu))
    f = np.array(sorted(fix))
    var = f[:, 4:7]
    if np.any(var < 0) or not np.all(np.isfinite(var)):
        raise DatasetError(f"{path}: a NavSatFix covariance has a negative or non-finite diagonal")
    tw = np.array([twist.get(round(t, 6), (np.nan,) * 6) for t in f[:, 0]])
    return Recording(imu_log(a[:, 0], a[:, 1:4], a[:, 4:7], str(path)),
                     gnss_log(f[:, 0], f[:, 1], f[:, 2], f[:, 3], np.sqrt(var), tw[:, :3], np.sqrt(tw[:, 3:]),
                              f[:, 7], source=str(path)))


def write(rec: Recording, path: str | Path, velocity: bool = True, mcap: bool = False) -> None:
    """``rec`` as a ROS 2 bag at ``path`` (topics ``/imu``, ``/fix`` and, with velocities,
    ``/fix_velocity``; sqlite3 storage, or MCAP)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    V3 = T["geometry_msgs/msg/Vector3"]

    def header(t: float, frame: str):
        ns = int(round(t * 1e9))
        return Header(stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame), ns

    plugin = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
    with Writer(Path(path), version=9, storage_plugin=plugin) as w:
        ci = w.add_connection("/imu", IMU, typestore=ts)
        cf = w.add_connection("/fix", FIX, typestore=ts)
        g = rec.gnss
        has_v = g.has_velocity & velocity
        ct = w.add_connection("/fix_velocity", TWIST, typestore=ts) if has_v.any() else None
        zero9 = np.zeros(9)
        q = T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
        events = [(float(t), 0, i) for i, t in enumerate(rec.imu.t)] + [(float(t), 1, i) for i, t in enumerate(g.t)]
        for t, kind, i in sorted(events):
            if kind == 0:
                h, ns = header(t, "imu")
                a, r = rec.imu.accel[i], rec.imu.gyro[i]
                msg = T[IMU](header=h, orientation=q, orientation_covariance=np.r_[-1.0, np.zeros(8)],
                             angular_velocity=V3(x=r[0], y=r[1], z=r[2]), angular_velocity_covariance=zero9,
                             linear_acceleration=V3(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=zero9)
                w.write(ci, ns, ts.serialize_cdr(msg, IMU))
                continue
            h, ns = header(t, "gnss")
            sd = g.sd_neu[i]
            status = T["sensor_msgs/msg/NavSatStatus"](status=2 if g.quality[i] == 1 else 0, service=1)
            cov = np.diag([sd[1] ** 2, sd[0] ** 2, sd[2] ** 2]).ravel()
            msg = T[FIX](header=h, status=status, latitude=float(np.degrees(g.llh[i, 0])),
                         longitude=float(np.degrees(g.llh[i, 1])), altitude=float(g.llh[i, 2]),
                         position_covariance=cov, position_covariance_type=2)
            w.write(cf, ns, ts.serialize_cdr(msg, FIX))
            if ct is not None and has_v[i]:
                v, sv = g.v_ned[i], g.sd_v[i]
                tcov = np.zeros(36)
                tcov[[0, 7, 14]] = [sv[1] ** 2, sv[0] ** 2, sv[2] ** 2]
                tcov[[21, 28, 35]] = 1e6  # no angular velocity
                lin, ang = V3(x=v[1], y=v[0], z=-v[2]), V3(x=0.0, y=0.0, z=0.0)
                tw = T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=lin, angular=ang), covariance=tcov)
                w.write(ct, ns, ts.serialize_cdr(T[TWIST](header=h, twist=tw), TWIST))
