"""A run's recording as a ROS 2 bag in MCAP storage (#44): the estimates and diagnostics round
trip exactly through the standard message types, and the bag reads with the MCAP reference
reader as well as with rosbags."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.deploy.mcap_recording import McapSink, enu_attitude, read_recording, topic_name
from slcp.transport.messages import Diagnostics, Estimate


def _estimates(rng, n: int = 30) -> list[Estimate]:
    out = []
    for k in range(n):
        a = rng.normal(size=(3, 3))
        out.append(Estimate("V0", "SL-CP" if k % 2 else "SP", 0.1 * k,
                            np.array([0.6973 + 1e-6 * k, 2.0302 - 2e-6 * k, 51.0 + 0.01 * k]), rng.normal(size=3),
                            np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-math.pi, math.pi)]),
                            a @ a.T + np.eye(3) * 0.01, first_stopped=k > 14))
    return out


def test_estimates_and_diagnostics_round_trip_through_the_bag(tmp_path) -> None:
    rng = np.random.default_rng(4)
    sent = _estimates(rng)
    sink = McapSink(tmp_path / "bag", (0.6973, 2.0302, 50.0))
    for e in sent:
        sink.write(e)
    sink.write(Diagnostics("V0", 2.0, {"beacons_rx": 7, "codec_errors": 0}, {"t": 2.0, "lost": {}}))
    sink.close()
    est, diags, counts = read_recording(tmp_path / "bag")
    assert diags == {"V0": {"beacons_rx": 7, "codec_errors": 0}}
    assert counts[topic_name("V0", "SL-CP", "fix")] == counts[topic_name("V0", "SL-CP", "odom")] == 15
    assert counts[topic_name("V0", "SL-CP", "first_stopped")] == 2  # written when it changes
    got = est[("V0", "SL-CP")] + est[("V0", "SP")]
    by_t = {round(r["t"], 6): r for r in got}
    for e in sent:
        r = by_t[round(e.t, 6)]
        assert r["method"] == e.method and r["first_stopped"] == e.first_stopped
        np.testing.assert_allclose(r["llh"], e.llh, rtol=0, atol=1e-13)
        np.testing.assert_allclose(r["cov_pos"], e.cov_pos, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(r["v_ned"], e.v_ned, rtol=0, atol=1e-12)
        np.testing.assert_allclose(r["rpy"], e.rpy, rtol=0, atol=1e-9)


def test_the_bag_reads_with_the_mcap_reference_reader_in_ros_conventions(tmp_path) -> None:
    """The MCAP library's own reader and ROS 2 decoder see the same topics and counts; a fix is
    in degrees with an ENU covariance, and the odometry's position is east, north, up of the
    map origin."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    origin = (0.6973, 2.0302, 50.0)
    e = Estimate("V2", "CP", 1.5, np.array([origin[0] + 1e-5, origin[1] - 2e-5, 53.0]), np.array([1.0, 2.0, -0.5]),
                 np.array([0.0, 0.0, math.radians(30.0)]), np.diag([4.0, 1.0, 9.0]))
    sink = McapSink(tmp_path / "bag", origin)
    sink.write(e)
    sink.close()
    _, _, counts = read_recording(tmp_path / "bag")
    seen: dict[str, int] = {}
    msgs = {}
    with open(next((tmp_path / "bag").glob("*.mcap")), "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, _, decoded in reader.iter_decoded_messages():
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            msgs[channel.topic] = (schema.name, decoded)
    assert seen == dict(counts)
    name, fix = msgs[topic_name("V2", "CP", "fix")]
    assert name == "sensor_msgs/msg/NavSatFix" and fix.latitude == pytest.approx(math.degrees(e.llh[0]), abs=1e-12)
    assert list(fix.position_covariance) == pytest.approx([1.0, 0, 0, 0, 4.0, 0, 0, 0, 9.0])  # east, north, up
    name, odom = msgs[topic_name("V2", "CP", "odom")]
    assert name == "nav_msgs/msg/Odometry" and odom.header.frame_id == "map"
    north, east = 1e-5 * 6_378_137 * (1 - 0.0066943800) / (1 - 0.0066943800 * math.sin(origin[0]) ** 2) ** 1.5, \
        -2e-5 * 6_378_137 * math.cos(origin[0]) / math.sqrt(1 - 0.0066943800 * math.sin(origin[0]) ** 2)
    p = odom.pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx((east, north, 3.0), abs=0.05)
    # heading 30° east of north is 60° north of east; the body's forward speed is along it
    q = odom.pose.pose.orientation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(math.radians(60.0), abs=1e-9)
    speed_fwd = math.cos(math.radians(30)) * 1.0 + math.sin(math.radians(30)) * 2.0
    assert odom.twist.twist.linear.x == pytest.approx(speed_fwd, abs=1e-12)
    assert odom.twist.twist.linear.z == pytest.approx(0.5, abs=1e-12)  # up, the body's z


def test_attitude_in_ros_conventions_in_closed_form() -> None:
    assert enu_attitude(np.array([0.1, 0.2, 0.0])) == pytest.approx((0.1, -0.2, math.pi / 2))
    assert enu_attitude(np.array([0.0, 0.0, math.pi / 2]))[2] == pytest.approx(0.0)


def test_a_failing_bag_never_stops_the_json_lines(tmp_path) -> None:
    from slcp.deploy.recorder import Recorder
    from slcp.transport import keys
    from slcp.transport.codec import encode

    class Broken:
        def write(self, m) -> None:
            raise OSError("disk full")

        def close(self) -> None:
            raise OSError("disk full")

    rec = Recorder(tmp_path / "r.jsonl", sinks=[Broken()])
    e = _estimates(np.random.default_rng(0), 3)
    rec.write([(keys.estimate(x.vehicle, x.method), encode(x)) for x in e])
    rec.close()
    assert rec.recorded == 3 and rec.sink_errors == 4
    assert len((tmp_path / "r.jsonl").read_text().splitlines()) == 3


def test_slcp_record_refuses_a_bag_directory_that_exists(tmp_path, capsys) -> None:
    from slcp.deploy.cli import main

    (tmp_path / "bag").mkdir()
    assert main(["record", "--out", str(tmp_path / "r.jsonl"), "--bag", str(tmp_path / "bag")]) == 2
    assert "exists" in capsys.readouterr().err


def test_the_site_and_the_truth_go_into_the_bag_and_not_among_the_estimates(tmp_path) -> None:
    """The lanes and stop lines as markers in the map frame (east, north), and a vehicle's true
    trajectory at 10 Hz on topics of its own, which the recording's estimates leave out."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from slcp.hw_emulation.scenario import load_scenario

    scn = load_scenario("paper-1")
    sink = McapSink(tmp_path / "bag", scn.origin_llh)
    lanes = list(scn.lanes.values())
    sink.write_site(lanes)
    t = np.arange(0.0, 2.0, 0.01)
    llh = np.tile(np.array(scn.origin_llh), (len(t), 1))
    sink.write_truth("V0", t, llh, np.zeros((len(t), 3)), np.zeros((len(t), 3)), t > 1.0)
    sink.close()
    est, _, counts = read_recording(tmp_path / "bag")
    assert est == {} and counts["/slcp/V0/truth/fix"] == 20 and counts["/slcp/V0/truth/first_stopped"] == 2
    with AnyReader([tmp_path / "bag"], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        (conn,) = [c for c in reader.connections if c.topic == "/slcp/site"]
        (_, _, raw), = list(reader.messages(connections=[conn]))
        markers = reader.deserialize(raw, conn.msgtype).markers
    strips = [m for m in markers if m.ns == "lanes"]
    stops = [m for m in markers if m.ns == "stop_lines"]
    assert len(strips) == len(lanes) and len(stops) == sum(1 for ln in lanes if ln.stop_line) > 0
    first = strips[0]
    assert first.header.frame_id == "map" and first.type == 4
    c = np.asarray(lanes[0].centerline)
    np.testing.assert_allclose([(p.x, p.y) for p in first.points], c[:, ::-1])  # east, north


@pytest.mark.parametrize("frame, child", [("map", "V1/SL-CP"), ("", "x"), ("odom_frame", "vehicle-007/SL-SP")])
def test_the_hand_laid_messages_are_rosbags_bytes(frame, child) -> None:
    """ros2_cdr lays out NavSatFix and Odometry as rosbags' serialiser does, byte for byte, for
    frame names of every length modulo 4 (the CDR padding moves with them)."""
    from rosbags.typesys import Stores, get_typestore

    from slcp.deploy import ros2_cdr

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rng = np.random.default_rng(len(frame) + 7 * len(child))
    for ns in (0, 1_234_567_890_123, 49_999_999_999):
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=frame)
        cov9, cov36, tw36 = rng.normal(size=9), rng.normal(size=36), rng.normal(size=36)
        lat, lon, alt = rng.uniform(-90, 90), rng.uniform(-180, 180), rng.normal(0, 100)
        fix = T["sensor_msgs/msg/NavSatFix"](header=header, status=T["sensor_msgs/msg/NavSatStatus"](
            status=0, service=1), latitude=lat, longitude=lon, altitude=alt, position_covariance=cov9,
            position_covariance_type=3)
        assert ros2_cdr.nav_sat_fix(ns, frame, lat, lon, alt, cov9.tolist(), 3) == bytes(
            ts.serialize_cdr(fix, "sensor_msgs/msg/NavSatFix"))
        p, q, v, w = rng.normal(size=3), rng.normal(size=4), rng.normal(size=3), rng.normal(size=3)
        V3 = T["geometry_msgs/msg/Vector3"]
        odom = T["nav_msgs/msg/Odometry"](header=header, child_frame_id=child, pose=T[
            "geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])), covariance=cov36),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                linear=V3(x=v[0], y=v[1], z=v[2]), angular=V3(x=w[0], y=w[1], z=w[2])), covariance=tw36))
        assert ros2_cdr.odometry(ns, frame, child, tuple(p), tuple(q), cov36.tolist(), tuple(v), tuple(w),
                                 tw36.tolist()) == bytes(ts.serialize_cdr(odom, "nav_msgs/msg/Odometry"))


def test_the_local_enu_frame_is_pymap3ds() -> None:
    import pymap3d

    from slcp.deploy.ros2_cdr import LocalEnu

    rng = np.random.default_rng(3)
    for _ in range(20):
        origin = (rng.uniform(-1.4, 1.4), rng.uniform(-3.1, 3.1), rng.uniform(-100, 3000))
        enu = LocalEnu(origin)
        p = (origin[0] + rng.normal(0, 1e-3), origin[1] + rng.normal(0, 1e-3), origin[2] + rng.normal(0, 50))
        assert enu(*p) == pytest.approx(pymap3d.geodetic2enu(*p, *origin, deg=False), abs=1e-6)


def test_the_inputs_go_into_the_bag_and_decode_with_the_mcap_reader(tmp_path) -> None:
    """`--bag-inputs`: IMU samples (ROS's body axes), GNSS fixes with their σ and velocity, UWB
    rounds and beacons, the two slcp_msgs types decoded from the schemas the bag carries."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from slcp.transport.messages import Beacon, GnssFix, ImuBatch, UwbRound

    sink = McapSink(tmp_path / "bag", (0.6973, 2.0302, 50.0), inputs=True)
    assert any("/sensor/*/imu" in k for k in sink.observe_keys)
    t = np.array([1.01, 1.02, 1.03])
    sink.observe(ImuBatch("V-1", 3, t, np.full(3, 0.01), np.array([[1e-3, 2e-3, 3e-3]] * 3),
                          np.array([[0.01, 0.02, -0.0981]] * 3)))
    sink.observe(GnssFix("V-1", 1, 1.0, np.array([0.6973, 2.0302, 52.0]), np.array([1.0, -2.0, 0.5]),
                         np.array([0.3, 0.4, 0.9]), 0.05, 4))
    sink.observe(UwbRound("V-1", 7, 1.05, ("V2", "V3"), np.array([12.5, 40.25])))
    sink.observe(Beacon("V-1", 9, "SL-CP", 1.1, np.array([0.6973, 2.0302, 52.0]), np.array([1.0, -2.0, 0.5]),
                        np.diag([0.25, 0.36, 1.0]), auth=b"x" * 10, first_stopped=True))
    sink.observe(Diagnostics("V-1", 1.0, {}))  # not an input: ignored
    sink.close()
    got: dict[str, list] = {}
    with open(next((tmp_path / "bag").glob("*.mcap")), "rb") as fh:
        for schema, channel, message, decoded in make_reader(
                fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            got.setdefault(channel.topic, []).append((schema.name, message.log_time, decoded))
    assert sorted(got) == ["/slcp/V_1/beacon", "/slcp/V_1/gnss", "/slcp/V_1/gnss_velocity", "/slcp/V_1/imu",
                           "/slcp/V_1/uwb", "/slcp/map_origin"]
    imu = got["/slcp/V_1/imu"]
    assert [x[1] for x in imu] == [1_010_000_000, 1_020_000_000, 1_030_000_000]
    name, _, m = imu[0]
    assert name == "sensor_msgs/msg/Imu" and m.header.frame_id == "V-1/imu" and m.orientation_covariance[0] == -1
    assert (m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z) == pytest.approx((0.1, -0.2, -0.3))
    assert (m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z) == pytest.approx(
        (1.0, -2.0, 9.81))  # forward, left, up: the reaction to gravity points up
    _, _, fix = got["/slcp/V_1/gnss"][0]
    assert fix.latitude == pytest.approx(math.degrees(0.6973)) and fix.position_covariance_type == 2
    assert list(fix.position_covariance) == pytest.approx([0.16, 0, 0, 0, 0.09, 0, 0, 0, 0.81])
    _, _, vel = got["/slcp/V_1/gnss_velocity"][0]
    assert (vel.twist.twist.linear.x, vel.twist.twist.linear.y, vel.twist.twist.linear.z) == pytest.approx(
        (-2.0, 1.0, -0.5))
    name, _, uwb = got["/slcp/V_1/uwb"][0]
    assert name == "slcp_msgs/msg/UwbRound" and list(uwb.peers) == ["V2", "V3"]
    assert list(uwb.ranges) == [12.5, 40.25] and uwb.seq == 7
    name, _, b = got["/slcp/V_1/beacon"][0]
    assert name == "slcp_msgs/msg/Beacon" and b.method == "SL-CP" and b.first_stopped and b.signed
    assert list(b.position_covariance_ned) == pytest.approx([0.25, 0, 0, 0, 0.36, 0, 0, 0, 1.0])
    # the estimates' reader passes over the inputs
    est, _, counts = read_recording(tmp_path / "bag")
    assert est == {} and counts["/slcp/V_1/imu"] == 3
