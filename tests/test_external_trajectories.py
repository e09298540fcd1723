"""External trajectories: SUMO FCD and CSV import, smoothing of 1 Hz input, sane IMU, truth
consistency, and clear errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slcp.geo import earth
from slcp.hw_emulation.external import TrajectoryError, read_csv_tracks, read_sumo_fcd, truth_from_tracks

from conftest import mechanization_drift

ORIGIN = (math.radians(39.9552), math.radians(116.3194), 50.0)
RADIUS = 20.0


def _turning_track(rate: float = 1.0):
    """East at 10 m/s for 200 m, a 90° left turn (radius 20 m) to north, north until t = 41 s,
    braking at 2.5 m/s² to a stop at 45 s, standing still until 60 s."""
    t = np.arange(0.0, 60.0 + 1e-9, 1.0 / rate)
    turn_len = math.pi / 2 * RADIUS
    pts = []
    for tk in t:
        tb = min(max(tk - 41.0, 0.0), 4.0)
        d = 10.0 * min(tk, 41.0) + 10.0 * tb - 1.25 * tb * tb
        if d <= 200.0:
            pts.append((0.0, d))
        elif d <= 200.0 + turn_len:
            a = (d - 200.0) / RADIUS
            pts.append((RADIUS * (1 - math.cos(a)), 200.0 + RADIUS * math.sin(a)))
        else:
            pts.append((RADIUS + d - 200.0 - turn_len, 200.0 + RADIUS))
    return t, np.array(pts)


def _write_fcd(path, t, ne, vid="veh0") -> None:
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<fcd-export>"]
    for tk, (n, e) in zip(t, ne):
        lines.append(f'  <timestep time="{tk:.2f}">')
        lines.append(f'    <vehicle id="{vid}" x="{e:.2f}" y="{n:.2f}" angle="0.00" type="car" speed="10.00"/>')
        lines.append("  </timestep>")
    lines.append("</fcd-export>")
    path.write_text("\n".join(lines))


@pytest.fixture(scope="module")
def fcd_truth(tmp_path_factory):
    p = tmp_path_factory.mktemp("fcd") / "small.fcd.xml"
    t, ne = _turning_track(1.0)
    _write_fcd(p, t, ne)
    tracks = read_sumo_fcd(p)
    return tracks, truth_from_tracks(tracks, ORIGIN)


def test_sumo_fcd_1hz_gives_sane_imu(fcd_truth) -> None:
    tracks, truths = fcd_truth
    assert list(tracks) == ["veh0"] and len(tracks["veh0"].t) == 61
    tr = truths["veh0"]
    dt = np.diff(tr.t)[:, None]
    w = tr.dtheta / dt
    f = tr.dvel / dt
    # yaw rate peaks near v/R = 0.5 rad/s; no spikes from the 1 Hz sampling
    assert 0.3 < np.abs(w[:, 2]).max() < 0.8
    # horizontal specific force bounded by v^2/R = 5 m/s^2 plus margin, vertical ~ -g
    assert np.hypot(f[:, 0], f[:, 1]).max() < 7.0
    assert np.all(np.abs(f[:, 2] + 9.8) < 0.1)
    # smoothed path stays within a metre of the input geometry; the end is standing still
    llh_end = tr.llh[-1]
    ne_end = earth.ned_offset(*llh_end, *ORIGIN)[:2]
    assert np.linalg.norm(ne_end - tracks["veh0"].ne[-1]) < 1.0
    assert np.linalg.norm(tr.v_ned[-1]) < 0.05


def test_external_truth_is_consistent_with_mechanisation(fcd_truth) -> None:
    _, truths = fcd_truth
    _, worst = mechanization_drift(truths["veh0"])
    assert worst < 0.05


def test_csv_tracks(tmp_path) -> None:
    t, ne = _turning_track(2.0)
    p = tmp_path / "tracks.csv"
    rows = ["time_s,vehicle_id,north_m,east_m"] + [f"{tk},A,{n},{e}" for tk, (n, e) in zip(t, ne)]
    rows += [f"{tk},B,{-n},{e}" for tk, (n, e) in zip(t[::-1], ne[::-1])]  # any row order
    p.write_text("\n".join(rows))
    tracks = read_csv_tracks(p)
    assert set(tracks) == {"A", "B"} and np.all(np.diff(tracks["B"].t) > 0)


def test_bad_trajectory_files(tmp_path) -> None:
    p = tmp_path / "bad.csv"
    p.write_text("time,id,x\n1,2,3\n")
    with pytest.raises(TrajectoryError, match="header must contain"):
        read_csv_tracks(p)
    p.write_text("time_s,vehicle_id,north_m,east_m\n0,A,1,2\n1,A,x,2\n")
    with pytest.raises(TrajectoryError, match=r"bad.csv:3"):
        read_csv_tracks(p)
    p.write_text("time_s,vehicle_id,north_m,east_m\n0,A,1,2\n1,A,1,2\n")
    with pytest.raises(TrajectoryError, match="need >= 4"):
        read_csv_tracks(p)
    x = tmp_path / "bad.xml"
    x.write_text("<fcd-export><timestep time='0'><vehicle id='a' x='1'")
    with pytest.raises(TrajectoryError, match="not valid FCD XML"):
        read_sumo_fcd(x)
    with pytest.raises(TrajectoryError, match="cannot read"):
        read_sumo_fcd(tmp_path / "missing.xml")
