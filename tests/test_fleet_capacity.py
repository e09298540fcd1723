"""The fleet's performance targets and the search for the largest fleet within them (stubs stand
for the fleet runs: what is tested is the verdict and the search, not this machine)."""

from __future__ import annotations

import json

import pytest

from slcp.deploy.fleet_capacity import BEACON_P99_MAX_MS, REALTIME_MIN, RSS_MAX_MB, capacity_search, missed_targets


def _point(n: int, rtf: float = 1.0, p99: float = 5.0, dropped: int = 0, rss: float = 75.0) -> dict:
    """A fleet point with every figure ``slcp bench`` prints."""
    return {"agents": n, "realtime_factor": rtf, "beacon_latency_ms": {"p50": 1.0, "p99": p99, "n": 100},
            "sensor_dropped": dropped, "rss_mb_per_agent": {"mean": rss - 1.0, "max": rss},
            "method": "SL-CP", "fusion": "source-ci", "zenoh_mode": "client", "imu_batch": 20, "lag_p99_s": 0.5,
            "cpu_pct_per_agent": {"mean": 4.0, "max": 5.0}, "threads_per_agent": 5, "emulator_cpu_pct": 10.0,
            "launcher_cpu_pct": 10.0, "machine_cpu_pct": 4.0 * n + 20.0}


def test_a_point_meets_the_targets_or_says_what_it_misses() -> None:
    assert missed_targets(_point(10)) == []
    assert missed_targets(_point(10, rtf=REALTIME_MIN, p99=BEACON_P99_MAX_MS - 0.1, rss=RSS_MAX_MB)) == []
    assert missed_targets(_point(10, rtf=0.9)) == ["real-time factor 0.90 below 0.97"]
    assert missed_targets(_point(10, p99=20.0)) == ["beacon p99 20 ms, not below 20"]
    assert missed_targets(_point(10, dropped=3)) == ["3 sensor samples dropped"]
    assert missed_targets(_point(10, rss=80.5)) == ["peak RSS 80 MB above 80"]
    assert len(missed_targets(_point(10, rtf=0.5, p99=900.0, dropped=1, rss=99.0))) == 4
    assert missed_targets({"agents": 3, "error": "the fleet never ran"}) == ["the fleet never ran"]
    nothing = {"agents": 3, "realtime_factor": None, "beacon_latency_ms": None, "sensor_dropped": 0,
               "rss_mb_per_agent": None}
    assert missed_targets(nothing) == ["real-time factor None below 0.97", "no beacon delivered",
                                       "no agent's RSS measured"]


def _machine(capacity: int):
    """A machine that holds ``capacity`` agents: the run of more misses the beacon latency."""
    runs: list[int] = []

    def run(n: int) -> dict:
        runs.append(n)
        return _point(n, p99=5.0 if n <= capacity else 500.0)
    return run, runs


@pytest.mark.parametrize(("capacity", "start", "most", "found", "first_missed", "runs"), [
    (27, 10, 100, 25, 30, [10, 20, 40, 30, 25]),        # doubled, then bisected to within 5
    (33, 10, 100, 30, 35, [10, 20, 40, 30, 35]),
    (500, 10, 100, 100, None, [10, 20, 40, 80, 100]),    # the cap meets them: nothing missed
    (3, 10, 100, 2, 5, [10, 5, 2]),                     # the start misses them: halved first
    (0, 10, 100, 0, 1, [10, 5, 2, 1]),                  # not even one agent
    (10, 10, 10, 10, None, [10]),
])
def test_the_search_finds_the_largest_count_that_meets_the_targets(capacity, start, most, found, first_missed,
                                                                    runs) -> None:
    run, seen = _machine(capacity)
    out = capacity_search(run, start=start, most=most, resolution=5)
    assert out["capacity"] == found and out["first_missed"] == first_missed
    assert seen == runs and [p["agents"] for p in out["points"]] == runs
    assert all((p["missed"] == []) == (p["agents"] <= capacity) for p in out["points"])
    if first_missed is not None:  # the two counts it reports bracket the machine's capacity
        assert found <= capacity < first_missed and first_missed - found <= 5


def test_the_search_refuses_a_range_it_cannot_search() -> None:
    for kw in ({"start": 0}, {"start": 20, "most": 10}, {"resolution": 0}):
        with pytest.raises(ValueError, match="capacity search"):
            capacity_search(lambda n: _point(n), **kw)


def test_slcp_bench_reports_the_capacity_and_each_points_verdict(capsys, monkeypatch) -> None:
    from slcp.deploy import bench, fleet_bench
    from slcp.deploy.cli import main
    from slcp.deploy.commands.lab import FLEET_POINT_STEPS

    run, seen = _machine(27)
    monkeypatch.setattr(fleet_bench, "run_fleet_point", lambda n, *a, **k: run(n))
    monkeypatch.setattr(bench, "micro_benchmarks", lambda quick=False: {k: 1.0 for k in (*FLEET_POINT_STEPS,
                                                                                          "imu_step_us")})
    assert main(["bench", "--quick", "--json", "--drive", "/nonexistent", "--fleet-capacity"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["capacity"] == {"capacity": 25, "first_missed": 30}
    assert [p["agents"] for p in out["fleet"]] == [10, 20, 40, 30, 25] and out["fleet"][2]["missed"]
    seen.clear()
    assert main(["bench", "--quick", "--drive", "/nonexistent", "--fleet-capacity", "20:30"]) == 0
    text = capsys.readouterr().out
    assert seen == [20, 30, 25]
    assert "    performance targets: met" in text and "    performance targets: missed: beacon p99 500 ms" in text
    assert "  capacity: 25 agents meet the targets" in text and "; 30 did not" in text
    for bad in ("0:10", "20:10", "x"):
        assert main(["bench", "--quick", "--drive", "/nonexistent", "--fleet-capacity", bad]) == 2
        assert "START:MOST" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # one or the other
        main(["bench", "--fleet", "10", "--fleet-capacity"])
