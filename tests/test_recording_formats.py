"""Recording formats: each reader on small files the test writes, round trips through each
writer, the readers' errors, and (on the shared drive) every format scoring as the native read."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from slcp.deploy.datasets import DatasetError, csv_columns, kfgins, ros2_bag
from slcp.deploy.datasets.formats import FORMATS, load_recording
from slcp.deploy.datasets.recording import Recording, gnss_log, imu_log
from slcp.deploy.datasets.rtklib import load_drive, read_imu_csv, read_pos

from conftest import DRIVE_PROFILE, SHARED_DRIVE

G0 = 9.80665


def _recording(n_imu: int = 400, rate: float = 100.0, velocity: bool = True) -> Recording:
    """A small recording: IMU samples with distinct values, 4 Hz fixes with a few qualities."""
    rng = np.random.default_rng(7)
    t = 1000.0 + np.arange(n_imu) / rate
    imu = imu_log(t, rng.normal(0, 1, (n_imu, 3)) + [0, 0, -G0], rng.normal(0, 0.1, (n_imu, 3)))
    tg = 1000.0 + np.arange(0.0, n_imu / rate, 0.25)
    n = len(tg)
    v = rng.normal(0, 3, (n, 3)) if velocity else None
    sv = np.abs(rng.normal(0.05, 0.01, (n, 3))) if velocity else None
    g = gnss_log(tg, 40.1 + 1e-5 * np.arange(n), -105.1 - 2e-5 * np.arange(n), 1600 + 0.01 * np.arange(n),
                 np.abs(rng.normal(0.01, 0.002, (n, 3))), v, sv, np.where(np.arange(n) % 7 == 3, 2, 1),
                 np.full(n, 20))
    return Recording(imu, g)


def _same(a: Recording, b: Recording, imu_tol: float = 1e-9, dropped_first: bool = False) -> None:
    k = 1 if dropped_first else 0
    assert np.allclose(a.imu.t[k:], b.imu.t, rtol=0, atol=1e-6)
    assert np.allclose(a.imu.accel[k:], b.imu.accel, rtol=imu_tol, atol=imu_tol)
    assert np.allclose(a.imu.gyro[k:], b.imu.gyro, rtol=imu_tol, atol=imu_tol)
    assert np.allclose(a.gnss.t, b.gnss.t, atol=1e-6)
    assert np.allclose(a.gnss.llh[:, :2], b.gnss.llh[:, :2], atol=1e-10)
    assert np.allclose(a.gnss.llh[:, 2], b.gnss.llh[:, 2], atol=1e-4)
    assert np.allclose(a.gnss.sd_neu, b.gnss.sd_neu, atol=1e-4)
    assert np.array_equal(a.gnss.has_velocity, b.gnss.has_velocity)
    hv = a.gnss.has_velocity
    assert np.allclose(a.gnss.v_ned[hv], b.gnss.v_ned[hv], atol=1e-4)
    assert np.allclose(a.gnss.sd_v[hv], b.gnss.sd_v[hv], atol=1e-4)


def test_every_format_is_listed_with_what_its_path_is() -> None:
    assert set(FORMATS) == {"rtklib", "kf-gins", "csv", "ros2"}
    with pytest.raises(ValueError, match="unknown recording format"):
        load_recording("vhs", ".")


@pytest.mark.parametrize("velocity", [True, False])
def test_kf_gins_round_trip(tmp_path, velocity) -> None:
    rec = _recording(velocity=velocity)
    kfgins.write(rec, tmp_path)
    back = load_recording("kf-gins", tmp_path)
    # increments back to rates, the first line only starting the first interval
    _same(rec, Recording(back.imu, back.gnss), imu_tol=1e-9, dropped_first=True)
    assert np.all(back.gnss.quality == 1)  # the format has no solution type


def test_kf_gins_reads_the_i2nav_example(tmp_path) -> None:
    """Hand-written lines in the i2Nav layout: increments of 0.005 s, GNSS of 7 and commas."""
    imu = "\n".join(f"{357000.0 + 0.005 * k:.3f} 1e-5 -2e-5 3e-5 0.001 -0.002 -0.049" for k in range(200))
    (tmp_path / "ADIS16465_IMU.txt").write_text("# header\n" + imu + "\n")
    (tmp_path / "GNSS_RTK.txt").write_text("357000.0, 30.4446124, 114.4718243, 22.103, 0.005, 0.006, 0.008\n"
                                           "357001.0, 30.4446130, 114.4718250, 22.110, 0.005, 0.006, 0.008\n")
    rec = kfgins.load(tmp_path)
    assert len(rec.imu.t) == 199 and rec.imu.t[0] == pytest.approx(357000.005)
    assert rec.imu.gyro[0] == pytest.approx([2e-3, -4e-3, 6e-3])
    assert rec.imu.accel[0] == pytest.approx([0.2, -0.4, -9.8])
    assert rec.gnss.llh[0] == pytest.approx([math.radians(30.4446124), math.radians(114.4718243), 22.103])
    assert rec.gnss.sd_neu[0] == pytest.approx([0.005, 0.006, 0.008]) and not rec.gnss.has_velocity.any()
    (tmp_path / "GNSS_RTK.txt").write_text("357000.0 30.4 114.4 22.1 0.005 0.006\n")
    with pytest.raises(DatasetError, match=r"GNSS_RTK.txt:1: expected 7 or 13 values, got 6"):
        kfgins.load(tmp_path)
    (tmp_path / "more_gnss.txt").write_text("")
    with pytest.raises(DatasetError, match=r"exactly one \*gnss\*.txt, found 2"):
        kfgins.load(tmp_path)


@pytest.mark.parametrize("increments", [False, True])
def test_csv_round_trip(tmp_path, increments) -> None:
    rec = _recording()
    csv_columns.write(rec, tmp_path, increments=increments)
    back = load_recording("csv", tmp_path)
    _same(rec, back, imu_tol=1e-9, dropped_first=increments)
    assert np.array_equal(back.gnss.quality, rec.gnss.quality) and np.array_equal(back.gnss.n_sat, rec.gnss.n_sat)


def test_csv_takes_declared_units_and_empty_velocities(tmp_path) -> None:
    rows = "\n".join(f"{100 + 0.01 * k:.2f},1.0,0,0,{k % 3},0,0" for k in range(150))
    (tmp_path / "imu.csv").write_text("t_s,gz_dps,ax_g,ay_g,az_g,gx_dps,gy_dps\n" + rows + "\n")
    (tmp_path / "gnss.csv").write_text(
        "t_s,lat_deg,lon_deg,h_m,sdh_m,sdu_m,vn_mps,ve_mps,vd_mps,sdv_mps\n"
        "100.0,40.0,-105.0,1600.0,0.02,0.03,1.0,2.0,0.0,0.05\n"
        "100.25,40.0,-105.0,1600.0,0.02,0.03,,,,\n")
    rec = csv_columns.load(tmp_path)
    assert rec.imu.gyro[0] == pytest.approx([0.0, 0.0, math.radians(1.0)])
    assert rec.imu.accel[2] == pytest.approx([0.0, 0.0, 2 * G0])
    assert rec.gnss.has_velocity.tolist() == [True, False]
    assert rec.gnss.sd_neu[0] == pytest.approx([0.02, 0.02, 0.03]) and rec.gnss.sd_v[0] == pytest.approx([0.05] * 3)
    (tmp_path / "imu.csv").write_text("t_s,ax_furlong,ay_furlong,az_furlong,gx_dps,gy_dps,gz_dps\n1,2,3,4,5,6,7\n")
    with pytest.raises(DatasetError, match="ax, ay, az need one unit of mps2, g, mg"):
        csv_columns.load(tmp_path)
    (tmp_path / "imu.csv").write_text("t_s,ax_g,ay_g,az_g,gx_dps,gy_dps,gz_dps\n1,2,3,4,5,6,x\n")
    with pytest.raises(DatasetError, match=r"imu.csv:2: column gz_dps: not a number: 'x'"):
        csv_columns.load(tmp_path)
    (tmp_path / "gnss.csv").write_text("t_s,lat_deg,lon_deg\n1,2,3\n")
    with pytest.raises(DatasetError, match="missing column"):
        csv_columns.read_gnss(tmp_path / "gnss.csv")


@pytest.mark.parametrize("mcap", [False, True])
def test_ros2_bag_round_trip(tmp_path, mcap) -> None:
    rec = _recording(n_imu=200)
    ros2_bag.write(rec, tmp_path / "bag", mcap=mcap)
    back = load_recording("ros2", tmp_path / "bag")
    _same(rec, back)
    assert np.array_equal(back.gnss.quality == 1, rec.gnss.quality == 1)  # RTK fixed survives, the rest is code
    ros2_bag.write(rec, tmp_path / "pos", velocity=False)
    assert not load_recording("ros2", tmp_path / "pos").gnss.has_velocity.any()


def test_bad_bags_are_clear_errors(tmp_path) -> None:
    with pytest.raises(DatasetError, match="no such bag"):
        ros2_bag.load(tmp_path / "none")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"empty: not a ROS 2 bag folder \(no metadata.yaml in it\)"):
        ros2_bag.load(tmp_path / "empty")
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "metadata.yaml").write_text("this: [is not a bag")
    with pytest.raises(DatasetError, match="not a readable ROS 2 bag"):
        ros2_bag.load(tmp_path / "junk")


def _tag(start: float, last_tick: int) -> bytes:
    t_int = int(start)
    return (b"TIMETAG RTKLIB demo5".ljust(60, b"\0") + struct.pack("<IId", 0, t_int, start - t_int)
            + struct.pack("<II", last_tick, 0))


def test_rtklib_skips_a_truncated_first_line_and_a_converted_copy(tmp_path) -> None:
    """The raw log's first line may be cut mid-line (as its docstring says); a second
    ``imu_*_sf.csv`` beside it, without time tags, is not the raw log."""
    lines = [f"0.1,0.0,1.0,0.5,0,0,{10 * k}" for k in range(300)]
    (tmp_path / "imu_1.csv").write_text("1,0.0\n" + "\n".join(lines[1:]) + "\n0.1,0")
    (tmp_path / "imu_1.csv.tag").write_bytes(_tag(1000.0, 3000))
    (tmp_path / "imu_1_sf.csv").write_text("converted, other layout\n")
    pos = "% header\n" + "\n".join(
        f"2025/07/08 19:34:{18 + k}.000 40.0 -105.0 1600.0 1 20 0.01 0.01 0.02 0 0 0 0.0 0.0" for k in range(3))
    (tmp_path / "s.pos").write_text(pos + "\n")
    rec = load_drive(tmp_path)
    assert len(rec.imu.t) == 299 and rec.imu.accel[0] == pytest.approx([0.1 * G0, 0.0, G0])
    assert not rec.gnss.has_velocity.any()  # 15 fields: positions only
    (tmp_path / "imu_1.csv").write_text("\n".join(lines[:100] + ["0.1,0,x,0,0,0,5"] + lines[100:]) + "\n")
    with pytest.raises(DatasetError, match="malformed IMU CSV"):
        read_imu_csv(tmp_path / "imu_1.csv")
    assert read_pos(tmp_path / "s.pos").t[1] - read_pos(tmp_path / "s.pos").t[0] == pytest.approx(1.0)


@pytest.mark.slow
@pytest.mark.skipif(not SHARED_DRIVE.is_dir(), reason="shared drive not available")
def test_the_drive_in_every_format_scores_as_the_native_read(tmp_path) -> None:
    """#38 acceptance 3: the drive written as KF-GINS text, CSV and a ROS 2 bag scores within 2 %
    of the native read; its position-only copy is scored and printed beside."""
    from slcp.deploy.replay import ReplayConfig, run_replay
    from slcp.vehicles.profile import load_profile

    cfg = ReplayConfig(profile=load_profile(DRIVE_PROFILE))
    native = load_drive(SHARED_DRIVE)
    kfgins.write(native, tmp_path / "kf-gins")
    csv_columns.write(native, tmp_path / "csv", increments=True)
    ros2_bag.write(native, tmp_path / "ros2")
    keys = ("outage_h_rms_m", "outage_h_end_mean_m", "outage_h_max_m")
    ref = run_replay(native, cfg).metrics
    rows = {"rtklib": ref}
    for fmt in ("kf-gins", "csv", "ros2"):
        rows[fmt] = m = run_replay(load_recording(fmt, tmp_path / fmt), cfg).metrics
        for k in keys:
            assert m[k] == pytest.approx(ref[k], rel=0.02), (fmt, k)
    rows["position-only"] = run_replay(Recording(native.imu, native.gnss.position_only()), cfg).metrics
    assert rows["position-only"]["outage_h_rms_m"] < 1.5 * ref["outage_h_rms_m"]
    # the docs' table of these figures is what this test measures
    measured = {name: [f"{m[k]:.3f}" for k in keys] for name, m in rows.items()}
    assert _formats_table() == measured, "docs/recording-formats.md's table should read:\n" + "\n".join(
        f"{DOC_ROWS[name]} | " + " | ".join(v) + " |" for name, v in measured.items())


#: the rows of docs/recording-formats.md's table of the drive in every format, by the row's start
DOC_ROWS = {"rtklib": "| `rtklib` (native)", "kf-gins": "| `kf-gins`", "csv": "| `csv`", "ros2": "| `ros2`",
            "position-only": "| native, positions only"}


def _formats_table() -> dict[str, list[str]]:
    """The figures of docs/recording-formats.md's table, by format (the cells as written)."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "recording-formats.md").read_text()
    section = text.split("## The same drive in every format", 1)[1].split("\n## ", 1)[0]
    out = {}
    for line in section.splitlines():
        for name, start in DOC_ROWS.items():
            if line.startswith(start):
                out[name] = [c.strip() for c in line.strip().strip("|").split("|")[1:]]
    return out


def test_a_recording_without_reference_writes_its_trajectory_and_says_so(tmp_path, capsys) -> None:
    """Code-solution fixes are no reference for the filter they feed: the replay writes the
    trajectory and no accuracy figures."""
    import json

    from slcp.deploy.cli import main

    rng = np.random.default_rng(3)
    n = 3000  # 30 s standing at 100 Hz
    t = 500.0 + np.arange(n) * 0.01
    imu = imu_log(t, rng.normal(0, 0.01, (n, 3)) + [0, 0, -G0], rng.normal(0, 1e-3, (n, 3)))
    tg = 500.0 + np.arange(0.0, 30.0, 1.0)
    g = gnss_log(tg, np.full(len(tg), 40.0), np.full(len(tg), -105.0), np.full(len(tg), 1600.0),
                 np.full((len(tg), 3), 2.0), quality=np.full(len(tg), 5))
    csv_columns.write(Recording(imu, g), tmp_path / "rec")
    assert main(["replay", "csv", str(tmp_path / "rec"), "--out", str(tmp_path / "out"), "--no-outage"]) == 0
    out = capsys.readouterr().out
    assert "no reference, only 0 % of the fixes are RTK-fixed" in out and "outage horizontal RMS" not in out
    rows = (tmp_path / "out" / "trajectory.csv").read_text().splitlines()
    assert len(rows) > 200 and rows[0].startswith("time_gpst_s,")
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["reference"] is False and m["reference_share"] == 0.0
