"""Real-sensor adapters (NMEA, UBX, IMU text), the ``slcp sensors`` driver over a serial port and
log files, and a live agent running on the shared real drive through Zenoh."""

from __future__ import annotations

import asyncio
import calendar
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pynmea2
import pytest
from pyubx2 import GET, UBXMessage

from slcp.deploy.processes import ConfigError, load_agent_config
from slcp.deploy.sensors.imu import ImuAdapter, ImuFormatError, imu_increments, parse_imu_line, parse_units
from slcp.deploy.sensors.nmea import KNOT, NmeaFixAssembler
from slcp.deploy.sensors.ubx import UbxFixReader

from conftest import DRIVE_PROFILE, REPO, SHARED_DRIVE, drive_config, free_port, wait_for_port

CLI = [sys.executable, "-m", "slcp.deploy.cli"]
needs_drive = pytest.mark.skipif(not SHARED_DRIVE.is_dir(), reason=f"shared drive not found at {SHARED_DRIVE}")


# ----------------------------------------------------------------------------------- NMEA
def _ddmm(deg: float, pos: str, neg: str, width: int) -> tuple[str, str]:
    a = abs(deg)
    d = int(a)
    return f"{d:0{width}d}{(a - d) * 60:010.7f}", pos if deg >= 0 else neg


def nmea_epoch(t_utc: float, lat_deg: float, lon_deg: float, h_ell: float, vn: float, ve: float,
               sig: tuple[float, float, float] | None = (0.02, 0.03, 0.05), quality: int = 4,
               sep: float = -16.8, hdop: float = 0.8) -> list[str]:
    """RMC, GGA (and GST) of one epoch, as a receiver would print them."""
    dt_ = datetime.fromtimestamp(t_utc, UTC)
    hms = dt_.strftime("%H%M%S") + f".{dt_.microsecond // 10000:02d}"
    la, ns = _ddmm(lat_deg, "N", "S", 2)
    lo, ew = _ddmm(lon_deg, "E", "W", 3)
    sog = math.hypot(vn, ve) / KNOT
    cog = math.degrees(math.atan2(ve, vn)) % 360.0
    out = [pynmea2.RMC("GN", "RMC", (hms, "A", la, ns, lo, ew, f"{sog:.4f}", f"{cog:.3f}",
                                     dt_.strftime("%d%m%y"), "", "", "D")),
           pynmea2.GGA("GN", "GGA", (hms, la, ns, lo, ew, str(quality), "12", f"{hdop:.2f}",
                                     f"{h_ell - sep:.3f}", "M", f"{sep:.3f}", "M", "", ""))]
    if sig is not None:
        out.append(pynmea2.GST("GN", "GST", (hms, "0.5", "0.1", "0.1", "0", f"{sig[0]:.3f}", f"{sig[1]:.3f}",
                                             f"{sig[2]:.3f}")))
    return [str(m) for m in out]


def test_nmea_epochs_become_fixes_with_the_receivers_values() -> None:
    t0 = calendar.timegm((2025, 7, 8, 19, 34, 0, 0, 0, 0))
    a = NmeaFixAssembler("car1")
    fixes = []
    for k in range(4):
        for line in nmea_epoch(t0 + 0.2 * k, 40.1012345, -105.1543210, 1520.25, 3.0, -4.0):
            fixes += a.feed(line)
    fixes += a.flush()
    assert [f.seq for f in fixes] == [0, 1, 2, 3]
    f = fixes[1]
    assert f.t == pytest.approx(t0 + 0.2, abs=1e-6)
    assert math.degrees(f.llh[0]) == pytest.approx(40.1012345, abs=2e-9)
    assert math.degrees(f.llh[1]) == pytest.approx(-105.1543210, abs=2e-9)
    assert f.llh[2] == pytest.approx(1520.25, abs=1e-3)  # altitude MSL + separation = ellipsoidal
    np.testing.assert_allclose(f.v_ned, [3.0, -4.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(f.sigma_ned, [0.02, 0.03, 0.05])
    assert f.quality == 4
    # once the epoch pattern (RMC, GGA, GST) is learned, an epoch is emitted on its last sentence
    a2 = NmeaFixAssembler("car1")
    emitted_at = []
    for k in range(3):
        for i, line in enumerate(nmea_epoch(t0 + 0.2 * k, 40.1, -105.1, 1500.0, 0.0, 0.0)):
            if a2.feed(line):
                emitted_at.append((k, i))
    assert emitted_at == [(1, 0), (1, 2), (2, 2)]  # the first epoch waits for the second


def test_nmea_bad_input_is_counted_and_the_rest_still_works() -> None:
    t0 = calendar.timegm((2025, 7, 8, 23, 59, 59, 0, 0, 0))
    a = NmeaFixAssembler("car1", uere=2.0)
    good = nmea_epoch(t0, 40.1, -105.1, 1500.0, 1.0, 0.0, sig=None, hdop=1.5)
    bad_checksum = good[1][:-2] + ("00" if not good[1].endswith("00") else "11")
    fixes = []
    for line in [
        bad_checksum,
        "garbage",
        "$GPXYZ,1,2*00",
        "$GPGSV,3,1,11,03,03,111,00,04,15,270,00,06,01,010,00,13,06,292,00*74",
        *good,
        *nmea_epoch(t0 + 0.4, 40.1, -105.1, 1500.0, 1.0, 0.0, sig=None, hdop=1.5, quality=0),
        *nmea_epoch(t0 + 1.2, 40.1, -105.1, 1500.0, 1.0, 0.0, sig=None, hdop=1.5),
    ]:
        fixes += a.feed(line)
    fixes += a.flush()
    c = a.counters
    assert c["nmea_bad"] == 3 and c["nmea_ignored"] == 1 and c["nmea_no_fix"] == 1
    assert len(fixes) == 2
    np.testing.assert_allclose(fixes[0].sigma_ned, [3.0, 3.0, 4.5])  # HDOP × UERE without GST
    assert fixes[1].t == pytest.approx(t0 + 1.2)  # crossed midnight: the date came from the new RMC
    # an epoch before any date (no RMC yet) cannot be placed in time
    b = NmeaFixAssembler("car1")
    for k in range(3):
        b.feed(nmea_epoch(t0 + k, 40.1, -105.1, 1500.0, 1.0, 0.0)[1])
    b.flush()
    assert b.counters["nmea_no_date"] == 3 and b.counters["gnss_fixes"] == 0


# ------------------------------------------------------------------------------------ UBX
def nav_pvt(second: int = 5, fix_type: int = 3, ok: int = 1, **kw) -> bytes:
    fields = dict(iTOW=1000, year=2025, month=7, day=8, hour=19, min=34, second=second, validDate=1, validTime=1,
                  nano=-5000, fixType=fix_type, gnssFixOk=ok, numSV=12, lon=-105.1543210, lat=40.1012345,
                  height=1520250, hMSL=1537050, hAcc=1414, vAcc=2500, velN=1000, velE=-2000, velD=30,
                  gSpeed=2236, sAcc=300, carrSoln=2)
    fields.update(kw)
    return UBXMessage("NAV", "NAV-PVT", GET, **fields).serialize()


def test_ubx_nav_pvt_is_decoded_and_a_corrupted_stream_resynchronises() -> None:
    frame = nav_pvt()
    r = UbxFixReader("car1")
    (f,) = r.feed(frame)
    assert f.t == pytest.approx(calendar.timegm((2025, 7, 8, 19, 34, 5, 0, 0, 0)) - 5e-6, abs=1e-6)
    assert math.degrees(f.llh[0]) == pytest.approx(40.1012345, abs=1e-9)
    assert f.llh[2] == pytest.approx(1520.25)
    np.testing.assert_allclose(f.v_ned, [1.0, -2.0, 0.03])
    np.testing.assert_allclose(f.sigma_ned, [1.0, 1.0, 2.5], atol=1e-3)
    assert f.sigma_v == pytest.approx(0.3) and f.quality == 4

    corrupt = bytearray(nav_pvt(second=6))
    corrupt[30] ^= 0xFF  # checksum fails
    huge = b"\xb5\x62\x01\x07\xff\xff"  # a length no NAV-PVT has
    status = UBXMessage("NAV", "NAV-STATUS", GET, iTOW=1000, gpsFix=3).serialize()
    stream = (b"junk" + bytes(corrupt) + huge + status + nav_pvt(second=7) + nav_pvt(second=8, fix_type=0, ok=0)
              + nav_pvt(second=9, validTime=0) + nav_pvt(second=10))
    whole = UbxFixReader("car1")
    fixes = whole.feed(stream)
    assert [round(x.t) % 60 for x in fixes] == [7, 10]
    c = whole.counters
    assert c["ubx_bad"] >= 2 and c["ubx_ignored"] == 1 and c["ubx_no_fix"] == 1 and c["ubx_no_time"] == 1
    # fed in random pieces (a serial port's reads), the same fixes come out
    rng = np.random.default_rng(7)
    pieces = UbxFixReader("car1")
    out, i = [], 0
    while i < len(stream):
        n = int(rng.integers(1, 40))
        out += pieces.feed(stream[i:i + n])
        i += n
    assert [x.t for x in out] == [x.t for x in fixes]


# ------------------------------------------------------------------------------------ IMU
def test_imu_adapter_batches_equal_the_whole_array_increments(rng) -> None:
    n = 251
    t = 1000.0 + np.cumsum(np.full(n, 0.01) + rng.normal(0, 5e-4, n))
    acc = rng.normal([0, 0, -9.8], 0.5, (n, 3))
    gyr = rng.normal(0, 0.1, (n, 3))
    mount = (math.radians(180.0), math.radians(-6.79), math.radians(185.35))
    ad = ImuAdapter("car1", mount, time_offset=-0.125)
    batches = ad.push_many(t, acc, gyr)
    last = ad.flush()
    batches += [last] if last is not None else []
    from slcp.agent.nav.rotation import euler_to_dcm

    dth, dv, dt = imu_increments(t - 0.125, acc, gyr, euler_to_dcm(*mount).T)
    np.testing.assert_allclose(np.concatenate([b.dtheta for b in batches]), dth, atol=1e-15)
    np.testing.assert_allclose(np.concatenate([b.dvel for b in batches]), dv, atol=1e-13)
    np.testing.assert_allclose(np.concatenate([b.dt for b in batches]), dt, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([b.t for b in batches]), t[1:] - 0.125)
    assert all(b.t[-1] - b.t[0] + b.dt[0] >= 0.1 - 1e-9 for b in batches[:-1])
    assert [b.seq for b in batches] == list(range(len(batches)))
    # closed form: a sensor yawed 90° has its x axis along body -y
    turned = ImuAdapter("car1", (0.0, 0.0, math.pi / 2), batch_period=0.0)
    turned.push(0.0, np.array([1.0, 0, 0]), np.zeros(3))
    (b,) = turned.push(0.5, np.array([1.0, 0, 0]), np.zeros(3))
    np.testing.assert_allclose(b.dvel[0], [0.0, -0.5, 0.0], atol=1e-12)


def test_imu_adapter_takes_a_stretch_at_once_as_it_takes_its_samples_one_by_one(rng) -> None:
    """push_many's array path (finite samples, increasing times) gives the batches of push,
    whatever the stretches (including ones of one sample, which go sample by sample), and falls
    back to push when a stretch has a bad or repeated sample."""
    n = 1200
    t = 50.0 + np.cumsum(rng.uniform(0.008, 0.012, n))
    acc, gyr = rng.normal(size=(n, 3)), rng.normal(0, 0.1, (n, 3))
    gyr[700] = np.nan
    t[900] = t[899]  # repeated: out of order
    for cuts in ([n], [1, 400, 699, n], [3, 4, 701, 899, 950, n]):
        one, many = ImuAdapter("car1", (0.1, -0.2, 3.0), -0.125), ImuAdapter("car1", (0.1, -0.2, 3.0), -0.125)
        ref = [b for k in range(n) for b in one.push(t[k], acc[k], gyr[k])] + [one.flush()]
        got, lo = [], 0
        for hi in cuts:
            got += many.push_many(t[lo:hi], acc[lo:hi], gyr[lo:hi])
            lo = hi
        got.append(many.flush())
        assert one.counters == many.counters and one.counters["imu_bad_sample"] == 1
        assert [(b.seq, len(b.t)) for b in ref] == [(b.seq, len(b.t)) for b in got]
        for x, y in zip(ref, got):
            np.testing.assert_array_equal(x.t, y.t)
            np.testing.assert_allclose(np.c_[x.dtheta, x.dvel], np.c_[y.dtheta, y.dvel], rtol=0, atol=1e-15)


def test_imu_adapter_counts_bad_samples_and_lines() -> None:
    ad = ImuAdapter("car1", max_gap=0.05)
    ad.push(1.0, np.zeros(3), np.zeros(3))
    ad.push(0.9, np.zeros(3), np.zeros(3))  # older
    ad.push(1.0, np.zeros(3), np.zeros(3))  # same time
    ad.push(1.01, np.array([np.nan, 0, 0]), np.zeros(3))
    ad.push(1.5, np.zeros(3), np.zeros(3))  # a gap, still integrated
    c = ad.counters
    assert (c["imu_samples"], c["imu_out_of_order"], c["imu_bad_sample"], c["imu_gaps"]) == (2, 2, 1, 1)
    ag, gg = parse_units("g,deg/s")
    t, a, g = parse_imu_line("12.5, 0, 0, -1, 90, 0, 0", ag, gg)
    assert t == 12.5 and a[2] == pytest.approx(-9.80665) and g[0] == pytest.approx(math.pi / 2)
    assert parse_imu_line("0 0 -9.8 0 0 0.1", host_time=77.0)[0] == 77.0
    assert parse_imu_line("# header") is None and parse_imu_line("  ") is None
    for bad in ("1,2,3", "a,b,c,d,e,f,g", "1,2,3,4,5,6,inf", "0 0 -9.8 0 0 0.1"):
        with pytest.raises(ImuFormatError):
            parse_imu_line(bad)
    with pytest.raises(ValueError, match="ACCEL,GYRO"):
        parse_units("furlong,deg/s")


# ------------------------------------------------------------------------- agent config
def test_a_site_less_agent_config_takes_the_vehicles_imu_and_gnss(tmp_path) -> None:
    cfg, z = load_agent_config(REPO / "deploy" / "vehicles" / "rtklibexplorer-drive.agent.toml", None)
    assert cfg.vehicle == "V0" and cfg.methods == ("SP",) and cfg.lanes == {}
    assert cfg.settings.noise.arw == pytest.approx(2 * math.radians(0.0038), rel=1e-3)
    assert cfg.settings.gnss_multipath_sigma is None  # the receiver's σ as white noise
    assert cfg.settings.gnss_gate is None  # ... and no χ² gate on it
    assert z.listen == ("tcp/127.0.0.1:7460",)
    p = tmp_path / "a.toml"
    for text, where in (("[imu]\narw = -1\n", "imu"), ("[imu]\nbogus = 1\n", "imu.bogus"),
                        ("[gnss]\nmultipath_tau = 0\n", "gnss.multipath_tau"), ("[gnss]\nwhite = 1\n", "gnss.white"),
                        ("[gnss]\ngate = 1\n", "gnss.gate"), ("[gnss]\nreset_after = 0\n", "gnss.reset_after"),
                        ("[stop_gap]\nsigma_xb = -1\n", "stop_gap.*sigma_xb must be >= 0"),
                        ("[stop_gap]\nl0 = -3\n", "stop_gap.*l0 must be >= 0"),
                        ("[stop_gap]\nm_xb = nan\n", "stop_gap.*m_xb must be a finite number"),
                        ("[site]\n", "[site]")):
        p.write_text('[agent]\nvehicle = "car1"\n' + text)
        with pytest.raises(
            ConfigError, match=str(p).replace(".", r"\.") + ".*" + where.replace("[", r"\[").replace(".", r"\.")
            .replace(r"\.*", ".*")
        ):
            load_agent_config(p, None)
    p.write_text('[agent]\nvehicle = "car1"\n[gnss]\ngate = 0.9999\nreset_after = 90\n')
    s = load_agent_config(p, None)[0].settings
    assert (s.gnss_gate, s.gnss_reset_after) == (0.9999, 90.0)
    p.write_text('[agent]\nvehicle = "car1"\n[gnss]\ngate = 0\n')
    assert load_agent_config(p, None)[0].settings.gnss_gate is None


# ------------------------------------------------------------------ driver and live agents
def _zenoh_listener(port: int):
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    return ZenohBus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",)))


def _stop(p: subprocess.Popen, timeout: float = 10.0) -> int:
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGTERM)
        try:
            return p.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    return p.returncode


@pytest.mark.fleet
@pytest.mark.timeout(60)
def test_the_driver_reads_nmea_from_a_serial_port() -> None:
    """A pseudo-terminal stands in for the receiver's USB serial port: pyserial opens it, the
    sentences written into it come out as fixes on the bus, bad ones are counted."""
    from slcp.transport import keys
    from slcp.transport.codec import decode

    master, slave = os.openpty()
    port = free_port()

    async def main():
        bus = _zenoh_listener(port)
        fixes = bus.subscribe(keys.gnss("car1"))
        diag = bus.subscribe(keys.diag("car1.sensors"))
        drv = subprocess.Popen([*CLI, "sensors", "--vehicle", "car1", "--gnss", f"nmea:{os.ttyname(slave)}@9600",
                                "--connect", f"tcp/127.0.0.1:{port}"], start_new_session=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            await asyncio.sleep(3.0)  # the driver opens the port and connects
            t0 = time.time()
            for k in range(6):
                lines = nmea_epoch(t0 + 0.2 * k, 40.1, -105.1, 1500.0, 2.0, 0.0)
                if k == 2:
                    lines.insert(1, "$GNGGA,bad*00")
                os.write(master, ("\r\n".join(lines) + "\r\n").encode())
                await asyncio.sleep(0.05)
            got = []
            deadline = time.monotonic() + 10
            while len(got) < 5 and time.monotonic() < deadline:
                try:
                    _k, payload = await asyncio.wait_for(fixes.get(), 1.0)
                    got.append(decode(payload))
                except TimeoutError:
                    pass
            counters = {}
            # a diagnostics message may be a snapshot from before the fifth fix was published
            while time.monotonic() < deadline and (counters.get("nmea_bad", 0) < 1
                                                   or counters.get("published_gnss", 0) < 5):
                try:
                    counters = decode((await asyncio.wait_for(diag.get(), 2.0))[1]).counters
                except TimeoutError:
                    pass
            return got, counters, drv
        finally:
            _stop(drv)
            await bus.close()

    try:
        got, counters, drv = asyncio.run(main())
    finally:
        os.close(master)
        os.close(slave)
    assert [f.seq for f in got] == [0, 1, 2, 3, 4]  # the sixth epoch waits for a seventh
    assert all(f.v_ned[0] == pytest.approx(2.0, abs=1e-3) for f in got)
    assert counters["nmea_bad"] == 1 and counters["published_gnss"] >= 5
    assert drv.returncode == 0, drv.stderr.read().decode()[-2000:]


@pytest.mark.fleet
@pytest.mark.timeout(90)
def test_a_log_played_before_its_agent_is_up_waits_for_it(tmp_path) -> None:
    """``slcp sensors`` on a 120 s NMEA log at 40x is started 2 s before anybody listens: it waits
    until the vehicle's agent (here the test, with its token and subscription) is up, and every
    fix of the log arrives. Without the wait the first ones were published to nobody (lost)."""
    from slcp.transport import keys
    from slcp.transport.codec import decode

    t0 = 1.75e9
    lines = [line for k in range(120) for line in nmea_epoch(t0 + k, 40.1, -105.1, 1500.0, 2.0, 0.0)]
    log = tmp_path / "rx.nmea"
    log.write_text("\r\n".join(lines) + "\r\n")
    port = free_port()

    async def main():
        bus = _zenoh_listener(port)
        drv = subprocess.Popen([*CLI, "sensors", "--vehicle", "car1", "--gnss", f"nmea:{log}", "--speed", "40",
                                "--connect", f"tcp/127.0.0.1:{port}"], start_new_session=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            await asyncio.sleep(2.0)  # it has started and connected (its log plays in 3 s)
            fixes = bus.subscribe(keys.gnss("car1"))
            bus.declare_alive(keys.alive("agent", "car1"))
            got = []
            while True:
                try:
                    got.append(decode((await asyncio.wait_for(fixes.get(), 3.0))[1]))
                except TimeoutError:
                    if drv.poll() is not None:
                        break
            out, err = await asyncio.to_thread(drv.communicate, timeout=30)
            return got, drv.returncode, out, err
        finally:
            _stop(drv)
            await bus.close()

    got, rc, out, err = asyncio.run(main())
    assert rc == 0, err[-2000:]
    assert json.loads(out.strip().splitlines()[-1])["published_gnss"] == 120
    assert [round(f.t - t0) for f in got] == list(range(120))


def _agent(cfg_text: str, tmp_path: Path, port: int) -> subprocess.Popen:
    cfg = tmp_path / "agent.toml"
    cfg.write_text(cfg_text + f'\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n')
    # -v: the agent logs its counters when it stops (a test can show them when it fails)
    p = subprocess.Popen([*CLI, "-v", "agent", "--config", str(cfg)], start_new_session=True,
                         stdout=subprocess.DEVNULL, stderr=open(tmp_path / "agent.log", "w"))
    wait_for_port(port)
    return p


def _drive_agent_config() -> str:
    text = (REPO / "deploy" / "vehicles" / "rtklibexplorer-drive.agent.toml").read_text()
    return text[:text.index("[zenoh]")].replace('profile = "rtklibexplorer-drive.toml"', f'profile = "{DRIVE_PROFILE}"')


@pytest.mark.fleet
@pytest.mark.slow
@needs_drive
@pytest.mark.timeout(180)
def test_replay_publish_drives_a_live_agent_like_the_offline_filter(tmp_path) -> None:
    """One engine under both hosts: the first 120 s of the real drive (two 15 s outages) played
    onto V0's topics at 2× to a live agent configured by the drive's vehicle file, and the
    offline replay with its defaults (the same engine settings: checked below), agree within a
    centimetre on the outage figures of the epochs the live run scored. (At 10× and 5× the
    live figures differed in some runs beside the suite's fleets, by up to 0.6 m at 10× and
    1.2 cm on the outage maximum at 5×; the cause is not shown. A failure prints the agent's
    sequencer and queue counters and the publisher's lateness.)"""
    import dataclasses

    from slcp.deploy.datasets.rtklib import load_drive
    from slcp.deploy.drive_scoring import outage_metrics
    from slcp.deploy.processes import load_agent_config
    from slcp.deploy.replay import engine_config, run_replay

    live_cfg, _ = load_agent_config(REPO / "deploy" / "vehicles" / "rtklibexplorer-drive.agent.toml", None)
    off_cfg = engine_config(drive_config())
    def flat(settings):
        out = {}
        for f in dataclasses.fields(settings):
            v = getattr(settings, f.name)
            out.update({f"{f.name}.{k}": x for k, x in dataclasses.asdict(v).items()}
                       if dataclasses.is_dataclass(v) else {f.name: v})
        return out

    live, off_settings = flat(live_cfg.settings), flat(off_cfg.settings)
    assert live.keys() == off_settings.keys()
    for k, v in off_settings.items():
        assert live[k] == (pytest.approx(v, rel=1e-12) if isinstance(v, (float, tuple)) else v), k
    port = free_port()
    agent = _agent(_drive_agent_config(), tmp_path, port)
    try:
        out = subprocess.run([*CLI, "replay", "rtklib", str(SHARED_DRIVE), "--vehicle", str(DRIVE_PROFILE),
                              "--publish", "--duration", "120",
                              "--speed", "2", "--connect", f"tcp/127.0.0.1:{port}", "--json"],
                             capture_output=True, text=True, timeout=150)
    finally:
        _stop(agent)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout)
    sp = res["methods"]["SP"]
    assert res["gnss_withheld"] == 120  # its lateness (max_late_s) is printed on a failure
    off = run_replay(load_drive(SHARED_DRIVE), drive_config())
    print(f"\nlive agent scored {sp['epochs']} epochs, {sp['first_epoch_t'] - off.t[0]:.2f}-"
          f"{sp['last_epoch_t'] - off.t[0]:.2f} s into the drive")
    assert sp["epochs"] >= 460 and sp["gnss_on_h_rms_m"] < 0.5 and sp["n_outages"] == 2, (sp, res["max_late_s"])
    # the epochs the live run scored, by time (the first n epochs assumed both runs start
    # scoring at the same epoch; a live run that starts later would be compared with a window
    # that also ends earlier)
    same = (off.t >= sp["first_epoch_t"] - 1e-6) & (off.t <= sp["last_epoch_t"] + 1e-6)
    assert int(same.sum()) == sp["epochs"]
    ref = outage_metrics(off.h_err[same], off.withheld[same])
    print(f"\nlive agent outage RMS {sp['outage_h_rms_m']:.3f} m, offline {ref['outage_h_rms_m']:.3f} m; "
          f"end mean {sp['outage_h_end_mean_m']:.3f} / {ref['outage_h_end_mean_m']:.3f} m")
    counters = [ln for ln in (tmp_path / "agent.log").read_text().splitlines() if "counters" in ln]
    # what a failure needs first: the sequencer's account of late and out-of-order data
    seq = re.findall(r"'(seq_[a-z_]+|queue_dropped_[a-z]+|gnss|imu_batches|estimates_tx|SP_gnss[a-z_]*)': (\d+)",
                     counters[-1]) if counters else []
    for k in ("outage_h_rms_m", "outage_h_end_mean_m", "outage_h_max_m"):
        assert sp[k] == pytest.approx(ref[k], abs=0.01), (k, sp[k], ref[k], res["max_late_s"], seq, sp)


def _write_logs(tmp_path: Path, t_from: float, t_to: float, gap: tuple[float, float]) -> tuple[Path, Path, dict]:
    """The drive as a receiver's NMEA log (UTC; no fixes inside ``gap``) and an IMU text log
    (UTC, g and deg/s, sensor frame, as logged)."""
    from slcp.deploy.datasets.rtklib import load_drive

    d = load_drive(SHARED_DRIVE)
    g, imu = d.gnss, d.imu
    leap = 18.0  # GPST - UTC in 2025
    sel = np.flatnonzero((g.t >= t_from) & (g.t <= t_to))
    lines = []
    for i in sel:
        if gap[0] <= g.t[i] < gap[1]:
            continue
        sig = tuple(float(max(x, 0.01)) for x in g.sd_neu[i])
        lines += nmea_epoch(float(g.t[i]) - leap, math.degrees(g.llh[i, 0]), math.degrees(g.llh[i, 1]),
                            float(g.llh[i, 2]) - 16.8, float(g.v_ned[i, 0]), float(g.v_ned[i, 1]), sig=sig)
    nmea = tmp_path / "gnss.nmea"
    nmea.write_text("\r\n".join(lines) + "\r\n")
    k = np.flatnonzero((imu.t >= t_from - 1.0) & (imu.t <= t_to))
    rows = np.column_stack([imu.t[k] - leap, imu.accel[k] / 9.80665, np.degrees(imu.gyro[k])])
    csv = tmp_path / "imu.csv"
    np.savetxt(
        csv, rows, fmt=["%.4f"] + ["%.6f"] * 6, delimiter=",", header="t_utc_s,ax_g,ay_g,az_g,gx_dps,gy_dps,gz_dps"
    )
    truth = {"t": g.t[sel] - leap, "llh": g.llh[sel] + np.array([0, 0, -16.8]),
             "gap": (gap[0] - leap, gap[1] - leap)}
    return nmea, csv, truth


@pytest.mark.fleet
@pytest.mark.slow
@needs_drive
@pytest.mark.timeout(180)
def test_the_driver_plays_nmea_and_imu_logs_to_a_live_agent(tmp_path) -> None:
    """80 s of the real drive written as an NMEA log (with a 12 s gap in the fixes) and an IMU
    text log in g and deg/s: ``slcp sensors`` converts and paces them at 8×, the agent runs on
    them, and its estimates follow the fixes (and coast through the gap)."""
    from slcp.transport import keys
    from slcp.transport.codec import decode

    t_from = float(np.floor(_first_fix_time())) + 2.0
    nmea, csv, truth = _write_logs(tmp_path, t_from, t_from + 80.0, (t_from + 50.0, t_from + 62.0))
    port, port2 = free_port(), free_port()
    agent = _agent(_drive_agent_config(), tmp_path, port)

    async def collect(start):
        from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

        # the driver starts once this session is subscribed and the agent is (its liveliness
        # token follows its subscriptions): at 8x, a session opened after the driver started
        # missed the first seconds of estimates (17 of 320 epochs, on a busy machine)
        bus = ZenohBus(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",)))
        est = bus.subscribe(f"{keys.ROOT}/estimate/V0/*", 4096)
        ready = asyncio.Event()
        bus.watch_alive(keys.alive("agent", "V0"), lambda key, alive: alive and ready.set())
        await asyncio.wait_for(ready.wait(), 30.0)
        await asyncio.sleep(0.2)  # this subscription reaches the agent (declared before the watch)
        drv = start()
        procs.append(drv)
        rows = []
        try:
            # until the driver has ended and the agent has been silent for 3 s: on a busy machine
            # the agent ends its estimates well after the driver published its last samples
            while True:
                try:
                    rows.append(decode((await asyncio.wait_for(est.get(), 3.0))[1]))
                except TimeoutError:
                    if drv.poll() is not None:
                        break
        finally:
            await bus.close()
        return rows

    procs: list[subprocess.Popen] = []

    def start() -> subprocess.Popen:
        return subprocess.Popen(
            [
                *CLI,
                "sensors",
                "--vehicle",
                "V0",
                "--gnss",
                f"nmea:{nmea}",
                "--imu",
                f"csv:{csv}",
                "--imu-units",
                "g,deg/s",
                "--imu-mount",
                "180,-6.79,185.35",
                "--imu-time-offset",
                "-0.125",
                "--speed",
                "8",
                "--connect",
                f"tcp/127.0.0.1:{port}",
                "--listen",
                f"tcp/127.0.0.1:{port2}",
            ],
            start_new_session=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    try:
        rows = asyncio.run(collect(start))
        drv = procs[0]
        out, err = drv.communicate(timeout=30)
    finally:
        for p in procs:
            if p.poll() is None:
                _stop(p)
        _stop(agent)
    assert drv.returncode == 0, err[-2000:]
    counters = json.loads(out.strip().splitlines()[-1])
    assert counters["nmea_bad"] == 0 and counters["imu_bad_line"] == 0 and counters["imu_out_of_order"] == 0
    gap_all = (truth["t"] >= truth["gap"][0]) & (truth["t"] < truth["gap"][1])
    assert gap_all.sum() > 40 and counters["gnss_fixes"] == int((~gap_all).sum())  # 12 s of fixes left out
    from slcp.deploy.drive_scoring import antenna_positions, errors_at_epochs

    inside, err = errors_at_epochs(truth["t"], truth["llh"], np.array([r.t for r in rows]),
                                   antenna_positions(rows, drive_config().profile.gnss.lever_arm_m))
    in_gap = (truth["t"][inside] >= truth["gap"][0]) & (truth["t"][inside] < truth["gap"][1])
    on_median, on_p95 = np.percentile(err[~in_gap], [50, 95])
    gap_rms = float(np.sqrt(np.mean(err[in_gap] ** 2)))
    # the offline filter with the same model and a GNSS outage at the same time
    from slcp.deploy.datasets.rtklib import load_drive
    from slcp.deploy.replay import OutageProtocol, run_replay

    d = load_drive(SHARED_DRIVE)
    outage = OutageProtocol(first=t_from + 50.0 - float(d.gnss.t[0]), period=1000.0, length=12.0, end_margin=0.0)
    off = run_replay(d, drive_config(outage, nhc=False, estimate_time_offset=False))
    off_rms = float(np.sqrt(np.mean(off.h_err[off.withheld] ** 2)))
    print(f"\nagent on NMEA + IMU logs: {len(rows)} estimates spanning {inside.sum()} of {len(inside)} fixes, "
          f"GNSS on median {on_median:.3f} m, "
          f"95th percentile {on_p95:.2f} m; 12 s gap RMS {gap_rms:.2f} m (offline filter {off_rms:.2f} m)")
    agent_log = (tmp_path / "agent.log").read_text(errors="replace").strip().splitlines()
    assert inside.sum() >= 0.95 * len(truth["t"]), f"{inside.sum()} of {len(inside)}; agent: {agent_log[-1:]}"
    assert on_median < 0.05 and on_p95 < 0.3
    # not worse than the offline filter: the agent, which starts standing here, keeps its yaw
    # out of the updates until the GNSS course gives it (agent.methods), the offline filter
    # does not; the agent's gap error went from about the offline filter's (6.1 m) to 1.1 m
    assert gap_rms <= 1.25 * off_rms


def _first_fix_time() -> float:
    from slcp.deploy.datasets.rtklib import read_pos

    return float(read_pos(next(SHARED_DRIVE.glob("*.pos"))).t[0])


def test_the_driver_merges_its_log_files_in_time_order(tmp_path) -> None:
    """An NMEA log (1 Hz) and an IMU log (100 Hz, 10 Hz batches) of the same 20 s, played as fast
    as the driver goes: the fixes and batches reach the bus in time order across the two files
    (played by two independent streams they came in whatever order the driver's tasks ran, and
    an agent drops a fix that comes later than its IMU hold)."""
    from slcp.deploy.sensors.driver import SensorDriver, SourceSpec
    from slcp.transport import keys
    from slcp.transport.bus import InMemoryNetwork
    from slcp.transport.codec import decode
    from slcp.transport.messages import GnssFix

    t0 = 1.75e9
    nmea = tmp_path / "rx.nmea"
    nmea.write_text("\r\n".join(line for k in range(20) for line in nmea_epoch(t0 + k, 40.1, -105.1, 1500.0,
                                                                               2.0, 0.0)) + "\r\n")
    imu = tmp_path / "imu.csv"
    imu.write_text("".join(f"{t0 - 0.5 + 0.01 * i:.3f},0.1,0,-9.8,0,0,0.01\n" for i in range(2100)))

    async def main():
        net = InMemoryNetwork()
        bus = net.bus()
        sub = bus.subscribe(f"{keys.ROOT}/sensor/car1/*", maxsize=100_000)
        drv = SensorDriver(bus, "car1", gnss=SourceSpec.parse("gnss", f"nmea:{nmea}"),
                           imu=SourceSpec.parse("imu", f"csv:{imu}"), speed=1e6)
        await asyncio.wait_for(drv.run(asyncio.Event()), 30)
        return [decode(payload) for _, payload in sub.drain()], drv.all_counters()

    got, counters = asyncio.run(main())
    times = [float(m.t) if isinstance(m, GnssFix) else float(m.t[-1]) for m in got]
    n_fix = sum(isinstance(m, GnssFix) for m in got)
    assert n_fix == counters["published_gnss"] == 20 and len(got) - n_fix == counters["published_imu"] > 150
    assert times == sorted(times)


def test_the_driver_reads_a_ubx_log_file_paced_by_its_time_stamps(tmp_path) -> None:
    """A UBX log with junk and a corrupted frame, through the driver on the in-memory bus at 5×:
    every valid NAV-PVT is published in order, no faster than 5× its own time."""
    from slcp.deploy.sensors.driver import SensorDriver, SourceSpec
    from slcp.transport import keys
    from slcp.transport.bus import InMemoryNetwork
    from slcp.transport.codec import decode

    frames = [nav_pvt(second=5, nano=200_000_000 * k) for k in range(5)]
    bad = bytearray(frames[2])
    bad[40] ^= 0x55
    log = tmp_path / "rx.ubx"
    log.write_bytes(b"\x00junk" + frames[0] + frames[1] + bytes(bad) + frames[3] + b"\xb5" + frames[4])

    async def main():
        net = InMemoryNetwork()
        bus = net.bus()
        sub = bus.subscribe(keys.gnss("car1"))
        drv = SensorDriver(bus, "car1", gnss=SourceSpec.parse("gnss", f"ubx:{log}"), speed=5.0)
        t0 = time.monotonic()
        await asyncio.wait_for(drv.run(asyncio.Event()), 10)
        wall = time.monotonic() - t0
        got = [decode(payload) for _, payload in sub.drain()]
        return got, wall, drv.all_counters()

    got, wall, counters = asyncio.run(main())
    assert [round((f.t % 1) * 5) for f in got] == [0, 1, 3, 4]
    assert wall >= 0.8 / 5 * 0.9  # 0.8 s of fixes at 5×
    assert counters["ubx_bad"] >= 1 and counters["published_gnss"] == 4
    with pytest.raises(ValueError, match="FORMAT:PATH"):
        SourceSpec.parse("gnss", f"sirf:{log}")
    with pytest.raises(ValueError, match="No such file"):
        SourceSpec.parse("imu", "csv:/nonexistent/imu.csv")
