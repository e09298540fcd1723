"""The fleet benchmark's parts: the grid scenario and the monitor's bookkeeping (the benchmark
itself prints figures and is not a test)."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import time

import numpy as np
import pytest

from slcp.deploy.fleet_bench import FleetMonitor, _proc_cpu_s, _proc_peak_rss_mb
from slcp.hw_emulation.grid import grid_scenario_toml
from slcp.hw_emulation.scenario import load_scenario
from slcp.transport import keys
from slcp.transport.bus import InMemoryNetwork
from slcp.transport.codec import encode
from slcp.transport.messages import GnssFix


def test_the_grid_has_the_vehicles_and_at_most_seven_neighbours_each(tmp_path) -> None:
    p = tmp_path / "grid.toml"
    p.write_text(grid_scenario_toml(19, duration=20.0))
    scn = load_scenario(p)
    assert len(scn.vehicles) == 19 and scn.duration == 20.0
    assert scn.radio.latency_max == 0.0 and scn.radio.stale_prob == 0.0
    from slcp.hw_emulation.truth import build_truth

    truth = build_truth(scn)
    ids = sorted(truth.vehicles)
    import pymap3d

    llh = np.stack([truth.vehicles[v].truth.llh for v in ids])  # (vehicles, time, 3)
    ne = np.stack(pymap3d.geodetic2ned(llh[..., 0], llh[..., 1], llh[..., 2], *llh[0, 0], deg=False)[:2], axis=-1)
    d = np.linalg.norm(ne[:, None] - ne[None, :], axis=-1)  # (v, v, time)
    in_range = (d < max(scn.radio.max_range, scn.uwb.max_range)).any(axis=-1)
    np.fill_diagonal(in_range, False)
    assert in_range.sum(axis=1).max() <= 7
    for bad in ((0,), (10, 0.0), (10, 20.0, 9)):
        with pytest.raises(ValueError):
            grid_scenario_toml(*bad)


@pytest.mark.parametrize(("stagger", "batch"), [(True, 10), (False, 10), (True, 20)])
def test_staggered_imu_batches_end_at_evenly_spread_phases(tmp_path, stagger, batch) -> None:
    from slcp.hw_emulation.service import EmulatorService
    from slcp.hw_emulation.truth import build_truth

    p = tmp_path / "grid.toml"
    p.write_text(grid_scenario_toml(5, duration=3.0, imu_stagger=stagger, imu_batch=batch))
    truth = build_truth(load_scenario(p))

    async def events():
        emu = EmulatorService(truth, InMemoryNetwork().bus(), seed=0)
        return emu, emu._events()

    emu, ev = asyncio.run(events())
    ends = {}
    for _t, _, kind, who, idx in ev:
        if kind == "imu":
            ends.setdefault(who, []).append(idx)
    # every vehicle gets whole batches (the scenario's imu_batch); staggered, vehicle k's end
    # k*batch//5 samples later
    assert emu.batch == batch and all(np.all(np.diff(v) == batch) for v in ends.values())
    first = [ends[v][0] for v in emu.ids]
    assert first == ([batch + k * batch // 5 for k in range(5)] if stagger else [batch] * 5)


def test_the_monitor_pairs_deliveries_with_publications_and_reads_proc() -> None:
    class Rec:
        latest_t = {"G0": -4.0, "G1": -4.0}  # 4 s behind the clock when sampled first
        diag = {"G0": (0.0, {"seq_late_dropped": 3, "queue_dropped_imu": 1}, {}), "G1": (0.0, {}, {})}

    class Proc:
        pid = os.getpid()

    async def main():
        net = InMemoryNetwork()
        bus = net.bus()
        mon = FleetMonitor(["G0", "G1"])
        mon.attach(bus, {"agent-G0": Proc()})
        # the 1x clock, from G0's fixes: sensor time 0 now (a late fix and junk do not move it)
        fix = GnssFix("G0", 0, 0.0, np.zeros(3), np.zeros(3), np.ones(3), 0.1)
        await bus.publish(keys.gnss("G0"), encode(fix))
        await asyncio.sleep(0.01)
        await bus.publish(keys.gnss("G0"), encode(dataclasses.replace(fix, t=-1.0)))
        await bus.publish(keys.gnss("G0"), b"junk")
        await bus.publish(keys.radio_tx("G0"), b"beacon-1")
        await asyncio.sleep(0.02)
        await bus.publish(keys.radio_rx("G1"), b"beacon-1")
        await bus.publish(keys.radio_rx("G1"), b"never-sent")
        mon.sample(Rec())
        for _ in range(3):
            sum(i * i for i in range(200_000))  # some CPU time to measure
            mon._next = 0.0
            Rec.latest_t = {v: t + 1.0 for v, t in Rec.latest_t.items()}
            time.sleep(0.75)
            mon.sample(Rec())
        return mon.result()

    res = asyncio.run(main())
    assert res["beacon_latency_ms"]["n"] == 1 and 15 <= res["beacon_latency_ms"]["p50"] < 500
    assert res["beacons_unmatched"] == 1
    assert res["sensor_dropped"] == 4
    assert 0.5 < res["realtime_factor"] < 2.0
    # at the end (about 2.3 s of wall time) the agents' newest estimates are at -1.0 s
    assert 3.0 < res["lag_p99_s"] < 4.5
    assert res["rss_mb_per_agent"]["max"] > 10 and res["cpu_pct_per_agent"]["max"] > 0
    assert res["launcher_cpu_pct"] > 0 and res["threads_per_agent"] >= 1  # the "agent" is this process
    assert _proc_cpu_s(2**22 + 12345) is None and _proc_peak_rss_mb(2**22 + 12345) is None


def test_the_monitor_reports_each_window_of_the_steady_part() -> None:
    """Machine CPU and beacon p99 per WINDOW_S: a busy middle window stands out of the average."""
    from slcp.deploy.fleet_bench import WINDOW_S

    mon = FleetMonitor(["G0"])
    # 1 s samples over 16 s: two processes, the agent busy (1.9 cores in all) from 5 to 10 s
    cpu = {"agent-G0": 0.0, "emulator": 0.0}
    for k in range(17):
        mon.points.append((100.0 + k, dict(cpu)))
        busy = 5 <= k < 10
        cpu = {"agent-G0": cpu["agent-G0"] + (1.8 if busy else 0.5), "emulator": cpu["emulator"] + 0.1}
    rng = np.random.default_rng(0)
    t_pub = 100.0 + np.sort(rng.uniform(0.0, 16.0, 3000))
    lat = np.where((t_pub >= 105.0) & (t_pub < 110.0), 0.2, 0.002) * rng.uniform(0.5, 1.0, t_pub.size)
    mon.latency_t, mon.latencies = list(t_pub), list(lat)
    w = mon._windows(np.array(mon.latencies) * 1e3)
    rows = w["windows"]
    assert [r["t_s"] for r in rows] == [0.0, WINDOW_S, 2 * WINDOW_S]  # the 1 s tail is left out
    assert [round(r["machine_cpu_pct"]) for r in rows] == [60, 190, 60]
    assert sum(r["n"] for r in rows) == np.count_nonzero(t_pub < 115.0)
    assert rows[1]["beacon_p99_ms"] > 150 and rows[0]["beacon_p99_ms"] < 2.5 and rows[2]["beacon_p99_ms"] < 2.5
    assert w["machine_cpu_pct_peak"] == rows[1]["machine_cpu_pct"]
    assert w["beacon_p99_ms_worst_window"] == rows[1]["beacon_p99_ms"]
