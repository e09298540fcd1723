"""The stand-in engine of the fleet benchmark (``slcp bench --fleet-engine stand-in``): the real
engine until its first beacon and estimate, then the same traffic at the same rates with no
estimation; and the option's way from the command line to every agent's."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from slcp.agent.engine import VehicleEngine
from slcp.agent.stand_in import DIAGNOSTICS_RATE, StandInEngine
from slcp.deploy.agent_configs import agent_config
from slcp.deploy.inprocess import run_inprocess
from slcp.hw_emulation.scenario import load_scenario
from slcp.hw_emulation.truth import build_truth
from slcp.transport.codec import encode
from slcp.transport.messages import Beacon, Diagnostics, Estimate

METHODS = ("SL-SP", "SL-CP")


@pytest.fixture(scope="module")
def v0_inputs():
    """Every message paper-1's V0 was handed in a seeded in-process run, in order."""
    truth = build_truth(load_scenario("paper-1"))
    msgs: list = []
    run_inprocess(truth, 0, METHODS, on_message=lambda v, m: msgs.append(m) if v == "V0" else None)
    return truth.scenario, msgs


def _play(engine: VehicleEngine, msgs: list) -> list[list]:
    """The outputs of each message handed to ``engine``, then of its finish."""
    outs = []
    for m in msgs:
        engine.handle(m)
        outs.append(engine.take_outbox())
    engine.finish()
    outs.append(engine.take_outbox())
    return outs


def test_the_stand_in_is_the_engine_until_its_first_beacon_and_estimate(v0_inputs) -> None:
    scn, msgs = v0_inputs
    real = VehicleEngine(agent_config(scn, "V0", METHODS))
    stand = StandInEngine(agent_config(scn, "V0", METHODS))
    k = 0
    while not stand.standing_in:  # the same messages out, to the last bit
        real.handle(msgs[k])
        stand.handle(msgs[k])
        assert [encode(m) for m in stand.take_outbox()] == [encode(m) for m in real.take_outbox()]
        k += 1
    assert k < len(msgs) // 10
    # then nothing is estimated: the filters stand where they were, every message is counted
    at_switch = {m: (f.filter.t, f.filter.state.llh.copy()) for m, f in stand.filters.items()}
    for m in msgs[k:]:
        stand.handle(m)
    stand.finish()
    assert stand.counters["stand_in_inputs"] == len(msgs) - k
    for m, f in stand.filters.items():
        assert f.filter.t == at_switch[m][0] and np.array_equal(f.filter.state.llh, at_switch[m][1])
    for m in msgs[k:]:  # where the engine itself moves on
        real.handle(m)
    assert real.filters["SL-CP"].filter.t > at_switch["SL-CP"][0] + 10.0


def test_the_stand_in_sends_the_engines_traffic_at_its_rates(v0_inputs) -> None:
    scn, msgs = v0_inputs
    cfg = agent_config(scn, "V0", METHODS)
    real = [m for o in _play(VehicleEngine(cfg), msgs) for m in o]
    stand = [m for o in _play(StandInEngine(dataclasses.replace(cfg)), msgs) for m in o]
    for kind in (Beacon, Estimate):
        for method in METHODS:
            r = [m for m in real if isinstance(m, kind) and m.method == method]
            s = [m for m in stand if isinstance(m, kind) and m.method == method]
            assert abs(len(s) - len(r)) <= 1, (kind.__name__, method, len(s), len(r))
            ts = np.array([m.t for m in s])
            rate = cfg.beacon_rate if kind is Beacon else cfg.estimate_rate
            np.testing.assert_allclose(np.diff(ts), 1.0 / rate, atol=1e-9)
            # copies: the size of the engine's message they copy, but for their stamps' encodings
            sizes = [len(encode(m)) for m in s[len(s) // 10:]]
            assert max(sizes) - min(sizes) <= 4
    seqs = [b.seq for b in stand if isinstance(b, Beacon) and b.method == "SL-CP"]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    diag = np.array([m.t for m in stand if isinstance(m, Diagnostics)])
    assert len(diag) >= 2 and np.all(np.diff(diag)[:-1] <= 1.0 / DIAGNOSTICS_RATE + 1e-9)


def test_slcp_bench_gives_the_stand_in_to_every_agent(monkeypatch, capsys, tmp_path) -> None:
    """``--fleet-engine stand-in`` reaches the fleet point, which gives ``--stand-in`` to the
    agents' command lines and says so in its figures."""
    from slcp.deploy import bench, fleet_bench
    from slcp.deploy.cli import main
    from slcp.deploy.commands import lab
    from slcp.deploy.supervisor import _Supervisor

    seen = {}

    def fake_run_fleet(scenario, **kw):
        seen.update(kw)
        return {"wall_s": 0.0, "processes": {}}

    monkeypatch.setattr("slcp.deploy.launcher.run_fleet", fake_run_fleet)
    monkeypatch.setattr(fleet_bench.FleetMonitor, "result", lambda self: {"agents": 3})
    point = fleet_bench.run_fleet_point(3, 5.0, engine="stand-in")
    assert seen["agent_args"] == ("--stand-in",) and point["engine"] == "stand-in"
    fleet_bench.run_fleet_point(3, 5.0)
    assert seen["agent_args"] == ()
    with pytest.raises(ValueError, match="engine must be one of"):
        fleet_bench.run_fleet_point(3, 5.0, engine="none")

    sup = _Supervisor(["V0"], {"V0": "a.toml"}, tmp_path, None, 0, [], None, 1.0, 5, None, 1.0, 1.0, "t",
                      agent_args=("--stand-in",))
    assert sup._agent_args("V0")[-1] == "--stand-in"

    got = {}

    def fake_point(n, *a, **kw):
        got.update(kw)
        return {"agents": n, "error": "stub"}

    monkeypatch.setattr(fleet_bench, "run_fleet_point", fake_point)
    monkeypatch.setattr(bench, "micro_benchmarks", lambda quick=False: {k: 1.0 for k in (*lab.FLEET_POINT_STEPS,
                                                                                          "imu_step_us")})
    assert main(["bench", "--quick", "--json", "--drive", "/nonexistent", "--fleet", "3",
                 "--fleet-engine", "stand-in"]) == 0
    assert got["engine"] == "stand-in"
    json.loads(capsys.readouterr().out)


def test_slcp_agent_stand_in_runs_the_stand_in(monkeypatch) -> None:
    from slcp.deploy import processes
    from slcp.deploy.cli import main

    calls = []

    async def fake_agent_main(config, vehicle, nice, stand_in=False):
        calls.append(stand_in)
        return 0

    monkeypatch.setattr(processes, "agent_main", fake_agent_main)
    assert main(["agent", "--config", "a.toml", "--stand-in"]) == 0
    assert main(["agent", "--config", "a.toml"]) == 0
    assert calls == [True, False]
