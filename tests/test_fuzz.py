"""Fuzz: over 10,000 bad payloads on every topic of a running fleet (agents, the emulator's radio,
the recorder) on the in-memory bus. No task crashes, every malformed payload is counted by the
process that received it, the semantic ones (duplicates, old messages, time jumps) are counted
by kind, and the estimates stay finite and accurate."""

from __future__ import annotations

import asyncio
import collections
import json
import math

import numpy as np
import pytest

from slcp.agent.runtime import Agent
from slcp.deploy.agent_configs import agent_config
from slcp.deploy.recorder import Recorder
from slcp.geo import earth
from slcp.hw_emulation.fuzz import MALFORMED, SEMANTIC, malformed, time_jumped
from slcp.hw_emulation.scenario import load_scenario
from slcp.hw_emulation.service import EmulatorService
from slcp.hw_emulation.truth import build_truth
from slcp.transport import keys
from slcp.transport.bus import InMemoryNetwork
from slcp.transport.codec import CodecError, decode, encode

from conftest import short_scenario

N_PAYLOADS = 10_200
BURST = 24  #: payloads per 0.05 s of sensor time: all sent within 21.25 s


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_ten_thousand_bad_payloads_are_counted_and_nothing_breaks(tmp_path) -> None:
    scn = load_scenario(short_scenario(tmp_path, "paper-1", 25.0))
    truth = build_truth(scn)
    ids = sorted(truth.vehicles)
    rng = np.random.default_rng(20261122)
    agent_topics = {k: v for v in ids for k in (keys.imu(v), keys.gnss(v), keys.uwb(v), keys.radio_rx(v))}
    other_topics = {**{keys.radio_tx(v): "radio" for v in ids},
                    **{keys.estimate(v, "CP"): "recorder" for v in ids}, **{keys.diag(v): "recorder" for v in ids}}
    topics = sorted(agent_topics) + sorted(other_topics)
    expected_codec = collections.Counter()
    expected_oversized = collections.Counter()
    sent = collections.Counter()

    async def main():
        net = InMemoryNetwork()
        stop = asyncio.Event()
        agents = {v: Agent(agent_config(scn, v), net.bus()) for v in ids}
        rec = Recorder(tmp_path / "messages.jsonl")
        rec_bus = net.bus()
        rec_tasks = [asyncio.create_task(rec.run(rec_bus.subscribe(keys.ROOT + "/estimate/**", 1_000_000))),
                     asyncio.create_task(rec.run(rec_bus.subscribe(keys.ROOT + "/diag/**", 100_000)))]
        emu = EmulatorService(truth, net.bus(), seed=0)
        spy = net.bus().subscribe(keys.ROOT + "/**", 1_000_000)
        fuzz_bus = net.bus()
        mine: set[bytes] = set()
        latest: dict[str, list[tuple[float, bytes]]] = collections.defaultdict(list)

        def observe() -> None:
            for key, payload in spy.drain():
                if payload in mine:
                    continue
                m = decode(payload)
                t = float(np.max(m.t)) if hasattr(m, "t") else 0.0
                hist = latest[key]
                hist.append((t, payload))
                if len(hist) > 60:
                    del hist[0]

        async def fuzzer() -> None:
            while not all(a.filters for a in agents.values()):
                observe()
                await asyncio.sleep(0.005)
            next_t = emu.now
            n = 0
            while n < N_PAYLOADS:
                observe()
                if emu.now < next_t and not emu.done.is_set():
                    await asyncio.sleep(0.002)
                    continue
                next_t += 0.05
                for _ in range(BURST):
                    key = topics[int(rng.integers(len(topics)))]
                    kind, payload = _bad_payload(rng, key, latest.get(key), key in agent_topics)
                    if kind == "oversized":  # refused by size before the codec sees it
                        expected_oversized[agent_topics.get(key) or other_topics[key]] += 1
                    elif kind in MALFORMED:
                        expected_codec[agent_topics.get(key) or other_topics[key]] += 1
                    mine.add(payload)
                    sent[kind] += 1
                    await fuzz_bus.publish(key, payload)
                    n += 1
                await asyncio.sleep(0)

        tasks = [asyncio.create_task(a.run(stop)) for a in agents.values()]
        fz = asyncio.create_task(fuzzer())
        await emu.run()
        await fz
        await _drained(agents)
        stop.set()
        await asyncio.gather(*tasks)  # an exception in any agent task fails the test here
        for t in rec_tasks:
            t.cancel()
        rec.close()
        return agents, emu, rec

    agents, emu, rec = asyncio.run(main())
    assert sum(sent.values()) >= 10_000
    print(f"sent {sum(sent.values())} bad payloads: {dict(sent)}")
    # every malformed payload counted by its receiver
    for v, a in agents.items():
        assert a.counters["codec_errors"] == expected_codec[v], (v, a.counters["codec_errors"], expected_codec[v])
        assert sum(s.oversized for s in a._subs.values()) == expected_oversized[v] > 0
        assert all(d == 0 for d in a.dropped.values()), a.dropped
    assert emu.radio_stats.codec_errors == expected_codec["radio"]
    assert emu.radio_stats.oversized == expected_oversized["radio"] > 0
    assert rec.codec_errors == expected_codec["recorder"]
    assert rec.rejected["oversized"] == expected_oversized["recorder"] > 0
    _check_semantic_counts(agents)
    _check_estimates(tmp_path / "messages.jsonl", agents, truth)


def _bad_payload(rng, key: str, hist, semantic_ok: bool) -> tuple[str, bytes]:
    """One bad payload for ``key``: a duplicate, replayed or time-jumped copy of a message seen
    there (``semantic_ok``: a sensor or beacon topic with history), else a malformed one."""
    if semantic_ok and hist and rng.random() < 0.35:
        kind = SEMANTIC[int(rng.integers(len(SEMANTIC)))]
        if kind == "duplicate":
            return kind, hist[-1][1]
        if kind == "replayed_old":
            return kind, hist[0][1]
        return kind, encode(time_jumped(rng, decode(hist[-1][1])))
    kind = MALFORMED[int(rng.integers(len(MALFORMED)))]
    return kind, malformed(rng, decode(hist[-1][1]) if hist else _example(key), kind)


async def _drained(agents) -> None:
    """Let the agents drain their queues before stopping (the non-waking queues, beacons and
    measurements, are drained at the stop)."""
    for _ in range(500):
        if all(len(s) == 0 for a in agents.values() for s in a._subs.values() if s.wake):
            return
        await asyncio.sleep(0.01)


def _check_semantic_counts(agents) -> None:
    """The semantic bad payloads counted by kind."""
    total = collections.Counter()
    for a in agents.values():
        total.update(a.counters)
        total.update({f"seq_{k}": n for k, n in a.seq.counters.items()})
        for _m, tab in a.tables.items():
            total.update({f"table_{k}": n for k, n in tab.counters.items()})
    print({k: total[k] for k in sorted(total) if any(s in k for s in ("duplicate", "jump", "stale", "future",
                                                                       "out_of_order", "late"))})
    for k in ("duplicate_imu", "duplicate_gnss", "duplicate_uwb", "imu_time_jump", "gnss_time_jump",
              "uwb_time_jump", "seq_imu_out_of_order", "seq_late_dropped", "table_duplicate_or_old",
              "beacon_stale", "beacon_future"):
        assert total[k] > 0, k


def _check_estimates(path, agents, truth) -> None:
    """Estimates finite everywhere, and V1 still finds its stop line."""
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    est = [d for d in lines if d["type"] == "Estimate"]
    assert len(est) > 1000
    assert all(math.isfinite(x) for d in est for f in ("llh", "v_ned", "cov_pos") for x in np.ravel(d[f]))
    for a in agents.values():
        for f in a.filters.values():
            assert np.all(np.isfinite(f.filter.state.llh)) and np.all(np.isfinite(f.filter.P))
    vt = truth.vehicles["V1"].truth
    errs = []
    for d in est:
        if d["vehicle"] == "V1" and d["method"] == "SL-SP" and d["first_stopped"]:
            k = int(np.searchsorted(vt.t, d["t"] - 1e-9))
            errs.append(np.hypot(*earth.ned_offset(*d["llh"], *vt.llh[k])[:2]))
    assert errs and float(np.sqrt(np.mean(np.square(errs)))) < 0.6




def _example(key: str):
    """A valid message for a topic nothing has been seen on yet (to derive malformed ones from)."""
    from slcp.transport.messages import Beacon, Diagnostics, Estimate, GnssFix, ImuBatch, UwbRange

    z3 = np.zeros(3)
    llh = np.array([0.7, 2.0, 50.0])
    kind = key.split("/")[2]
    if kind == "sensor":
        if key.endswith("imu"):
            return ImuBatch("V1", 0, np.array([1.0]), np.array([0.01]), np.zeros((1, 3)), np.zeros((1, 3)))
        return GnssFix("V1", 0, 1.0, llh, z3, np.ones(3), 0.1)
    if kind == "uwb":
        return UwbRange("V0", "V1", 0, 1.0, 5.0)
    if kind == "radio":
        return Beacon("V1", 0, "CP", 1.0, llh, z3, np.eye(3))
    if kind == "estimate":
        return Estimate("V1", "CP", 1.0, llh, z3, z3, np.eye(3))
    return Diagnostics("V1", 1.0, {"n": 1}, {})


def test_malformed_payloads_never_decode() -> None:
    """Each malformed kind, derived from each message type, is refused by the codec."""
    rng = np.random.default_rng(7)
    from slcp.transport.messages import UwbRound

    examples = [_example(key) for key in (keys.imu("V1"), keys.gnss("V1"), keys.uwb("V1"), keys.radio_rx("V1"),
                                          keys.estimate("V1", "CP"), keys.diag("V1"))]
    examples.append(UwbRound("V1", 0, 1.0, ("V0",), np.array([5.0])))
    for example in examples:
        for kind in MALFORMED:
            for _ in range(30):
                with pytest.raises(CodecError):
                    decode(malformed(rng, example, kind))
