"""Fault schedules: the file format and its errors, and link and sensor faults played on a running
fleet (in-memory bus): a V2V blackout, burst loss, a latency spike, a UWB and a GNSS outage."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from slcp.hw_emulation.faults import Fault, FaultError, load_faults, parse_faults


def test_a_schedule_file_is_read_and_its_errors_name_the_fault(tmp_path) -> None:
    p = tmp_path / "faults.toml"
    p.write_text('[[fault]]\nkind = "v2v_blackout"\nstart = 20\nend = 24\nvehicles = ["V2"]\n\n'
                 '[[fault]]\nkind = "burst_loss"\nstart = 26\nend = 30\nloss = 0.7\n\n'
                 '[[fault]]\nkind = "agent_kill"\nstart = 15\nvehicles = ["V1"]\n')
    fs = load_faults(p, {"V0", "V1", "V2"})
    assert fs[0] == Fault("v2v_blackout", 20.0, 24.0, ("V2",))
    assert fs[1].loss == 0.7 and fs[1].vehicles == () and fs[2].end == 15.0
    assert fs[0].hits_link("V2", "V0") and fs[0].hits_link("V1", "V2") and not fs[0].hits_link("V0", "V1")
    pair = Fault("uwb_outage", 0, 1, ("V1", "V2"))
    assert pair.hits_pair("V2", "V1") and not pair.hits_pair("V0", "V1")
    bad = [('kind = "meteor"\nstart = 1\nend = 2', "kind must be one of"),
           ('kind = "gnss_outage"\nstart = 5\nend = 2', "need 0 <= start <= end"),
           ('kind = "gnss_outage"\nstart = 5\nend = 5', "gnss_outage needs an end after its start"),
           ('kind = "gnss_outage"\nstart = 1\nend = 2\nvehicles = ["V9"]', "unknown vehicle 'V9'"),
           ('kind = "agent_freeze"\nstart = 1\nend = 2', "agent_freeze needs exactly one vehicle"),
           ('kind = "burst_loss"\nstart = 1\nend = 2\nloss = 1.5', "loss must be a probability"),
           ('kind = "burst_loss"\nstart = 1\nend = 2\nduration = 3', "unknown field 'duration'"),
           ('kind = "burst_loss"\nend = 2', "start is missing"),
           ('kind = "router_restart"\nstart = 1\nend = 1', "router_restart needs an end after its start"),
           ('kind = "router_restart"\nstart = 1\nend = 2\nvehicles = ["V1"]', "router_restart takes no vehicles")]
    for body, msg in bad:
        p.write_text("[[fault]]\n" + body + "\n")
        with pytest.raises(FaultError, match=f"faults.toml: fault 1: {msg}"):
            load_faults(p, {"V0", "V1", "V2"})
    p.write_text("[[fault]\n")
    with pytest.raises(FaultError, match="not valid TOML"):
        load_faults(p)
    with pytest.raises(FaultError, match="cannot read"):
        load_faults(tmp_path / "missing.toml")
    with pytest.raises(FaultError, match="unknown section"):
        parse_faults({"faults": []}, "x")


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_link_and_sensor_faults_on_a_running_fleet() -> None:
    from slcp.agent.runtime import Agent
    from slcp.deploy.agent_configs import agent_config
    from slcp.hw_emulation.scenario import load_scenario
    from slcp.hw_emulation.service import EmulatorService
    from slcp.hw_emulation.truth import build_truth
    from slcp.transport import keys
    from slcp.transport.bus import InMemoryNetwork
    from slcp.transport.codec import decode

    scn = load_scenario("paper-1")
    truth = build_truth(scn)
    faults = [Fault("v2v_blackout", 20.0, 24.0, ("V2",)), Fault("burst_loss", 26.0, 30.0, loss=0.7),
              Fault("latency_spike", 30.0, 32.0, latency=0.4), Fault("uwb_outage", 33.0, 37.0, ("V1", "V2")),
              Fault("gnss_outage", 8.0, 14.0, ("V2",))]

    async def main():
        net = InMemoryNetwork()
        stop = asyncio.Event()
        agents = {v: Agent(agent_config(scn, v), net.bus()) for v in sorted(truth.vehicles)}
        rec = net.bus().subscribe(keys.ROOT + "/estimate/**", 1_000_000)
        emu = EmulatorService(truth, net.bus(), seed=0, faults=faults)
        tasks = [asyncio.create_task(a.run(stop)) for a in agents.values()]
        await emu.run()
        stop.set()
        await asyncio.gather(*tasks)
        est = [decode(payload) for _, payload in rec.drain()]
        return agents, emu, est

    agents, emu, est = asyncio.run(main())
    print("fault stats:", emu.fault_stats)
    for kind in ("v2v_blackout", "burst_loss", "latency_spike", "uwb_outage", "gnss_outage"):
        assert emu.fault_stats.get(kind, 0) > 0, kind
    # GNSS outage: 6 s at 5 Hz withheld from V2 only
    assert emu.fault_stats["gnss_outage"] == 30
    assert agents["V2"].counters["gnss"] == agents["V1"].counters["gnss"] - 30
    # the blackout cut V2 off: it lost its neighbours by silence within 1.5 s and they lost it
    dep = {v: [(t, o, how) for t, o, how in a.departures] for v, a in agents.items()}
    assert any(o == "V1" and how == "silence" and 21.0 <= t <= 21.7 for t, o, how in dep["V2"]), dep["V2"]
    assert any(o == "V2" and 21.0 <= t <= 21.7 for t, o, _ in dep["V1"]), dep["V1"]
    # ... and V2, stopping behind V1 while deaf, never took V1's stop line (V1's ghost)
    assert not any(e.first_stopped for e in est if e.vehicle == "V2")
    assert any(e.first_stopped for e in est if e.vehicle == "V1" and e.method == "SL-SP")
    # ranges resumed after the UWB outage, and every estimate stayed finite
    for v in ("V1", "V2"):
        assert agents[v].filters["CP"].counters["ranges"] + agents[v].filters["CP"].counters["ranges_skipped"] > 0
    assert all(np.all(np.isfinite(e.llh)) and np.all(np.isfinite(e.cov_pos)) for e in est)


def test_a_chaos_schedule_is_valid_spaced_and_within_the_restart_limits(tmp_path) -> None:
    import numpy as np

    from slcp.hw_emulation.faults import PROCESS_FAULTS, random_schedule, schedule_toml

    vehicles = [f"V{k}" for k in range(6)]
    for seed in range(20):
        fs = random_schedule(vehicles, 300.0, np.random.default_rng(seed), per_minute=6.0, max_freeze=30.0)
        assert len(fs) == 30
        p = tmp_path / f"chaos-{seed}.toml"
        p.write_text(schedule_toml(fs, "test"))
        assert load_faults(p, set(vehicles)) == fs  # the file says exactly this schedule
        proc = [f.start for f in fs if f.kind in PROCESS_FAULTS]
        assert all(b - a >= 10.0 for a, b in zip(proc, proc[1:]))
        assert all(10.0 <= f.start <= 290.0 for f in fs)
        kills = [f.vehicles[0] if f.vehicles else "emulator" for f in fs if f.kind.endswith("_kill")]
        assert all(kills.count(k) <= 2 for k in kills)
        assert all(f.end - f.start <= 30.0 for f in fs if f.kind == "agent_freeze")
    kinds = {f.kind for seed in range(20)
             for f in random_schedule(vehicles, 300.0, np.random.default_rng(seed))}
    assert kinds == {"agent_kill", "agent_freeze", "v2v_blackout", "gnss_outage", "emulator_kill", "router_restart"}
    with pytest.raises(FaultError):
        random_schedule(vehicles, 20.0, np.random.default_rng(0))
