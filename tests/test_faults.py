"""Fault injection on a real fleet (separate processes, Zenoh on 127.0.0.1): an agent killed with
SIGKILL in the middle of the run is restarted by the launcher and rejoins; its neighbours see it go
(liveliness or beacon silence) within 2 s of sensor time and stop using it; the recording loses nothing."""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import free_port, run_group, short_scenario, wait_for_port

pytestmark = [pytest.mark.fleet, pytest.mark.slow]


def _t_of(line: str) -> float | None:
    """A recorded message's sensor time, None for a line the recorder is still writing."""
    try:
        return float(json.loads(line)["t"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError):
        return None


@pytest.mark.timeout(240)
def test_an_agent_killed_with_sigkill_is_restarted_and_rejoins(tmp_path) -> None:
    out = tmp_path / "run"
    scn = short_scenario(tmp_path, "paper-1", 25.0)
    p = subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "run", str(scn), "--out", str(out)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        rec = out / "recorded" / "messages.jsonl"
        deadline = time.monotonic() + 90
        victim = None
        while time.monotonic() < deadline and victim is None:  # kill V2 once it has run ~8 s of sensor time
            time.sleep(0.2)
            if rec.exists():
                ts = [_t_of(x) for x in rec.read_text().splitlines()[-200:] if '"Estimate"' in x and '"V2"' in x]
                ts = [t for t in ts if t is not None]
                if ts and max(ts) > 8.0:
                    pid = subprocess.run(["pgrep", "-f", f"agent --vehicle V2 --config {out}"],
                                         capture_output=True, text=True).stdout.split()
                    victim = int(pid[0])
        assert victim is not None, "V2 never got going"
        os.kill(victim, signal.SIGKILL)
        assert p.wait(timeout=150) == 0
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            # the launcher's children run in their own sessions: end them too
            subprocess.run(["pkill", "-KILL", "-f", str(out)], check=False)
    m = json.loads((out / "metrics.json").read_text())
    restarts = m["processes"]["restarts"]
    print("restarts:", restarts)
    assert len(restarts) == 1 and restarts[0]["process"] == "agent-V2" and restarts[0]["exit_code"] == -9
    # rejoined, not stuck: the bound is not a speed target (alone a restart is back within 2 s;
    # beside the suite's 38-agent SUMO fleet test one took 8 s)
    assert restarts[0]["rejoined_after_s"] is not None and restarts[0]["rejoined_after_s"] < 15.0
    lines = [json.loads(x) for x in (out / "recorded" / "messages.jsonl").read_text().splitlines()]
    v2 = sorted(d["t"] for d in lines if d["type"] == "Estimate" and d["vehicle"] == "V2" and d["method"] == "CP")
    gaps = [(a, b) for a, b in zip(v2, v2[1:]) if b - a > 0.15]  # 10 Hz estimates; the clock waits for V2
    assert len(gaps) == 1, gaps  # the one outage, and V2 estimates again after it
    last_before = gaps[0][0]
    for v in ("V0", "V1"):
        diags = [d for d in lines if d["type"] == "Diagnostics" and d["source"] == v]
        gone = [(t, how) for t, who, how in diags[-1]["status"]["departures"] if who == "V2" and t < gaps[0][1]]
        assert gone, f"{v} never noticed V2 leave"
        # the departure that the outage caused is the last one before V2 came back: on a loaded
        # machine a receiver may also have timed V2 out for a moment earlier (beacons delayed
        # beyond the table's timeout, then heard again: a departure of its own, and a return)
        t_lost, how = gone[-1]
        print(f"{v} saw V2 gone ({how}) {t_lost - last_before:.2f} s of sensor time after V2's last estimate")
        # in the receiver's own sensor time, which may trail V2's by up to the IMU hold (0.25 s)
        assert how in ("liveliness", "silence") and -0.3 <= t_lost - last_before < 2.0
        back = [d["t"] for d in diags if gaps[0][1] < d["t"] < v2[-1] and "V2" not in d["status"]["lost"]]
        assert back, f"{v} never took V2 back"  # its beacons came back with the restarted agent
    # the run's recording is complete: every estimate of V0 and V1 on a 10 Hz grid
    for v in ("V0", "V1"):
        ts = sorted(d["t"] for d in lines if d["type"] == "Estimate" and d["vehicle"] == v and d["method"] == "SP")
        assert max(b - a for a, b in zip(ts, ts[1:])) < 0.15 and not any(math.isnan(t) for t in ts)


@pytest.mark.timeout(240)
def test_a_fault_schedule_runs_on_the_fleet_and_is_reported(tmp_path) -> None:
    """The shipped example schedule (every fault kind: link and sensor faults, an agent frozen, an
    agent killed, the emulator killed, the router restarted) on `slcp run`."""

    schedule = Path(__file__).resolve().parents[1] / "deploy" / "faults" / "paper-1.toml"
    out = tmp_path / "run"
    r = run_group([sys.executable, "-m", "slcp.deploy.cli", "run", "paper-1", "--faults", str(schedule),
                   "--out", str(out)], timeout=200)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((out / "metrics.json").read_text())
    assert [f["kind"] for f in m["faults"]] == ["v2v_blackout", "burst_loss", "latency_spike", "uwb_outage",
                                                "gnss_outage", "agent_freeze", "agent_kill", "emulator_kill",
                                                "router_restart"]
    restarts = m["processes"]["restarts"]
    assert [(x["process"], x["exit_code"]) for x in restarts] == [("router", "stopped"), ("agent-V1", -9),
                                                                  ("emulator", -9)]
    # the bounds only tell a resumed run from a stuck one (speed is a figure): an agent was back
    # within 2 s alone, but beside the suite's heaviest fleet test (38 SUMO agents) a restart
    # took over 5 s; the emulator rebuilds the scenario's truth and sensor data before it
    # resumes (about 2.5 s of CPU) and took 5.15 to 12.1 s in suite runs on the 2-core machine
    limit = {"agent-V1": 15.0, "emulator": 20.0, "router": 10.0}
    assert all(x["rejoined_after_s"] is not None and x["rejoined_after_s"] < limit[x["process"]]
               for x in restarts), restarts
    # resumed where the fleet was: the kill comes at t = 45 s on the launcher's 0.2 s (wall) poll,
    # up to 4 s of sensor time later at the emulator's 20x, and it leads the agents by 0.5 s
    assert 45.0 <= restarts[2]["resumed_at_t_s"] < 50.0
    report = (out / "report.md").read_text()
    assert "## Faults" in report and "| agent_freeze (V0) |" in report and "## Process faults" in report
    lines = [json.loads(x) for x in (out / "recorded" / "messages.jsonl").read_text().splitlines()]
    for row in ("| gnss_outage (V2) | 8.0–14.0 | V2 |", "| v2v_blackout (V2) | 20.0–24.0 | V2 |",
                "| emulator_kill (all) | 45.0–45.0 | V0 |", "| router_restart (all) | 16.0–18.0 | V0 |",
                "| router | stopped |"):
        assert row in report, row
    v0 = [d["t"] for d in lines if d["type"] == "Estimate" and d["vehicle"] == "V0" and d["method"] == "SP"]
    assert max(v0) > 45.0  # the frozen agent resumed and went on to the end
    assert not any(d["first_stopped"] for d in lines if d["type"] == "Estimate" and d["vehicle"] == "V2")
    assert (out / "config" / "faults.toml").read_text() == schedule.read_text()


@pytest.mark.timeout(120)
def test_a_run_whose_scheduled_faults_were_not_applied_says_so_and_fails(tmp_path) -> None:
    """A process fault the fleet's clock never reaches (here: after the scenario's end) leaves
    the run untested as scheduled: named in metrics.json and on stderr, exit code 1."""
    scn = short_scenario(tmp_path, "paper-1", 12.0)
    schedule = tmp_path / "late.toml"
    schedule.write_text('[[fault]]\nkind = "agent_kill"\nstart = 30.0\nvehicles = ["V1"]\n')
    out = tmp_path / "run"
    r = run_group([sys.executable, "-m", "slcp.deploy.cli", "run", str(scn), "--methods", "SP", "--faults",
                   str(schedule), "--out", str(out)], timeout=100)
    assert r.returncode == 1, r.stderr[-2000:]
    assert "scheduled faults not applied" in r.stderr and "agent_kill at 30 s" in r.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["processes"]["faults_not_applied"] == [{"kind": "agent_kill", "start_s": 30.0, "vehicles": ["V1"]}]


@pytest.mark.timeout(120)
def test_a_killed_recorder_keeps_what_it_wrote_and_a_restarted_one_continues(tmp_path) -> None:
    """`slcp record` behind `slcp router` (loopback): SIGKILL mid-stream, restart, stream again.
    Everything published well before the kill is on disk, the file is appended to (never
    rewritten), and the restarted recorder records what follows."""
    import asyncio

    import numpy as np

    from slcp.transport import keys
    from slcp.transport.codec import encode
    from slcp.transport.messages import Estimate
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    out = tmp_path / "messages.jsonl"
    cli = [sys.executable, "-m", "slcp.deploy.cli"]
    router = subprocess.Popen([*cli, "router", "--listen", ep], start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [router]

    def recorder() -> subprocess.Popen:
        p = subprocess.Popen([*cli, "record", "--connect", ep, "--out", str(out)], start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        procs.append(p)
        return p

    def est(k: int) -> bytes:
        return encode(Estimate("V1", "SP", 0.1 * k, np.array([0.7, 2.0, 50.0]), np.zeros(3), np.zeros(3), np.eye(3)))

    async def publish(bus, ks, pause: float = 0.01) -> None:
        for k in ks:
            await bus.publish(keys.estimate("V1", "SP"), est(k))
            await asyncio.sleep(pause)

    def times() -> list[float]:
        text = out.read_text() if out.exists() else ""
        return [json.loads(x)["t"] for x in text.splitlines() if x.endswith("}")]

    async def until_recorded(bus, k: int) -> int:
        """Probes from ``k`` on until the recorder takes one (its start-up takes seconds on a
        loaded machine); the next ``k``."""
        lo, deadline = 0.1 * k - 0.05, time.monotonic() + 30.0
        while time.monotonic() < deadline and not [x for x in times() if x >= lo]:
            await publish(bus, [k], pause=0.05)
            k += 1
        return k

    try:
        wait_for_port(port, timeout=60.0)  # a router's start-up takes seconds on a loaded machine
        rec = recorder()

        async def main():
            bus = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
            try:
                k0 = await until_recorded(bus, 0)
                await publish(bus, range(k0, k0 + 200))  # ~2 s
                await asyncio.sleep(0.5)
                before = out.read_bytes()
                os.kill(rec.pid, signal.SIGKILL)
                rec.wait(timeout=10)
                await publish(bus, range(k0 + 200, k0 + 250))  # nobody records these
                recorder()
                k1 = await until_recorded(bus, k0 + 250)
                await publish(bus, range(k1, k1 + 200))
                await asyncio.sleep(1.0)
                return before, k0, k1
            finally:
                await bus.close()

        before, k0, k1 = asyncio.run(main())
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(timeout=10)
    got = times()
    assert out.read_bytes().startswith(before)  # appended to, never rewritten
    t = set(np.round(np.array(got) * 10).astype(int))
    assert set(range(k0, k0 + 200)) <= t  # all flushed before the kill
    assert set(range(k1, k1 + 200)) <= t  # the restarted recorder got everything after it
    assert not set(range(k0 + 200, k0 + 250)) & t


@pytest.mark.timeout(120)
def test_a_launcher_killed_with_sigkill_leaves_no_process_behind(tmp_path) -> None:
    """`slcp run` killed with SIGKILL cannot stop its processes; they notice it is gone (their
    parent changes) and stop by themselves within about a second."""
    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "run", "paper-1", "--speed", "1", "--out", str(out)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)

    def children() -> set[int]:
        return {int(x) for x in subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True,
                                               text=True).stdout.split()}

    def running(pids: set[int]) -> set[int]:  # not gone and not a zombie left to a non-reaping init
        alive = set()
        for pid in pids:
            with contextlib.suppress(OSError):
                state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
                if state != "Z":
                    alive.add(pid)
        return alive

    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(children()) < 4:  # 3 agents, emulator
            time.sleep(0.2)
        time.sleep(2.0)
        kids = children()
        assert len(kids) == 4, kids
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and running(kids):
            time.sleep(0.2)
        assert not running(kids)
        for log in ("agent-V1.log", "emulator.log"):
            assert "the launcher" in (out / "logs" / log).read_text()
    finally:
        subprocess.run(["pkill", "-KILL", "-f", str(out)], check=False)


def test_a_rejoin_is_the_first_estimate_after_the_restart_not_an_old_one_in_flight() -> None:
    """#39 finding 9: an estimate the killed agent sent before it died, received just after its
    restart, was reported as a rejoin 4.7 ms after a 2.1 s gap. A rejoin is an estimate of a
    sensor time after the restart's."""
    from types import SimpleNamespace

    from slcp.deploy.supervisor import _Supervisor

    rec = SimpleNamespace(latest_t={"V0": 10.0, "V1": 10.0}, last_wall={"V0": 100.0, "V1": 100.0})
    r_agent = {"process": "agent-V0", "_t": 100.0, "_after_t": 10.0, "rejoined_after_s": None}
    r_emu = {"process": "emulator", "_t": 100.0, "_after_t": 10.0, "rejoined_after_s": None}
    sup = SimpleNamespace(rec=rec, restarts=[r_agent, r_emu])
    rec.latest_t["V0"], rec.last_wall["V0"] = 10.0, 100.005  # the old process's last estimate, late
    _Supervisor._note_rejoins(sup)
    assert r_agent["rejoined_after_s"] is None and r_emu["rejoined_after_s"] is None
    rec.latest_t["V1"], rec.last_wall["V1"] = 10.4, 101.0  # the emulator's data flows again
    _Supervisor._note_rejoins(sup)
    assert r_agent["rejoined_after_s"] is None and r_emu["rejoined_after_s"] == pytest.approx(1.0)
    rec.latest_t["V0"], rec.last_wall["V0"] = 12.2, 102.1  # the new V0's first estimate
    _Supervisor._note_rejoins(sup)
    assert r_agent["rejoined_after_s"] == pytest.approx(2.1)
