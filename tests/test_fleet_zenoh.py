"""End to end over real Zenoh on 127.0.0.1 with separate processes: `slcp run paper-1` starts
the emulator and three agents, beacons flow, ranges are fused, the run directory is written,
and no process is left behind."""

from __future__ import annotations

import json
import os
import subprocess

import pytest

from slcp.deploy.launcher import run_fleet

from conftest import short_scenario

pytestmark = [pytest.mark.fleet, pytest.mark.slow]


@pytest.mark.timeout(400)
def test_slcp_run_paper_1_over_zenoh(tmp_path) -> None:
    from foxglove_client import FoxgloveClient

    from conftest import free_port

    out = tmp_path / "run"
    port = free_port()
    fix_topics = [f"/slcp/{v}/SL_CP/fix" for v in ("V0", "V1", "V2")]
    client = FoxgloveClient(port, seconds=120.0, until=lambda c: all(
        len(c.messages.get(t, [])) >= 100 for t in fix_topics) and len(c.messages.get("/slcp/diagnostics", [])) >= 6)
    client.start()
    m = run_fleet("paper-1", out=out, seed=0, foxglove_port=port)
    client.join(10)
    assert m["processes"]["exit_codes"] == {"agent-V0": 0, "agent-V1": 0, "agent-V2": 0, "emulator": 0}
    # the agents are Zenoh clients of the launcher's router (no peer mesh)
    assert 'mode = "client"' in (out / "config" / "agent-V1.toml").read_text()
    with pytest.raises(ValueError, match="zenoh_mode"):
        run_fleet("paper-1", out=tmp_path / "mesh", zenoh_mode="mesh")
    for name in ("metrics.json", "report.md", "recorded/messages.jsonl", "estimates/V1.csv", "logs/emulator.log",
                 "errors.png", "map.png"):
        assert (out / name).exists(), name
    diag = m["diagnostics"]
    for vid in ("V0", "V1", "V2"):
        d = diag[vid]
        assert d["beacons_rx"] > 100 and d["beacons_tx"] > 100
        # V0 has the fewest ranges, about 240: it turns away from the queue it ranges with
        assert d["CP_ranges"] >= 1 and d["CP_ranges"] + d["CP_ranges_skipped"] + d["CP_ranges_skipped_near"] > 150
        assert d["codec_errors"] == 0
    assert m["rmse"]["t_s1-t_e"]["V1"]["SL-SP"]["n"] > 100
    # the first stopped vehicle was found over the network, the one behind it never claimed
    recs = [json.loads(line) for line in (out / "recorded/messages.jsonl").read_text().splitlines()]
    est = [r for r in recs if r["type"] == "Estimate"]
    assert any(r["first_stopped"] for r in est if r["vehicle"] == "V1")
    assert not any(r["first_stopped"] for r in est if r["vehicle"] == "V2")
    # detection and consistency in the metrics; the report rebuilds from the recording alone
    assert m["first_stopped"]["V1"]["SL-SP"]["precision"] == 1.0
    assert m["first_stopped"]["V1"]["SL-SP"]["sl_rmse_claimed_m"] < 0.3
    cell = m["rmse"]["t_s1-t_e"]["V2"]["SL-CP"]
    assert 0.0 < cell["bound_rms_m"] < m["rmse"]["t_s1-t_e"]["V2"]["SP"]["bound_rms_m"]
    (out / "metrics.json").unlink()
    from slcp.deploy.cli import main

    assert main(["report", str(out)]) == 0
    again = json.loads((out / "metrics.json").read_text())
    assert again["rmse"]["t_s1-t_e"]["V1"]["SL-SP"]["rmse_m"] == pytest.approx(
        m["rmse"]["t_s1-t_e"]["V1"]["SL-SP"]["rmse_m"]
    )
    _the_bag_holds_the_recording(out, m, recs)
    _foxglove_saw_the_fleet_live(client, recs)
    # no process left behind
    ps = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True)
    assert ps.stdout.strip() == ""


def _the_bag_holds_the_recording(out, m, recs) -> None:
    """#44 acceptance 1: the run's ROS 2 bag (MCAP) holds per topic what the launcher counted,
    a decoded estimate equals the recorded one, and the report made from the bag alone is the
    report made from the JSON lines."""
    import numpy as np

    from slcp.deploy.cli import main
    from slcp.deploy.mcap_recording import read_recording, topic_name

    bag = out / "recorded" / "bag"
    est, diags, counts = read_recording(bag)
    by_key = m["processes"]["recorded_by_key"]
    assert sorted(f"slcp/v1/estimate/{v}/{meth}" for v, meth in est) == sorted(k for k in by_key if "/estimate/" in k)
    for (v, meth), rows in est.items():
        n = by_key[f"slcp/v1/estimate/{v}/{meth}"]
        assert counts[topic_name(v, meth, "fix")] == counts[topic_name(v, meth, "odom")] == len(rows) == n
    assert counts["/slcp/diagnostics"] == sum(n for k, n in by_key.items() if "/diag/" in k)
    assert set(diags) == {"V0", "V1", "V2", "emulator"}
    # the truth at 10 Hz over the 50 s scenario, and the site once
    assert all(counts[f"/slcp/{v}/truth/fix"] == counts[f"/slcp/{v}/truth/odom"] == 501 for v in ("V0", "V1", "V2"))
    assert counts["/slcp/site"] == 1
    from mcap.reader import make_reader

    with open(next(bag.glob("*.mcap")), "rb") as fh:  # the MCAP library's own reader: the same
        stats = make_reader(fh).get_summary().statistics
    assert stats.message_count == sum(counts.values())
    jsonl = [r for r in recs if r["type"] == "Estimate" and (r["vehicle"], r["method"]) == ("V1", "SL-CP")]
    for a, b in zip(jsonl, est[("V1", "SL-CP")], strict=True):
        assert b["t"] == pytest.approx(a["t"], abs=1e-9) and b["first_stopped"] == a["first_stopped"]
        np.testing.assert_allclose(b["llh"], a["llh"], rtol=0, atol=1e-13)
        np.testing.assert_allclose(b["cov_pos"], a["cov_pos"], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(b["v_ned"], a["v_ned"], rtol=0, atol=1e-12)
    before = json.loads((out / "metrics.json").read_text())
    # the same to a micrometre: a bag's stamps are whole nanoseconds and its latitudes degrees
    (out / "recorded" / "messages.jsonl").rename(out / "messages.jsonl.aside")
    assert main(["report", str(out)]) == 0
    after = json.loads((out / "metrics.json").read_text())
    for window, cells in before["rmse"].items():
        for v, per_method in cells.items():
            for meth, cell in per_method.items():
                assert after["rmse"][window][v][meth]["rmse_m"] == pytest.approx(cell["rmse_m"], rel=1e-6, abs=1e-6)
    # the claims' times come back to the nanosecond (the bag's stamps)
    assert _flat(after["first_stopped"]) == pytest.approx(_flat(before["first_stopped"]), rel=1e-9, abs=1e-6)


def _foxglove_saw_the_fleet_live(client, recs) -> None:
    """#44 acceptance 3: a Foxglove WebSocket client connected during the run received every
    vehicle's estimates live, with their schema, moving, and equal to what was recorded."""
    import math

    from foxglove_client import protobuf_doubles

    assert client.error is None, client.error
    topics = client.topics()
    recorded = {(r["vehicle"], round(r["t"], 6)): r for r in recs if r["type"] == "Estimate" and r["method"] == "SL-CP"}
    for v in ("V0", "V1", "V2"):
        assert topics[f"/slcp/{v}/SL_CP/fix"]["schemaName"] == "foxglove.LocationFix"
        got = client.messages[f"/slcp/{v}/SL_CP/fix"]
        times = [t for t, _ in got]
        assert times == sorted(times) and len(set(times)) == len(times) >= 100
        fields = [protobuf_doubles(p) for _, p in got]
        lat, lon = [f[1][0] for f in fields], [f[2][0] for f in fields]
        for (t, _), la, lo in zip(got, lat, lon, strict=True):
            llh = recorded[(v, round(t / 1e9, 6))]["llh"]
            assert (la, lo) == pytest.approx((math.degrees(llh[0]), math.degrees(llh[1])), abs=1e-12)
        if v == "V0":  # driving through the junction while the client watched
            moved = math.hypot(lat[-1] - lat[0], (lon[-1] - lon[0]) * math.cos(math.radians(lat[0]))) * 111_000
            assert moved > 20.0
    assert topics["/slcp/diagnostics"]["schemaName"] == "slcp.Diagnostics"


def _flat(d, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}/"))
        elif isinstance(v, (int, float)) and v is not None:
            out[f"{prefix}{k}"] = v
    return out


@pytest.mark.timeout(150)
@pytest.mark.parametrize(("extra", "up"), [([], 2), ([], 4), (["--seeds", "3", "--jobs", "1"], 4)],
                         ids=["run-while-starting", "run", "study"])
def test_sigterm_to_the_launcher_stops_every_child(tmp_path, extra, up) -> None:
    """SIGTERM once ``up`` processes name the run directory: 2 = the launcher and its first agent
    (the signal lands while the other children are being started), 4 = the launcher and every agent."""
    import signal
    import sys
    import time

    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "run", "paper-1", "--out", str(out), *extra],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            ps = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
            if len(ps) >= up:
                break
            time.sleep(0.05)
        assert len(ps) >= up, "the fleet did not start"
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=60) != 0
        time.sleep(0.5)
        left = subprocess.run(["pgrep", "-af", str(out)], capture_output=True, text=True).stdout.strip()
        assert left == "", left
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        subprocess.run(["pkill", "-KILL", "-f", str(out)], check=False)  # whatever a failure left


def test_a_termination_signal_while_a_child_starts_still_leaves_it_to_be_stopped(monkeypatch) -> None:
    """The signal arrives inside ``Popen`` (after the fork): the child must still be entered in the
    process table, and the interruption must come after that."""
    import signal
    import sys

    from slcp.deploy import supervisor

    real_popen = subprocess.Popen

    def popen_then_signal(*args, **kwargs):
        p = real_popen(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)  # as if the launcher were killed at this instant
        return p

    monkeypatch.setattr(supervisor.subprocess, "Popen", popen_then_signal)
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    procs: dict = {}
    try:
        supervisor.interrupt_on_termination()
        with pytest.raises(KeyboardInterrupt):
            supervisor._spawn(procs, "sleeper", [sys.executable, "-c", "import time; time.sleep(60)"],
                              subprocess.DEVNULL)
        assert "sleeper" in procs and procs["sleeper"].poll() is None
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
        supervisor._stop_all(procs, grace=5.0)
    assert procs["sleeper"].returncode is not None


def _emulator_replaced(monkeypatch, command) -> None:
    """Make the launcher start ``command(emulator_argv)`` (an argv) in place of the emulator."""
    from slcp.deploy import supervisor

    real = supervisor._slcp
    monkeypatch.setattr(supervisor, "_slcp", lambda *a: command(real(*a)) if "emulate" in a else real(*a))


@pytest.mark.timeout(200)
def test_an_emulator_that_does_not_exit_after_the_scenario_is_killed_and_the_run_completes(
        tmp_path, monkeypatch) -> None:
    """The emulator plays paper-1 and then hangs instead of exiting (as one was seen to, once in
    a few runs, after its Zenoh session closed): the launcher kills it after its grace and
    evaluates the run."""
    import functools
    import sys

    from slcp.deploy import launcher

    hang_after = "import sys, time; from slcp.deploy.cli import main; main(sys.argv[1:]); time.sleep(600)"
    _emulator_replaced(monkeypatch, lambda argv: [sys.executable, "-c", hang_after, *argv[3:]])
    monkeypatch.setattr(launcher, "_supervise", functools.partial(launcher._supervise, exit_grace_s=3.0))
    out = tmp_path / "run"
    try:
        m = run_fleet(str(short_scenario(tmp_path, "paper-1", 25.0)), out=out, seed=0, methods=("SP", "CP"))
        assert m["processes"]["emulator_killed_at_end"] is True
        # where it hung is in its log: SIGUSR1 before the kill dumps its Python stacks
        assert "most recent call first" in (out / "logs" / "emulator.log").read_text()
        assert m["processes"]["restarts"] == []
        assert m["processes"]["exit_codes"]["emulator"] == -9
        assert all(c == 0 for n, c in m["processes"]["exit_codes"].items() if n != "emulator")
        # evaluated as usual, on estimates to the scenario's end
        rows = m["rmse"]["t_s1-t_e"]
        assert sorted(rows) == ["V0", "V1", "V2"]
        assert all(0.0 < rows[v][k]["rmse_m"] < 10.0 for v in rows for k in ("SP", "CP"))
        last = max(json.loads(x)["t"] for x in (out / "recorded" / "messages.jsonl").read_text().splitlines())
        assert last > 24.0
        left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
        assert left == [], left
    finally:
        subprocess.run(["pkill", "-KILL", "-f", str(out)], check=False)


@pytest.mark.timeout(120)
def test_a_silent_emulator_is_killed_and_restarted_then_given_up(tmp_path, monkeypatch) -> None:
    """An emulator that never publishes is treated as hung: killed and restarted once; when the
    resumed one hangs at the same point the run fails with a clear error instead of repeating
    the restart (each one costs the watchdog's whole timeout)."""
    import functools
    import sys
    import time

    from slcp.deploy import launcher

    _emulator_replaced(monkeypatch, lambda argv: [sys.executable, "-c", "import time; time.sleep(600)", *argv])
    # up to three restarts allowed, but the resumed emulator fails at the same point (t = 0)
    # again, so the launcher stops after the first resume instead of repeating it
    monkeypatch.setattr(launcher, "_supervise", functools.partial(launcher._supervise, stall_s=2.0, max_restarts=3))
    out = tmp_path / "run"
    t0 = time.monotonic()
    try:
        with pytest.raises(
            RuntimeError, match=r"resumed at t=0\.00 s was killed after \d+ s of silence.*not restarted again"
        ):
            run_fleet("paper-1", out=out, seed=0, methods=("SP",), wait_agents=1.0, evaluate=False)
        assert time.monotonic() - t0 < 60.0
        left = subprocess.run(["pgrep", "-f", str(out)], capture_output=True, text=True).stdout.split()
        assert left == [], left
    finally:
        subprocess.run(["pkill", "-KILL", "-f", str(out)], check=False)
