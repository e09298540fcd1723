"""#44: a fleet live in Foxglove. The view's WebSocket server speaks Foxglove's protocol: a
client sees every topic advertised with its schema and receives the estimates and diagnostics
as they are written, in the units and frames the schemas say."""

from __future__ import annotations

import json
import math
import struct
import time

import numpy as np
from foxglove_client import FoxgloveClient

from slcp.deploy.foxglove_view import FoxgloveSink
from slcp.transport.messages import Diagnostics, Estimate


def test_a_foxglove_client_receives_the_topics_with_their_schemas() -> None:
    sink = FoxgloveSink(port=0)
    client = FoxgloveClient(sink.port, seconds=5.0,
                            until=lambda c: len(c.messages.get("/slcp/V1/SL_CP/fix", [])) == 5
                            and "/slcp/diagnostics" in c.messages)
    try:
        e = Estimate("V1", "SL-CP", 2.0, np.array([0.6973, 2.0302, 53.0]), np.array([1.0, 2.0, -0.5]),
                     np.array([0.0, 0.0, math.radians(30.0)]), np.diag([4.0, 1.0, 9.0]), True)
        sink.write(e)  # the channel exists (and is advertised) from the first estimate
        client.start()
        client.wait_subscribed({"/slcp/V1/SL_CP/fix", "/slcp/diagnostics"})
        for k in range(5):
            sink.write(Estimate(e.vehicle, e.method, 2.1 + 0.1 * k, e.llh, e.v_ned, e.rpy, e.cov_pos, True))
        sink.write(Diagnostics("V1", 2.5, {"beacons_rx": 12}, {"t": 2.5}))
        client.join()
    finally:
        sink.close()
    assert client.error is None, client.error
    topics = client.topics()
    fix = topics["/slcp/V1/SL_CP/fix"]
    assert fix["schemaName"] == "foxglove.LocationFix" and fix["encoding"] == "protobuf" and fix["schema"]
    diag = topics["/slcp/diagnostics"]
    assert diag["schemaName"] == "slcp.Diagnostics" and diag["encoding"] == "json"
    assert json.loads(diag["schema"])["properties"]["counters"]["type"] == "object"
    got = client.messages["/slcp/V1/SL_CP/fix"]
    assert [t for t, _ in got] == [int(round((2.1 + 0.1 * k) * 1e9)) for k in range(5)]
    # protobuf's doubles are little-endian in the payload: degrees, and the ENU covariance
    payload = got[0][1]
    assert struct.pack("<d", math.degrees(0.6973)) in payload and struct.pack("<d", 4.0) in payload
    (t, body), = client.messages["/slcp/diagnostics"]
    assert t == 2_500_000_000 and json.loads(body)["counters"] == {"beacons_rx": 12}


def test_a_taken_port_is_a_one_line_error(tmp_path, capsys) -> None:
    import socket

    from slcp.deploy.cli import main

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["run", "paper-1", "--out", str(tmp_path / "run"), "--foxglove", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"cannot serve the Foxglove view on 127.0.0.1:{port}" in err and "Traceback" not in err


def test_the_scene_holds_the_site_the_vehicles_with_their_ellipses_and_the_uwb_links() -> None:
    """/slcp/scene (foxglove.SceneUpdate, map = east, north of the site's origin): the stop lines
    where the site has them, each vehicle's 95 % ellipse and the link measured between them."""
    import pymap3d

    from slcp.deploy.foxglove_view import K95
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.transport.messages import UwbRound

    scn = load_scenario("paper-1")
    sink = FoxgloveSink(port=0, lanes=scn.lanes.values(), origin_llh=scn.origin_llh)
    # the site is sent again every second: a client that joined late sees it
    client = FoxgloveClient(sink.port, seconds=6.0, until=lambda c: len(c.messages.get("/slcp/scene", [])) >= 3
                            and any(b"site" in p for _, p in c.messages["/slcp/scene"]))
    positions = {"V1": (-20.0, 1.75), "V2": (-27.0, 1.75)}  # north, east [m]
    try:
        def estimates(t: float) -> None:
            for v, (n, e) in positions.items():
                llh = np.array(pymap3d.ned2geodetic(n, e, 0.0, *scn.origin_llh, deg=False))
                sink.write(Estimate(v, "SL-CP", t, llh, np.zeros(3), np.zeros(3), np.diag([0.25, 0.04, 1.0]),
                                    v == "V1"))

        estimates(1.0)
        client.start()
        client.wait_subscribed({"/slcp/scene"})
        sink.observe(UwbRound("V1", 1, 1.5, ("V2",), np.array([7.0])))
        for k in range(12):
            estimates(1.6 + 0.1 * k)
            time.sleep(0.21)
        client.join()
    finally:
        sink.close()
    assert client.error is None, client.error
    assert client.topics()["/slcp/scene"]["schemaName"] == "foxglove.SceneUpdate"
    scenes = b"".join(p for _, p in client.messages["/slcp/scene"])
    stop = next(ln for ln in scn.lanes.values() if ln.stop_line).stop_line_ends()
    for x in stop.ravel():  # the site's stop line, east and north, as the scene's doubles (proto3 leaves out 0)
        assert x == 0.0 or struct.pack("<d", float(x)) in scenes
    # V1's ellipse: 2.45 σ north of it at its northernmost point (σ_n 0.5 m)
    north_tip = -20.0 + K95 * 0.5
    doubles = [struct.unpack_from("<d", scenes, i)[0] for i in range(len(scenes) - 7)]
    assert any(abs(x - north_tip) < 1e-6 for x in doubles)
    assert b"uwb_links" in scenes and b"V2" in scenes
