"""The live map in the browser (#44): what its WebSocket sends, checked against independent
computations; its server's guards; and the page itself in headless Chromium during a real run."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pymap3d
import pytest

from slcp.deploy.live_map import LINK_TTL_S, LiveMapSink, LiveMapState
from slcp.hw_emulation.scenario import load_scenario
from slcp.transport.messages import Diagnostics, Estimate, UwbRange, UwbRound

from conftest import free_port, short_scenario, wait_for_port

ORIGIN = (math.radians(40.0), math.radians(-83.0), 200.0)


def _estimate(vehicle: str, t: float, north: float, east: float, method: str = "SL-CP", cov=None, claim=False,
              origin=ORIGIN):
    llh = pymap3d.ned2geodetic(north, east, 0.0, *origin, deg=False)
    c = np.diag([0.04, 0.09, 0.25]) if cov is None else cov
    return Estimate(vehicle, method, t, np.array(llh), np.array([3.0, -4.0, 0.0]), np.array([0.0, 0.0, 0.3]), c, claim)


def test_the_state_puts_each_vehicle_where_pymap3d_does_with_its_covariance_east_north() -> None:
    s = LiveMapState(origin_llh=ORIGIN)
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.0], [0.0, 0.0, 0.25]])  # north, east, down
    s.write(_estimate("V1", 10.0, 120.0, -35.0, cov=cov, claim=True))
    s.write(_estimate("V1", 9.0, 0.0, 0.0))  # older: ignored
    s.write(Diagnostics("V1", 10.0, {"beacons_rx": 3}))
    (row,) = s.snapshot()["estimates"]
    assert (row["e"], row["n"]) == pytest.approx((-35.0, 120.0), abs=1e-3)
    assert row["cov"] == pytest.approx([0.09, 0.01, 0.04])  # ee, en, nn
    assert row["speed"] == pytest.approx(5.0) and row["heading"] == pytest.approx(0.3)
    assert row["sigma_h"] == pytest.approx(math.sqrt(0.13)) and row["first_stopped"] is True
    assert "err_h" not in row  # no truth: a deployed fleet


def test_uwb_links_are_shown_for_a_second_after_their_last_range() -> None:
    s = LiveMapState(origin_llh=ORIGIN)
    s.observe(UwbRound("V2", 1, 5.0, ("V0", "V1"), np.array([10.0, 12.0])))
    s.observe(UwbRange("V1", "V0", 1, 5.2, 8.0))
    s.write(_estimate("V0", 5.0 + LINK_TTL_S - 0.1, 0.0, 0.0))
    assert s.snapshot()["links"] == [["V0", "V1"], ["V0", "V2"], ["V1", "V2"]]
    s.write(_estimate("V0", 5.0 + LINK_TTL_S + 0.1, 0.0, 0.0))
    assert s.snapshot()["links"] == [["V0", "V1"]]


def test_the_error_shown_is_the_reports_error_against_the_truth() -> None:
    from slcp.hw_emulation.truth import build_truth

    scn = load_scenario("paper-1")
    truth = build_truth(scn, stop_seed=0)
    s = LiveMapState(scn.lanes.values(), scn.origin_llh, truth)
    tr = truth.vehicles["V2"].truth
    k = int(np.searchsorted(tr.t, 20.0))
    # an estimate 3 m north and 4 m east of the truth at that sample: 5 m off
    n0, e0, _ = pymap3d.geodetic2ned(*tr.llh[k], *scn.origin_llh, deg=False)
    llh = pymap3d.ned2geodetic(n0 + 3.0, e0 + 4.0, -tr.llh[k][2] + scn.origin_llh[2], *scn.origin_llh, deg=False)
    s.write(Estimate("V2", "SP", float(tr.t[k]), np.array(llh), np.zeros(3), np.zeros(3), np.eye(3)))
    (row,) = s.snapshot()["estimates"]
    assert row["err_h"] == pytest.approx(5.0, abs=2e-3)
    assert row["truth"] == pytest.approx([e0, n0], abs=2e-3)
    site = s.site()
    assert len(site["lanes"]) == len(scn.lanes) and set(site["truth_tracks"]) == {"V0", "V1", "V2"}
    stops = [ln for ln in site["lanes"] if ln["stop_line"]]
    assert stops and all(math.dist(*ln["stop_line"]) == pytest.approx(ln["width"], abs=2e-3) for ln in stops)


def test_the_server_serves_its_page_and_answers_only_its_own_origin() -> None:
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    sink = LiveMapSink(LiveMapState(origin_llh=ORIGIN), port=0, rate_hz=20.0)
    try:
        with urllib.request.urlopen(sink.url, timeout=5) as r:
            page = r.read().decode()
            assert r.headers["Content-Type"].startswith("text/html")
            assert "connect-src 'self'" in r.headers["Content-Security-Policy"]
        # nothing is fetched from elsewhere: no address in the page but its own WebSocket
        assert "http://" not in page and "https://" not in page and "<script src" not in page
        with pytest.raises(urllib.error.HTTPError, match="404"):
            urllib.request.urlopen(sink.url + "other", timeout=5)
        with pytest.raises(InvalidStatus, match="403"):
            connect(f"ws://127.0.0.1:{sink.port}/ws", origin="http://evil.example", open_timeout=5)
        sink.write(_estimate("V0", 1.0, 10.0, 20.0))
        with connect(f"ws://127.0.0.1:{sink.port}/ws", origin=f"http://127.0.0.1:{sink.port}", open_timeout=5) as ws:
            site = json.loads(ws.recv(timeout=5))
            assert site["type"] == "site" and site["origin"] == pytest.approx([40.0, -83.0, 200.0])
            t0 = time.monotonic()
            states = [json.loads(ws.recv(timeout=5)) for _ in range(10)]
            assert time.monotonic() - t0 < 2.0  # 20 a second asked
            assert all(m["type"] == "state" and m["estimates"][0]["vehicle"] == "V0" for m in states)
        with pytest.raises(OSError, match=f"cannot serve the live map on 127.0.0.1:{sink.port}"):
            LiveMapSink(LiveMapState(), port=sink.port)
    finally:
        sink.close()


def _browser():
    """Headless Chromium (Debian's package) under Playwright, or a skip saying what is missing."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("needs Debian's chromium (apt-get install chromium); .ci/run installs it")
    pw = pytest.importorskip("playwright.sync_api")
    return exe, pw


@pytest.mark.fleet
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_chromium_sees_every_vehicle_of_paper_1_moving_with_the_recorded_error(tmp_path) -> None:
    """#44 acceptance 2: during `slcp run paper-1 --view`, headless Chromium shows every vehicle
    moving, and the error it displays for a vehicle is the one the run's report records. The
    agents of this run are configured as deployed vehicles (`--lanelet2`: no scenario, the site
    from a Lanelet2 map), which the page does not see, and its bag holds the inputs too. The run
    plays at 2× real time, so that the page, read four times a second, shows each vehicle at
    enough times whatever the machine's speed (as fast as the agents kept up, a fast moment left
    fewer than ten readings of a vehicle's SL-CP estimate)."""
    exe, pw = _browser()
    scn = short_scenario(tmp_path, "paper-1", 25.0)
    port, out = free_port(), tmp_path / "run"
    seen: dict[str, list[tuple[float, float, float, str]]] = {}  # vehicle -> (t, e, n, error shown)
    run = None
    try:
        with pw.sync_playwright() as p:
            # the browser first: started beside a busy suite it took seconds, at 2× the run's
            # time, and the page then saw a vehicle only in the run's last seconds
            browser = p.chromium.launch(executable_path=exe, args=[
                "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                "--disable-sync", "--no-first-run"])
            page = browser.new_page(viewport={"width": 1280, "height": 760})
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            run = subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "run", str(scn), "--out", str(out),
                                    "--methods", "SP", "SL-CP", "--view", str(port), "--lanelet2", "--bag-inputs",
                                    "--speed", "2"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            wait_for_port(port, 60)
            page.goto(f"http://127.0.0.1:{port}/")
            shot = False
            while run.poll() is None:
                rows = page.eval_on_selector_all("tr.vehicle", """rs => rs.map(r => [r.dataset.vehicle,
                    r.dataset.method, +r.dataset.t, +r.dataset.e, +r.dataset.n,
                    r.querySelector('.err').textContent])""")
                for v, method, t, e, n, err in rows:
                    # the best method present is shown: SP for the moment before SL-CP's first estimate
                    assert method in ("SP", "SL-CP")
                    if method == "SL-CP" and (not seen.get(v) or seen[v][-1][0] != t):
                        seen.setdefault(v, []).append((t, e, n, err))
                if not shot and len(rows) == 3 and rows[0][2] > 12.0:
                    page.screenshot(path=str(tmp_path / "live-map.png"))
                    shot = True
                time.sleep(0.25)
            browser.close()
        assert not errors, errors
        assert shot and (tmp_path / "live-map.png").stat().st_size > 10_000
    finally:
        if run is not None and run.poll() is None:
            run.kill()
        _, stderr = run.communicate(timeout=60) if run is not None else (None, "")
    assert run is not None and run.returncode == 0, stderr[-3000:]
    agent_file = (out / "config" / "agent-V1.toml").read_text()
    assert 'site = "site.osm"' in agent_file and "scenario" not in agent_file
    from slcp.deploy.mcap_recording import read_recording

    est, _, counts = read_recording(out / "recorded" / "bag")
    for v in ("V0", "V1", "V2"):  # 25 s of IMU at 100 Hz, fixes, UWB rounds and beacons of every vehicle
        assert counts[f"/slcp/{v}/imu"] >= 2400 and counts[f"/slcp/{v}/gnss"] >= 20, v
        assert counts[f"/slcp/{v}/uwb"] >= 100 and counts[f"/slcp/{v}/beacon"] >= 100, v
        assert len(est[(v, "SL-CP")]) == counts[f"/slcp/{v}/SL_CP/fix"] > 100
    assert sorted(seen) == ["V0", "V1", "V2"]
    for v, samples in seen.items():
        ts = [s[0] for s in samples]
        assert len(samples) >= 10 and ts == sorted(ts) and ts[-1] - ts[0] > 5.0, (v, ts)
        span = max(math.dist(a[1:3], b[1:3]) for a in samples for b in samples)
        assert span > 10.0, (v, span)  # it moved on the page while the run went on
        recorded = _recorded_errors(out / "estimates" / f"{v}.csv")
        for t, _, _, err in samples:
            assert float(err) == pytest.approx(recorded[round(t, 3)], abs=0.01), (v, t)


def _recorded_errors(path) -> dict[float, float]:
    """Time [s] (to the ms) -> horizontal error [m] of SL-CP in a run's estimates CSV."""
    import csv

    with open(path) as fh:
        return {round(float(r["time_s"]), 3): float(r["err_h_m"]) for r in csv.DictReader(fh) if r["method"] == "SL-CP"}


@pytest.mark.fleet
@pytest.mark.timeout(120)
def test_slcp_view_shows_a_deployed_fleet_through_its_router(tmp_path) -> None:
    """`slcp view --connect` (a deployed fleet): the estimates and UWB rounds published through a
    Zenoh router reach the page's WebSocket, on the scenario's site, with σ and no truth."""
    import asyncio
    import os
    import signal

    from websockets.sync.client import connect

    from slcp.transport import keys
    from slcp.transport.codec import encode
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    rport, vport = free_port(), free_port()
    ep = f"tcp/127.0.0.1:{rport}"
    cli = [sys.executable, "-m", "slcp.deploy.cli"]
    procs = [subprocess.Popen([*cli, "router", "--listen", ep], start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    scn = load_scenario("paper-1")

    async def publish(ws) -> dict:
        bus = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
        try:
            for k in range(100):
                t = 1.0 + 0.1 * k
                for v, north in (("V0", 50.0), ("V1", -15.0)):
                    e = _estimate(v, t, north, 1.75, origin=scn.origin_llh)
                    await bus.publish(keys.estimate(v, "SL-CP"), encode(e))
                await bus.publish(keys.uwb("V0"), encode(UwbRound("V0", k, t, ("V1",), np.array([65.0]))))
                await asyncio.sleep(0.1)
                state = await asyncio.to_thread(_latest_state, ws)
                if state and len(state["estimates"]) == 2 and state["links"]:
                    return state
            raise AssertionError("the view never showed both vehicles and their link")
        finally:
            await bus.close()

    try:
        wait_for_port(rport)
        procs.append(subprocess.Popen([*cli, "view", "--connect", ep, "--port", str(vport), "--scenario", "paper-1"],
                                      start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                      text=True))
        wait_for_port(vport, 30)
        with connect(f"ws://127.0.0.1:{vport}/ws", open_timeout=10) as ws:
            site = json.loads(ws.recv(timeout=10))
            assert len(site["lanes"]) == len(scn.lanes) and site["truth_tracks"] == {}
            assert site["origin"] == pytest.approx([math.degrees(scn.origin_llh[0]), math.degrees(scn.origin_llh[1]),
                                                    scn.origin_llh[2]])
            state = asyncio.run(publish(ws))
        rows = {r["vehicle"]: r for r in state["estimates"]}
        assert (rows["V0"]["e"], rows["V0"]["n"]) == pytest.approx((1.75, 50.0), abs=1e-3)
        assert state["links"] == [["V0", "V1"]] and "err_h" not in rows["V1"]
    finally:
        for p in procs:
            os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            p.wait(timeout=20)
    assert procs[1].returncode == 0, procs[1].stderr.read()[-2000:]


def _latest_state(ws) -> dict | None:
    """The newest state message the WebSocket has queued (None if none came in 0.5 s)."""
    from websockets.exceptions import ConnectionClosed

    latest = None
    try:
        while True:
            m = json.loads(ws.recv(timeout=0.5 if latest is None else 0.01))
            if m["type"] == "state":
                latest = m
    except (TimeoutError, ConnectionClosed):
        return latest


def test_invented_names_cannot_grow_the_map_without_bound(monkeypatch) -> None:
    from slcp.deploy import live_map

    monkeypatch.setattr(live_map, "MAX_ROWS", 5)
    monkeypatch.setattr(live_map, "MAX_LINKS", 3)
    s = LiveMapState(origin_llh=ORIGIN)
    for k in range(8):
        s.write(_estimate(f"X{k}", 1.0, 0.0, 0.0))
        s.observe(UwbRange(f"X{k}", "V0", k, 1.0, 5.0))
    s.write(_estimate("X0", 2.0, 1.0, 0.0))  # a known row still updates
    rows = s.snapshot()["estimates"]
    assert len(rows) == 5 and s.refused == 3 + 5
    assert next(r for r in rows if r["vehicle"] == "X0")["t"] == 2.0
