"""A fleet's start does not depend on the order in which a vehicle's first messages arrive (#40).

At start-up the emulator plays the first few tenths of a second as fast as it can, so a vehicle's
first GNSS fix and its first IMU batches reach the agent within milliseconds, on different keys,
through different Zenoh callback threads. If the IMU batches were handed over first, the agent
dropped its first batch for want of a fix, started one batch later, and held its first estimate
back until IMU data came that the emulator, pacing on the agents' estimates, would not send:
the whole fleet waited. These tests replay such an order deterministically."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from slcp.agent.engine import VehicleEngine
from slcp.agent.runtime import Agent
from slcp.deploy.agent_configs import agent_config
from slcp.hw_emulation.playback import SensorPlayback
from slcp.hw_emulation.scenario import load_scenario
from slcp.hw_emulation.service import EmulatorService
from slcp.hw_emulation.truth import build_truth
from slcp.transport import keys
from slcp.transport.bus import InMemoryNetwork
from slcp.transport.codec import decode, encode
from slcp.transport.messages import Estimate, GnssFix, ImuBatch


@pytest.fixture(scope="module")
def paper1():
    scn = load_scenario("paper-1")
    truth = build_truth(scn)
    return scn, truth


def _first_messages(truth, vehicle: str, until: float) -> list:
    """``vehicle``'s own sensor messages up to ``until`` [s], in the emulator's order."""
    out = []
    for t, msgs in SensorPlayback(truth, seed=0).messages():
        if t > until:
            break
        out += [m for m in msgs if getattr(m, "vehicle", None) == vehicle and isinstance(m, (ImuBatch, GnssFix))]
    return out


def _fix_late(msgs: list, n_imu: int) -> list:
    """The same messages with the GNSS fixes handed over only after ``n_imu`` IMU batches (in
    their order: one key, one publisher)."""
    k = [i for i, m in enumerate(msgs) if isinstance(m, ImuBatch)][n_imu - 1]
    fixes = [m for m in msgs[:k + 1] if isinstance(m, GnssFix)]
    rest = [m for m in msgs if not any(m is f for f in fixes)]
    k = [i for i, m in enumerate(rest) if isinstance(m, ImuBatch)][n_imu - 1]
    return rest[:k + 1] + fixes + rest[k + 1:]


def _estimates(scn, vehicle: str, msgs: list) -> list[Estimate]:
    eng = VehicleEngine(agent_config(scn, vehicle))
    out = []
    for m in msgs:
        eng.handle(m)
        out += [e for e in eng.take_outbox() if isinstance(e, Estimate)]
    return out


@pytest.mark.parametrize("n_imu", [1, 3, 4, 6])
def test_the_filters_start_the_same_whichever_arrives_first_the_fix_or_the_imu(paper1, n_imu) -> None:
    scn, truth = paper1
    msgs = _first_messages(truth, "V1", 2.0)
    assert isinstance(msgs[0], GnssFix) or isinstance(msgs[1], GnssFix)
    direct = _estimates(scn, "V1", msgs)
    late = _estimates(scn, "V1", _fix_late(msgs, n_imu))
    assert direct and [(e.method, e.t) for e in late] == [(e.method, e.t) for e in direct]
    for a, b in zip(direct, late, strict=True):
        np.testing.assert_allclose(b.llh, a.llh, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.cov_pos, a.cov_pos, rtol=1e-12, atol=0)


def test_without_any_fix_the_first_imu_batches_are_dropped_not_kept(paper1) -> None:
    scn, truth = paper1
    imu = [m for m in _first_messages(truth, "V1", 3.0) if isinstance(m, ImuBatch)]
    eng = VehicleEngine(agent_config(scn, "V1"))
    for m in imu:
        eng.handle(m)
    held_s = float(imu[-1].t[-1] - eng._imu_buffer[0].t[0])
    # the wait for a fix is bounded: the hold plus the fix window, and a batch more
    assert held_s <= eng.cfg.imu_hold + eng.INIT_FIX_WINDOW + 0.2
    assert eng.counters["before_init"] >= len(imu) - len(eng._imu_buffer) > 0 and not eng.filters


@pytest.mark.timeout(60)
def test_an_agent_whose_fix_comes_after_its_imu_reports_without_more_imu(paper1) -> None:
    """The agent's host: only the IMU wakes it once it runs, so a fix that comes after the last
    IMU batch the emulator will send before it hears from the agent must wake it before that."""
    scn, truth = paper1
    msgs = _fix_late(_first_messages(truth, "V1", 0.45), 4)
    assert isinstance(msgs[-1], GnssFix)

    async def main() -> list[Estimate]:
        net = InMemoryNetwork()
        agent = Agent(agent_config(scn, "V1"), net.bus())
        src, rec = net.bus(), net.bus().subscribe(keys.ROOT + "/estimate/**", 1000)
        stop = asyncio.Event()
        task = asyncio.create_task(agent.run(stop))
        await asyncio.sleep(0)
        for m in msgs:
            await src.publish(keys.imu("V1") if isinstance(m, ImuBatch) else keys.gnss("V1"), encode(m))
            await asyncio.sleep(0.01)
        try:
            await asyncio.wait_for(rec.get(), 5.0)
        finally:
            stop.set()
            await task
        return [decode(p) for _, p in [*rec.drain()]]

    asyncio.run(main())  # wait_for raises TimeoutError if no estimate comes


@pytest.mark.timeout(60)
def test_with_no_agent_reporting_the_emulator_waits_once_not_at_every_event(paper1) -> None:
    _, truth = paper1

    async def main() -> float:
        emu = EmulatorService(truth, InMemoryNetwork().bus(), seed=0, stall_timeout=0.3)
        emu.playback.messages = lambda start_at=None, orig=emu.playback.messages: (
            x for x in orig(start_at) if x[0] <= 3.0)
        t0 = asyncio.get_running_loop().time()
        await emu.run()
        return asyncio.get_running_loop().time() - t0

    wall = asyncio.run(main())
    # one wait of 0.3 s, then 3 s of events at up to 20x: not 0.3 s at each of ~100 events, nor
    # the final wait for the last estimates (nobody reports them)
    assert wall < 2.0


@pytest.mark.timeout(60)
def test_a_departure_of_a_name_outside_the_scenario_does_not_hold_the_clock(paper1) -> None:
    """#39 finding 5: the emulator took a 'left' notice for any name and held the clock for the
    rejoin grace (8-10 s). Only the scenario's vehicles count; the rest is counted and ignored."""
    _, truth = paper1

    async def main() -> tuple[float, EmulatorService]:
        emu = EmulatorService(truth, InMemoryNetwork().bus(), seed=0, stall_timeout=0.3, rejoin_grace=5.0)
        emu.playback.messages = lambda start_at=None, orig=emu.playback.messages: (
            x for x in orig(start_at) if x[0] <= 1.0)
        for k in range(5000):
            emu.forget_agent(f"X{k}")
        t0 = asyncio.get_running_loop().time()
        await emu.run()
        return asyncio.get_running_loop().time() - t0, emu

    wall, emu = asyncio.run(main())
    assert emu.unknown_liveliness == 5000 and not emu._away
    assert wall < 2.0  # not the 5 s grace
