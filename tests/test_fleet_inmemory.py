"""Agents + emulator service on the in-memory bus (paper-1): sensor data flow, beacons through
the radio, ranges fused, the first stopped vehicle found, bad payloads counted, no crash."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from slcp.agent.runtime import Agent
from slcp.deploy.agent_configs import agent_config
from slcp.hw_emulation.scenario import load_scenario
from slcp.hw_emulation.service import EmulatorService
from slcp.hw_emulation.truth import build_truth
from slcp.transport import keys
from slcp.transport.bus import InMemoryNetwork
from slcp.transport.codec import decode
from slcp.transport.messages import Beacon

pytestmark = pytest.mark.slow


@pytest.mark.timeout(300)
def test_fleet_on_the_in_memory_bus() -> None:
    scn = load_scenario("paper-1")
    truth = build_truth(scn)

    async def main():
        net = InMemoryNetwork()
        stop = asyncio.Event()
        agents = [Agent(agent_config(scn, vid), net.bus()) for vid in sorted(truth.vehicles)]
        rec_bus = net.bus()
        rec = rec_bus.subscribe(keys.ROOT + "/estimate/**", 1_000_000)
        emu = EmulatorService(truth, net.bus(), seed=0)
        tasks = [asyncio.create_task(a.run(stop)) for a in agents]
        await asyncio.sleep(0)
        # garbage on every topic an agent listens to: counted, never a crash
        for k in (keys.imu("V1"), keys.gnss("V1"), keys.uwb("V1"), keys.radio_rx("V1")):
            await rec_bus.publish(k, b"\x93garbage")
        await emu.run()
        stop.set()
        await asyncio.gather(*tasks)
        records = [decode(payload) for _, payload in rec.drain()]
        return agents, emu, records

    agents, emu, records = asyncio.run(main())
    by = {a.cfg.vehicle: a for a in agents}
    assert by["V1"].counters["codec_errors"] == 4
    assert emu.radio_stats.sent > 100 and emu.radio_stats.delivered > 0.8 * emu.radio_stats.sent
    for a in agents:
        assert a.counters["imu_batches"] > 400 and a.counters["gnss"] > 100 and a.counters["beacons_rx"] > 100
        c = a.filters["CP"].counters
        # every range reaches the filter: fused, skipped by node selection (little expected gain)
        # or gated; a good share is fused (V0 has the fewest, about 240: it turns away from the
        # queue it ranges with)
        handled = c["ranges"] + c["ranges_skipped"] + c["ranges_skipped_near"]
        assert handled + c["ranges_rejected"] > 150, c
        # the gate refuses the biased ranges (UWB NLOS episodes and outliers, which come in runs:
        # V0's few ranges can be an eighth biased) and few others
        biased = sum(int(np.count_nonzero(r.nlos | r.outlier)) for pair, r in emu.playback.ranges.items()
                     if a.cfg.vehicle in pair)
        assert c["ranges"] >= 1 and c["ranges_rejected"] <= biased + 0.05 * handled, (c, biased)
        assert all(d == 0 for d in a.dropped.values()), a.dropped
    # V1 decided it is first stopped; V2 (behind it) never did
    assert any(r.first_stopped for r in records if r.vehicle == "V1" and r.method == "SL-SP")
    assert not any(r.first_stopped for r in records if r.vehicle == "V2")
    # SL-SP error of V1 while it claims first
    vt = truth.vehicles["V1"].truth
    errs = []
    from slcp.geo import earth
    for r in records:
        if r.vehicle == "V1" and r.method == "SL-SP" and r.first_stopped:
            k = int(np.searchsorted(vt.t, r.t - 1e-9))
            e = earth.ned_offset(*r.llh, *vt.llh[k])
            errs.append(np.hypot(e[0], e[1]))
    rmse = float(np.sqrt(np.mean(np.square(errs))))
    print(f"V1 SL-SP RMSE while first over the bus: {rmse:.2f} m ({len(errs)} estimates)")
    assert rmse < 0.6


def test_an_unusable_range_is_counted_and_the_agent_goes_on() -> None:
    """A range whose fusion raises (here: the neighbour's beacon at our own position) is dropped and
    counted; it must not stay queued and break every later IMU batch."""
    from slcp.agent.neighbours import NeighbourState

    scn = load_scenario("paper-1")
    agent = Agent(agent_config(scn, "V1"), InMemoryNetwork().bus())

    class Boom:
        spec = type("S", (), {"ranges": True})()
        t = 10.0

        def range(self, *a):
            raise ValueError("vehicles coincide: range direction undefined")

    agent.engine.filters = {"CP": Boom()}
    agent.tables["CP"].update("V2", 1, 10.0, np.array([0.7, 2.0, 50.0]), np.zeros(3), np.eye(3), "CP", 10.0)
    agent.engine._deferred = [(10.0, "CP", "V2", 7.0)]
    agent.engine._fuse_ranges()
    assert agent._deferred == [] and agent.counters["rejected_range"] == 1
    assert isinstance(agent.tables["CP"].at("V2", 10.0), NeighbourState)


def test_a_ranging_round_reaches_the_filters_as_its_single_ranges_would() -> None:
    """A UwbRound (one message per vehicle and round) is sequenced exactly as the UwbRange of
    each of its pairs; a peer equal to the receiver and a repeated round are counted, not used."""
    from slcp.transport.messages import UwbRange, UwbRound

    scn = load_scenario("paper-1")

    def sequenced(messages):
        agent = Agent(agent_config(scn, "V1"), InMemoryNetwork().bus())
        agent.engine.filters = {"CP": object()}  # initialised: measurements go to the sequencer
        agent.engine.checks.imu_newest = 10.0
        pushed = []
        agent.seq.push = lambda t, kind, msg: pushed.append(
            (t, kind, msg.b if msg.a == "V1" else msg.a, msg.range_m)) or []
        for m in messages:
            asyncio.run(agent.handle(m))
        return pushed, agent.counters

    rnd = UwbRound("V1", 42, 9.9, ("V0", "V2", "V1"), np.array([7.5, 6.25, 3.0]))
    singles = [UwbRange("V0", "V1", 42, 9.9, 7.5), UwbRange("V1", "V2", 42, 9.9, 6.25)]
    by_round, counters = sequenced([rnd, rnd])
    by_single, _ = sequenced(singles)
    assert by_round == by_single == [(9.9, "uwb", "V0", 7.5), (9.9, "uwb", "V2", 6.25)]
    assert counters["uwb"] == 2 and counters["not_for_me"] == 1 and counters["duplicate_uwb"] == 1
    assert sequenced([UwbRound("V2", 1, 9.9, ("V1",), np.array([5.0]))])[0] == []  # not for V1


def test_a_late_estimate_of_a_departed_agent_does_not_hold_the_clock() -> None:
    """An estimate the dead process sent just before its liveliness token went is ignored while
    the agent is away (else the pacing would wait for its old time, for ever); the restarted
    agent's estimates count again."""
    truth = build_truth(load_scenario("paper-1"))
    emu = EmulatorService(truth, InMemoryNetwork().bus(), seed=0)
    emu.agent_progress("V2", 16.2)
    emu.forget_agent("V2")
    emu.agent_progress("V2", 16.2)  # still queued when the token went
    assert "V2" not in emu.agent_time
    emu.agent_back("V2")
    emu.agent_progress("V2", 17.0)
    assert emu.agent_time["V2"] == 17.0


def test_a_restarted_agent_declared_before_its_predecessor_left_does_not_hold_the_clock() -> None:
    """A restarted agent's token seen before the killed one's departure: the agent is set aside
    until it reports an estimate newer than its old one (the clock does not wait for the new
    process at the old time; it could not report before the data it missed), then paced on."""
    truth = build_truth(load_scenario("paper-1"))
    emu = EmulatorService(truth, InMemoryNetwork().bus(), seed=0, stall_timeout=5.0)
    stop = asyncio.Event()
    for v in ("V0", "V1", "V2"):
        emu.agent_progress(v, 8.0)
    emu.agent_back("V2")  # the new process's token, the old one not yet withdrawn
    assert "V2" not in emu.agent_time and emu.stalled == {"V2": 8.0}
    for v in ("V0", "V1"):
        emu.agent_progress(v, 10.0)
    w = time.monotonic()
    asyncio.run(emu._pace(10.1, w - 1e3, 0.0, stop))
    assert time.monotonic() - w < 1.0  # not stall_timeout
    emu.agent_progress("V2", 8.0)  # a stale estimate of the old process: still aside
    assert "V2" not in emu.agent_time
    emu.agent_progress("V2", 9.5)
    assert emu.agent_time["V2"] == 9.5 and "V2" not in emu.stalled


def test_an_agent_that_stalls_the_clock_is_waited_for_once_then_set_aside_until_it_reports() -> None:
    """Agent-paced clock: an agent whose estimates stop arriving (hung, or its messages no longer
    get through) holds the clock for ``stall_timeout`` once, not at every later event; it is paced
    on again as soon as it reports a time later than the one it stalled at."""
    truth = build_truth(load_scenario("paper-1"))
    emu = EmulatorService(truth, InMemoryNetwork().bus(), seed=0, stall_timeout=0.3)
    wall0, stop = time.monotonic() - 1e3, asyncio.Event()  # (max_speed adds at most 0.05 s a call here)

    def pace(t: float) -> float:
        w = time.monotonic()
        asyncio.run(emu._pace(t, wall0, 0.0, stop))
        return time.monotonic() - w

    for v, t in (("V0", 5.0), ("V1", 10.0), ("V2", 10.0)):
        emu.agent_progress(v, t)
    assert pace(10.2) >= 0.3 and emu.stalled == {"V0": 5.0} and "V0" not in emu.agent_time
    emu.agent_progress("V0", 5.0)  # nothing new: still aside
    assert pace(10.3) < 0.1 and pace(10.4) < 0.1
    emu.agent_progress("V0", 10.1)
    assert emu.stalled == {} and emu.agent_time["V0"] == 10.1
    assert pace(10.5) < 0.1  # everyone within the lead
    assert 0.3 <= pace(11.5) < 1.0 and emu.stalled == {"V0": 10.1, "V1": 10.0, "V2": 10.0}
    assert pace(11.6) < 0.1  # nobody left to wait for: the clock runs on


def test_the_clock_never_makes_up_held_time_in_a_burst() -> None:
    """Agent-paced clock with every agent set aside (back after a network outage, not yet
    reporting): it runs at max_speed, measured from the last time it was held, not from the start
    of the run. Long after the start (the run's budget at max_speed far ahead of the clock), 2 s
    of sensor time still take at least 2 s / max_speed of wall time; once it has run that fast,
    waiting has not bought a burst either."""
    truth = build_truth(load_scenario("paper-1"))
    emu = EmulatorService(truth, InMemoryNetwork().bus(), seed=0, max_speed=20.0)
    emu.stalled = {v: -np.inf for v in truth.vehicles}
    wall0, stop = time.monotonic() - 1e3, asyncio.Event()

    async def play(t_from: float, t_to: float) -> float:
        w = time.monotonic()
        for t in np.arange(t_from, t_to + 1e-9, 0.05):
            await emu._pace(float(t), wall0, 0.0, stop)
        return time.monotonic() - w

    async def main() -> tuple[float, float]:
        first = await play(20.0, 22.0)
        await asyncio.sleep(0.5)  # held (as by a restart): 10 s of sensor time at max_speed
        return first, await play(22.05, 24.05)

    first, after_hold = asyncio.run(main())
    assert 2.0 / 20.0 <= first < 1.0
    assert 2.0 / 20.0 <= after_hold < 1.0


def test_the_filters_start_from_the_fix_nearest_the_first_imu_sample_whatever_had_arrived() -> None:
    """Which GNSS fixes an agent holds when its first IMU batch is processed depends on message
    timing; the start does not: the fix nearest in time, moved to the IMU start by its velocity."""
    from slcp.geo import earth
    from slcp.transport.messages import GnssFix, ImuBatch

    scn = load_scenario("paper-1")
    cfg = agent_config(scn, "V1", methods=("SP",))
    llh0, v = np.array(scn.origin_llh), np.array([10.0, 0.0, 0.0])

    def fix(seq: int, t: float) -> GnssFix:
        return GnssFix("V1", seq, t, earth.offset_llh(llh0, v * t), v, np.array([1.0, 1.0, 2.0]), 0.1)

    n = 10
    batch = ImuBatch("V1", 0, np.arange(1, n + 1) * 0.01, np.full(n, 0.01), np.zeros((n, 3)),
                     np.tile([0.0, 0.0, -9.8 * 0.01], (n, 1)))

    async def start(fixes):
        a = Agent(cfg, InMemoryNetwork().bus())
        for g in fixes:
            await a.handle(g)
        a.engine._imu(batch)
        return a

    starts = [asyncio.run(start(fs)) for fs in ([fix(0, 0.0)], [fix(0, 0.0), fix(1, 0.2), fix(2, 0.4)],
                                                [fix(1, 0.2)], [fix(2, 0.4), fix(1, 0.2)])]
    llh = [a.filters["SP"].filter.state.llh for a in starts]
    for other in llh[1:]:
        assert np.allclose(earth.ned_offset(*llh[0], *other), 0.0, atol=1e-3)
    # the later fixes wait in the sequencer as measurements; a fix too far from the IMU starts nothing
    assert starts[1].seq.counters.get("late_dropped", 0) == 0 and len(starts[1].seq._heap) == 2
    far = asyncio.run(start([fix(0, 5.0)]))
    assert not far.filters and far.counters["before_init"] == 1


def test_the_radio_delivers_to_exactly_the_receivers_within_its_range() -> None:
    """The radio's positions (the truth in the scenario's local frame, once per clock value) give
    the same horizontal distances as pymap3d's exact offset of each vehicle in every other's
    local frame (to a millimetre per kilometre), and a beacon goes to every other vehicle within
    ``max_range`` and to no one beyond it."""
    import dataclasses

    import pymap3d

    from slcp.hw_emulation.playback import Radio

    truth = build_truth(load_scenario("rush-hour"))
    radio = Radio(truth, seed=0)
    ids = radio.ids
    assert radio._ne_grid is not None  # build_truth's vehicles share one time grid: stacked
    for now in (5.0, 31.7, 60.0, 88.8):
        ne = radio.positions(now)
        # the same as the per-vehicle search (vehicles on different grids)
        stacked, radio._ne_grid, radio._ne_at = radio._ne_grid, None, None
        np.testing.assert_array_equal(radio.positions(now), ne)
        radio._ne_grid = stacked
        llh = {}
        for v in ids:
            t = truth.vehicles[v].truth.t
            llh[v] = truth.vehicles[v].truth.llh[min(int(np.searchsorted(t, now)), len(t) - 1)]
        for i, a in enumerate(ids):
            for j, b in enumerate(ids):
                n, e, _ = pymap3d.geodetic2ned(*llh[a], *llh[b], deg=False)
                assert np.hypot(*(ne[i] - ne[j])) == pytest.approx(np.hypot(n, e), rel=1e-6, abs=1e-4)
        # a lossless radio whose range cuts the fleet in two
        sender = ids[len(ids) // 2]
        dist = {v: float(np.hypot(*(ne[ids.index(v)] - ne[ids.index(sender)]))) for v in ids if v != sender}
        reach = float(np.median(list(dist.values())))
        radio.model = dataclasses.replace(radio.model, loss=0.0, ge_p_good_to_bad=0.0, stale_prob=0.0,
                                          max_range=reach)
        radio._pending.clear()
        before = radio.stats.out_of_range
        b = Beacon(sender, 1, "SL-CP", now, llh[sender], np.zeros(3), np.eye(3))
        radio.send(b, b, now)
        got = [p[1] for p in radio._pending]
        assert got == sorted(v for v, d in dist.items() if d <= reach) and got
        assert radio.stats.out_of_range - before == sum(d > reach for d in dist.values()) > 0
        assert sorted(rx for _, rx, _ in radio.due(now + 1.0)) == got and radio.stats.delivered >= len(got)


def test_the_radio_reaches_no_vehicle_before_or_after_its_time_in_the_traffic() -> None:
    """A vehicle that has not yet entered the traffic, or has left it (a SUMO vehicle, a track
    of imported trajectories), stands where its truth starts or ends but has no radio there: a
    beacon in range of that spot is not delivered to it (counted ``off_air``), and is once the
    vehicle is on the air."""
    import dataclasses

    from slcp.hw_emulation.playback import Radio

    truth = build_truth(load_scenario("paper-1"))
    late, gone = "V1", "V2"
    t = truth.vehicles[late].truth.t
    vehicles = dict(truth.vehicles)
    vehicles[late] = dataclasses.replace(vehicles[late], present=t >= 20.0)
    vehicles[gone] = dataclasses.replace(vehicles[gone], present=t < 30.0)
    radio = Radio(dataclasses.replace(truth, vehicles=vehicles), seed=0)
    radio.model = dataclasses.replace(radio.model, loss=0.0, ge_p_good_to_bad=0.0, stale_prob=0.0, max_range=1e6)
    for now, receivers in ((10.0, ["V2"]), (25.0, ["V1", "V2"]), (35.0, ["V1"])):
        radio._pending.clear()
        off = radio.stats.off_air
        b = Beacon("V0", 1, "SL-CP", now, np.array([0.7, 2.0, 50.0]), np.zeros(3), np.eye(3))
        radio.send(b, b, now)
        assert [p[1] for p in radio._pending] == receivers, now
        assert radio.stats.off_air - off == 2 - len(receivers)
    assert Radio(truth, seed=0).on_air(10.0) is None  # every vehicle always on the air: no check


def test_the_radio_counts_per_link_what_it_delivers_and_what_a_late_delivery_lets_overtake() -> None:
    """The radio's per-link account (the emulator's diagnostics publish it): every delivery
    counts on its (transmitter, receiver) link, and one that reaches the receiver after a newer
    beacon of the same transmitter and method is out of order (a receiver refuses it as old)."""
    import dataclasses

    from slcp.hw_emulation.playback import Radio

    truth = build_truth(load_scenario("paper-1"))
    radio = Radio(truth, seed=0)
    now = 5.0
    late = dataclasses.replace(radio.model, loss=0.0, ge_p_good_to_bad=0.0, stale_prob=1.0, stale_min=0.3,
                               stale_max=0.3, max_range=1e6)
    radio.model = late
    llh = truth.vehicles["V0"].truth.llh[0]
    first = Beacon("V0", 1, "SL-CP", now, llh, np.zeros(3), np.eye(3))
    radio.send(first, first, now)  # delivered at now + 0.3
    radio.model = dataclasses.replace(late, stale_prob=0.0)
    for seq, (t, method) in enumerate([(now + 0.2, "SL-CP"), (now + 0.2, "CP")], start=2):
        b = Beacon("V0", seq, method, t, llh, np.zeros(3), np.eye(3))
        radio.send(b, b, t)
    got = radio.due(now + 1.0)
    assert [p[0] for p in got] == sorted(p[0] for p in got) and len(got) == 3 * 2  # to V1 and V2
    assert radio.links == {("V0", "V1"): [3, 1], ("V0", "V2"): [3, 1]}
    assert radio.stats.delivered == 6


def test_the_radio_drops_future_dated_beacons_instead_of_keeping_them() -> None:
    """#39 finding 3: 20,000 beacons dated t = 1e9 stayed in the radio for ever and were scanned
    at every event. A beacon stamped more than MAX_AHEAD past the radio's clock is counted and
    dropped; nothing stays pending."""
    from slcp.hw_emulation.playback import MAX_AHEAD, Radio

    truth = build_truth(load_scenario("paper-1"))
    radio = Radio(truth, seed=0)
    llh = truth.vehicles[radio.ids[0]].truth.llh[0]
    for k in range(20_000):
        b = Beacon(radio.ids[0], k, "SL-CP", 1e9, llh, np.zeros(3), np.eye(3))
        radio.send(b, b, 5.0)
    assert radio.stats.future_dated == 20_000 and radio.stats.sent == 0 and not radio._pending
    ok = Beacon(radio.ids[0], 1, "SL-CP", 5.0 + MAX_AHEAD / 2, llh, np.zeros(3), np.eye(3))
    radio.send(ok, ok, 5.0)
    assert radio.stats.sent == 1


def test_one_transmitter_gets_its_share_of_the_channel_and_no_more() -> None:
    """#39 finding 6: a station flooding the radio. Each transmitter may send max_tx_rate
    packets a second (a second's burst); the rest are counted as channel_busy, and the other
    stations are not affected."""
    from slcp.hw_emulation.playback import Radio

    truth = build_truth(load_scenario("paper-1"))
    radio = Radio(truth, seed=0)
    a, b = radio.ids[0], radio.ids[1]
    rate = radio.model.max_tx_rate
    llh = truth.vehicles[a].truth.llh[0]
    for k in range(10_000):  # 10,000 beacons in 1 s, all keyed as a's transmissions
        now = 5.0 + k * 1e-4
        x = Beacon(a, k, "SL-CP", now, llh, np.zeros(3), np.eye(3))
        radio.send(x, x, now, transmitter=a)
        if k % 500 == 0:  # b at 20 a second
            y = Beacon(b, k, "SL-CP", now, llh, np.zeros(3), np.eye(3))
            radio.send(y, y, now, transmitter=b)
    assert radio.stats.sent == pytest.approx(rate + rate * 1.0 + 20, abs=2)
    assert radio.stats.channel_busy == 10_020 - radio.stats.sent
    x = Beacon(a, 1, "SL-CP", 6.0, llh, np.zeros(3), np.eye(3))
    radio.send(x, x, 6.0, transmitter="stranger")  # not a station of the scenario
    assert radio.stats.codec_errors == 1


@pytest.mark.timeout(300)
def test_agent_paced_play_with_longer_imu_batches_does_not_wait_for_itself() -> None:
    """With 0.2 s IMU messages (imu_batch 20) an agent reports up to 0.2 s + its hold behind the
    clock: the agent-paced clock leads by that much more, so the run neither stalls nor drops
    sensor data, and every agent reports throughout."""
    import dataclasses

    scn = dataclasses.replace(load_scenario("paper-1"), imu_batch=20, duration=25.0)  # the clock, not the drive
    truth = build_truth(scn)

    async def main():
        net = InMemoryNetwork()
        stop = asyncio.Event()
        agents = [Agent(agent_config(scn, vid, ("SP", "SL-SP")), net.bus()) for vid in sorted(truth.vehicles)]
        emu = EmulatorService(truth, net.bus(), seed=0)
        tasks = [asyncio.create_task(a.run(stop)) for a in agents]
        await asyncio.sleep(0)
        await emu.run()
        stop.set()
        await asyncio.gather(*tasks)
        return agents, emu

    agents, emu = asyncio.run(main())
    assert emu.batch == 20 and emu._lead == pytest.approx(0.8) and not emu.stalled
    for a in agents:
        assert a.counters["imu_batches"] == pytest.approx(scn.duration * scn.imu_rate / 20, abs=2)
        assert a.counters.get("seq_late_dropped", 0) == 0 and all(d == 0 for d in a.dropped.values())
        assert a.counters["estimates_tx"] > 0.9 * scn.duration * a.cfg.estimate_rate * 2
