"""Transport: codec round trips (property-based) and malformed input, keys, the in-memory bus,
and two Zenoh peers on loopback."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slcp.transport import keys
from slcp.transport.bus import InMemoryNetwork, Subscription, Waker, drain_in_arrival_order
from slcp.transport.codec import SCHEMA_VERSION, CodecError, decode, encode
from slcp.transport.messages import Beacon, Diagnostics, Estimate, GnssFix, ImuBatch, LaneMarkings, UwbRange, UwbRound

from conftest import free_port

names = st.from_regex(r"[A-Za-z0-9_.\-]{1,20}", fullmatch=True)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64, min_value=-1e12, max_value=1e12)
seqs = st.integers(min_value=0, max_value=2**63 - 1)


def arr(shape):
    return st.lists(finite, min_size=int(np.prod(shape)), max_size=int(np.prod(shape))).map(
        lambda v: np.array(v, float).reshape(shape))


@st.composite
def imu_batches(draw):
    n = draw(st.integers(1, 20))
    return ImuBatch(draw(names), draw(seqs), draw(arr((n,))), draw(arr((n,))), draw(arr((n, 3))), draw(arr((n, 3))))


@st.composite
def uwb_rounds(draw):
    peers = draw(st.lists(names, min_size=1, max_size=12))
    return UwbRound(draw(names), draw(seqs), draw(finite), tuple(peers), draw(arr((len(peers),))))


messages = st.one_of(
    imu_batches(),
    uwb_rounds(),
    st.builds(GnssFix, names, seqs, finite, arr((3,)), arr((3,)), arr((3,)), finite, st.integers(0, 9)),
    st.builds(UwbRange, names, names, seqs, finite, finite),
    st.builds(LaneMarkings, names, seqs, finite, st.integers(0, 2), st.integers(0, 2)),
    st.builds(Beacon, names, seqs, names, finite, arr((3,)), arr((3,)), arr((3, 3)), st.binary(max_size=100),
              st.booleans(), st.lists(st.tuples(st.lists(names, min_size=1, max_size=3).map(tuple),
                                                 st.just(np.diag([0.5, 0.25, 2.0]))), max_size=4).map(tuple),
              st.lists(st.tuples(names, arr((3,))), max_size=4).map(tuple)),
    st.builds(Estimate, names, names, finite, arr((3,)), arr((3,)), arr((3,)), arr((3, 3)), st.booleans()),
    st.builds(Diagnostics, names, finite, st.dictionaries(names, st.integers(0, 2**40), max_size=5),
              st.dictionaries(names, st.one_of(st.integers(0, 100), names, finite), max_size=5)),
)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(messages)
def test_codec_round_trip(msg) -> None:
    assert decode(encode(msg)) == msg


def test_a_ranging_round_needs_one_range_per_peer() -> None:
    obj = msgpack.unpackb(encode(UwbRound("V1", 3, 2.0, ("V0", "V2"), np.array([5.0, 6.0]))))
    for change, match in [({"ranges": np.array([5.0]).tobytes()}, "2 peers but 1 ranges"),
                          ({"peers": []}, "list of 1-"), ({"peers": ["V0", 7]}, "string"),
                          ({"peers": "V0"}, "list of 1-")]:
        with pytest.raises(CodecError, match=match):
            decode(msgpack.packb(dict(obj, **change), use_bin_type=True))


def _beacon() -> Beacon:
    return Beacon("V1", 7, "SL-CP", 12.5, np.array([0.7, 2.0, 50.0]), np.zeros(3), np.eye(3))


def test_truncated_and_wrong_version_and_types() -> None:
    raw = encode(_beacon())
    for cut in range(0, len(raw), 7):
        with pytest.raises(CodecError):
            decode(raw[:cut])
    obj = msgpack.unpackb(raw)
    for change, match in [
        ({"v": SCHEMA_VERSION + 1}, "schema version"),
        ({"type": "teleport"}, "unknown message type"),
        ({"seq": -1}, "non-negative integer"),
        ({"t": float("nan")}, "finite"),
        ({"llh": np.array([np.nan, 0, 0]).tobytes()}, "beacon.llh: non-finite"),
        ({"v_ned": np.array([0, np.inf, 0]).tobytes()}, "beacon.v_ned: non-finite"),
        ({"cov_pos": np.r_[np.ones(8), np.nan].tobytes()}, "beacon.cov_pos: non-finite"),
        ({"cov_pos": np.zeros(4).tobytes()}, "expected 9 values"),
        ({"vehicle": "x" * 100}, "string"),
        ({"vehicle": 3}, "string"),
        ({"extra": 1}, "unknown fields"),
    ]:
        bad = dict(obj, **change)
        with pytest.raises(CodecError, match=match):
            decode(msgpack.packb(bad, use_bin_type=True))
    for sources, match in [
        (3, "list of at most"),
        ([[["V0"], np.eye(3).tobytes()]] * 65, "list of at most"),
        ([["V0", np.eye(3).tobytes()]], "labels must be a list"),
        ([[[], np.eye(3).tobytes()]], "labels must be a list"),
        ([[["V0"]]], r"\[labels, covariance\]"),
        ([[["V0"], np.eye(2).tobytes()]], "expected 9 values"),
        ([[["V0"], (-np.eye(3)).tobytes()]], "non-negative diagonal"),
        ([[["V0"], np.array([[1, 0.5, 0], [0, 1, 0], [0, 0, 1.0]]).tobytes()]], "symmetric"),
        ([[["V0"], np.full(9, np.inf).tobytes()]], "non-finite"),
        ([[[7], np.eye(3).tobytes()]], "string"),
        ([[["x" * 130], np.eye(3).tobytes()]], "string of 1-129"),
    ]:
        with pytest.raises(CodecError, match=match):
            decode(msgpack.packb(dict(obj, sources=sources), use_bin_type=True))
    for constants, match in [
        (3, "list of at most"),
        ([["V0~1", np.ones(3).tobytes()]] * 65, "list of at most"),
        ([["V0~1"]], r"\[name, sensitivity\]"),
        ([[7, np.ones(3).tobytes()]], "name must be a string"),
        ([["V0~1", np.ones(2).tobytes()]], "expected 3 values"),
        ([["V0~1", np.array([0.0, np.nan, 0.0]).tobytes()]], "non-finite"),
    ]:
        with pytest.raises(CodecError, match=match):
            decode(msgpack.packb(dict(obj, constants=constants), use_bin_type=True))
    del obj["llh"]
    with pytest.raises(CodecError, match="missing field 'llh'"):
        decode(msgpack.packb(obj, use_bin_type=True))
    with pytest.raises(CodecError, match="exceeds"):
        decode(b"\x00" * (300 * 1024))



def test_an_imu_batch_has_one_row_per_sample_in_every_field() -> None:
    """The leading dimension is shared within a message: a field with one row more or less
    than the others, an empty batch, or more than ``MAX_SAMPLES`` rows is refused by name."""
    from slcp.transport.codec import MAX_SAMPLES

    def batch(n: int) -> dict:
        t = np.arange(1, n + 1) * 0.01
        return msgpack.unpackb(encode(ImuBatch("V0", 1, t, np.full(n, 0.01), np.zeros((n, 3)), np.ones((n, 3)))))

    obj = batch(4)
    assert decode(msgpack.packb(obj, use_bin_type=True)).dvel.shape == (4, 3)
    for fname, rows in (("t", 5), ("dt", 3), ("dtheta", 3), ("dvel", 5)):
        width = 3 if fname in ("dtheta", "dvel") else 1
        bad = dict(obj, **{fname: np.zeros(rows * width).tobytes()})
        # the first field read sets the count; the first that differs is named
        with pytest.raises(CodecError, match=r"imu\.(t|dt|dtheta|dvel): [345] rows, other fields have [45]"):
            decode(msgpack.packb(bad, use_bin_type=True))
    with pytest.raises(CodecError, match="not a multiple of 3"):
        decode(msgpack.packb(dict(obj, dtheta=np.zeros(13).tobytes()), use_bin_type=True))
    empty = {k: (b"" if isinstance(v, bytes) else v) for k, v in obj.items()}
    with pytest.raises(CodecError, match="0 rows outside"):
        decode(msgpack.packb(empty, use_bin_type=True))
    assert len(decode(msgpack.packb(batch(MAX_SAMPLES), use_bin_type=True)).t) == MAX_SAMPLES
    with pytest.raises(CodecError, match=f"{MAX_SAMPLES + 1} rows outside"):
        decode(msgpack.packb(batch(MAX_SAMPLES + 1), use_bin_type=True))

def test_the_codec_limits_are_exact() -> None:
    """Each limit accepts its edge and refuses one past it, and each refusal names its field:
    sequence numbers below 2⁶³, an auth block of at most 1,024 bytes, constant names of
    1-129 characters; and a payload that is not bytes."""
    obj = msgpack.unpackb(encode(_beacon()))

    def dec(**change):
        return decode(msgpack.packb(dict(obj, **change), use_bin_type=True))

    assert dec(seq=2**63 - 1).seq == 2**63 - 1
    with pytest.raises(CodecError, match="beacon.seq"):
        dec(seq=2**63)
    assert len(dec(auth=bytes(1024)).auth) == 1024
    for bad in (bytes(1025), "text"):
        with pytest.raises(CodecError, match=r"beacon\.auth: must be bytes \(<= 1024\)"):
            dec(auth=bad)
    g = np.ones(3).tobytes()
    assert dec(constants=[["x" * 129, g]]).constants[0][0] == "x" * 129
    for name in ("x" * 130, ""):
        with pytest.raises(CodecError, match="a name must be a string of 1-129 characters"):
            dec(constants=[[name, g]])
    with pytest.raises(CodecError, match="payload is not bytes"):
        decode("not bytes")

def test_fuzzed_payloads_only_raise_codec_errors() -> None:
    """5,000 seeded random, mutated and truncated payloads: every one is rejected with CodecError
    (or, rarely, decodes to a valid message) and nothing else is raised."""
    rng = np.random.default_rng(11)
    good = [encode(_beacon()), encode(ImuBatch("V1", 1, np.ones(2), np.ones(2), np.ones((2, 3)), np.ones((2, 3))))]
    rejected = 0
    for i in range(5000):
        if i % 3 == 0:
            p = rng.bytes(int(rng.integers(0, 400)))
        else:
            b = bytearray(good[i % 2])
            for _ in range(int(rng.integers(1, 6))):
                b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
            p = bytes(b[: int(rng.integers(1, len(b) + 1))])
        try:
            decode(p)
        except CodecError:
            rejected += 1
    assert rejected > 4000


def test_keys() -> None:
    assert keys.imu("V1") == "slcp/v1/sensor/V1/imu"
    assert keys.matches("slcp/v1/sensor/*/imu", keys.imu("V7"))
    assert keys.matches("slcp/v1/**", keys.estimate("V1", "SL-CP"))
    assert not keys.matches("slcp/v1/sensor/*/imu", keys.gnss("V1"))
    assert keys.lane("V1") == "slcp/v1/sensor/V1/lane" and keys.matches("slcp/v1/sensor/V1/*", keys.lane("V1"))
    assert keys.matches("a/**/b", "a/b") and keys.matches("a/**/b", "a/x/y/b")
    for bad in ("", "a/b", "V*", "x" * 65, "sp ace"):
        with pytest.raises(ValueError):
            keys.check_name(bad)


def test_in_memory_bus_delivery_drops_and_liveliness() -> None:
    async def main():
        net = InMemoryNetwork()
        a, b = net.bus(), net.bus()
        sub = b.subscribe("slcp/v1/radio/rx/*", maxsize=4)
        events = []
        b.watch_alive("slcp/v1/alive/agent/*", lambda k, alive: events.append((k, alive)))
        a.declare_alive(keys.alive("agent", "V1"))
        for i in range(10):
            await a.publish(
                keys.radio_rx("V2"), encode(Beacon("V1", i, "SP", float(i), np.zeros(3), np.zeros(3), np.eye(3)))
            )
        await a.publish(keys.imu("V2"), b"not for this subscriber")
        got = []
        async for _, payload in sub:  # (a subscription is an async iterator too)
            got.append(decode(payload).seq)
            if len(got) == 4:
                break
        assert got == [6, 7, 8, 9] and sub.dropped == 6 and sub.received == 10
        await a.close()
        assert events == [("slcp/v1/alive/agent/V1", True), ("slcp/v1/alive/agent/V1", False)]

    asyncio.run(main())


def test_a_drain_is_one_instant_for_every_queue() -> None:
    """The transport's thread keeps queueing while the consumer takes the queues one after the
    other: a fix that arrives after the GNSS queue was taken, and the IMU batch after it, both
    wait for the next drain, so the batch is never handed over before the fix."""
    async def main():
        loop = asyncio.get_running_loop()
        gnss, imu = Subscription("g", 8, loop), Subscription("i", 8, loop)
        gnss.offer("g", b"g0")
        imu.offer("i", b"i0")
        take = gnss._take

        def take_then_more_arrive(before=None):
            out = take(before)
            gnss.offer("g", b"g1")  # arrives while the IMU queue is still to be taken
            imu.offer("i", b"i1")
            return out

        gnss._take = take_then_more_arrive
        subs = {"gnss": gnss, "imu": imu}
        assert [p for _, _, p in drain_in_arrival_order(subs)] == [b"g0", b"i0"]
        gnss._take = take
        assert [p for _, _, p in drain_in_arrival_order(subs)] == [b"g1", b"i1"]
        assert gnss.queued_bytes == imu.queued_bytes == 0 and len(gnss) == len(imu) == 0

    asyncio.run(main())


def test_non_waking_queues_are_drained_with_the_waking_one_in_arrival_order() -> None:
    async def main():
        net = InMemoryNetwork()
        pub, rx = net.bus(), net.bus()
        waker = Waker(asyncio.get_running_loop())
        subs = {"imu": rx.subscribe(keys.imu("V2"), 8, waker=waker),
                "beacon": rx.subscribe(keys.radio_rx("V2"), 8, wake=False, waker=waker)}
        await pub.publish(keys.radio_rx("V2"), b"b0")
        # a beacon alone does not wake the consumer
        with pytest.raises(asyncio.TimeoutError):
            await asyncio.wait_for(waker.wait(), 0.05)
        await pub.publish(keys.imu("V2"), b"i0")
        await pub.publish(keys.radio_rx("V2"), b"b1")
        await asyncio.wait_for(waker.wait(), 1.0)
        assert [(n, p) for n, _, p in drain_in_arrival_order(subs)] == [("beacon", b"b0"), ("imu", b"i0"),
                                                                        ("beacon", b"b1")]
        # a non-waking queue wakes its consumer once half full, before anything is dropped
        for i in range(4):
            await pub.publish(keys.radio_rx("V2"), b"b%d" % i)
        await asyncio.wait_for(waker.wait(), 1.0)
        assert len(subs["beacon"]) == 4 and subs["beacon"].dropped == 0

    asyncio.run(main())


def test_a_burst_from_another_thread_wakes_the_loop_once() -> None:
    import threading

    async def main():
        loop = asyncio.get_running_loop()
        sub = Subscription("k", 1000, loop)
        wakes = 0
        orig = loop.call_soon_threadsafe

        def counting(*a):
            nonlocal wakes
            wakes += 1
            return orig(*a)

        loop.call_soon_threadsafe = counting
        th = threading.Thread(target=lambda: [sub.offer("k", b"%d" % i, threadsafe=True) for i in range(200)])
        th.start()
        th.join()  # the loop is not running meanwhile: one wake-up is pending for the whole burst
        got = [await sub.get() for _ in range(200)]
        assert [p for _, p in got] == [b"%d" % i for i in range(200)]
        assert wakes == 1
        # once the consumer has waited again, the next offer wakes it again
        th = threading.Thread(target=lambda: sub.offer("k", b"x", threadsafe=True))
        task = asyncio.ensure_future(sub.get())
        await asyncio.sleep(0)
        th.start()
        th.join()
        assert (await asyncio.wait_for(task, 1.0)) == ("k", b"x") and wakes == 2

    asyncio.run(main())


@pytest.mark.fleet
@pytest.mark.timeout(60)
def test_two_zenoh_peers_on_loopback() -> None:
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    async def main():
        port = free_port()
        a = ZenohBus(ZenohConfig(listen=(f"tcp/127.0.0.1:{port}",)))
        b = ZenohBus(ZenohConfig(connect=(f"tcp/127.0.0.1:{port}",)))
        try:
            sub = b.subscribe("slcp/v1/radio/rx/**")
            alive = []
            b.watch_alive("slcp/v1/alive/**", lambda k, up: alive.append((k, up)))
            a.declare_alive(keys.alive("agent", "V1"))
            await asyncio.sleep(0.5)
            sent = [Beacon("V1", i, "SL-CP", 0.2 * i, np.array([0.7, 2.0, 50.0]), np.ones(3), np.eye(3) * i)
                    for i in range(20)]
            for m in sent:
                await a.publish(keys.radio_rx("V2"), encode(m))
            got = [decode((await asyncio.wait_for(sub.get(), 5.0))[1]) for _ in range(20)]
            assert got == sent
            deadline = asyncio.get_running_loop().time() + 5
            while not alive and asyncio.get_running_loop().time() < deadline:
                await asyncio.sleep(0.05)
            assert alive[0] == ("slcp/v1/alive/agent/V1", True)
            await a.close()
            deadline = asyncio.get_running_loop().time() + 5
            while len(alive) < 2 and asyncio.get_running_loop().time() < deadline:
                await asyncio.sleep(0.05)
            assert alive[-1] == ("slcp/v1/alive/agent/V1", False)
        finally:
            await a.close()
            await b.close()

    asyncio.run(main())


@pytest.mark.fleet
@pytest.mark.timeout(60)
def test_messages_on_several_keys_reach_their_queues_in_the_order_they_were_sent() -> None:
    """An agent hands its queues' messages to the engine in arrival order
    (:func:`transport.bus.drain_in_arrival_order`), and the engine's sensor timing relies on it:
    a GNSS fix published before the IMU batches that follow it must not be queued after them.
    20,000 messages on three keys from one client, through a router, to another client: every
    one arrives, in the order sent, with no thread per subscription. (With zenoh-python's
    default callbacks, each subscription's in a Python thread of its own, 450-580 were out of
    order here.)"""
    import struct

    from slcp.transport.bus import Waker, drain_in_arrival_order
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    n = 20_000

    def threads() -> int:
        return len(os.listdir("/proc/self/task"))

    async def main() -> None:
        ep = f"tcp/127.0.0.1:{free_port()}"
        router = ZenohBus(ZenohConfig(mode="router", listen=(ep,)))
        pub = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
        sub = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
        try:
            waker = Waker(asyncio.get_running_loop())
            before = threads()
            subs = {k: sub.subscribe(f"slcp/v1/test/{k}", n, wake=False, waker=waker) for k in "abc"}
            after = threads()
            await asyncio.sleep(0.5)  # the subscriptions reach the router
            for i in range(n):
                await pub.publish(f"slcp/v1/test/{'abc'[i % 3 if i % 7 else 0]}", struct.pack("<q", i))
                if i % 500 == 0:
                    await asyncio.sleep(0.001)
            deadline = asyncio.get_running_loop().time() + 20
            while sum(len(s) for s in subs.values()) < n and asyncio.get_running_loop().time() < deadline:
                await asyncio.sleep(0.1)
            got = [struct.unpack("<q", p)[0] for _, _, p in drain_in_arrival_order(subs)]
            assert got == list(range(n)), (len(got), sum(1 for a, b in zip(got, got[1:]) if b < a))
            assert after == before
        finally:
            await sub.close()
            await pub.close()
            await router.close()

    asyncio.run(main())


_RUNTIME_PROBE = """
import asyncio, json, os, sys
from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

async def main():
    ep = f"tcp/127.0.0.1:{sys.argv[1]}"
    router = ZenohBus(ZenohConfig(mode="router", listen=(ep,)))
    client = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
    sub = client.subscribe("slcp/v1/probe")
    await asyncio.sleep(0.3)
    await router.publish("slcp/v1/probe", b"x")
    got = (await asyncio.wait_for(sub.get(), 5.0))[1]
    names = sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task"))
    await client.close()
    await router.close()
    print(json.dumps({"got": got.decode(), "threads": names}))

asyncio.run(main())
"""


@pytest.mark.fleet
@pytest.mark.timeout(60)
def test_the_light_runtime_runs_zenoh_on_few_threads_and_a_bad_one_is_a_clear_error() -> None:
    """slcp run gives its agents LIGHT_CLIENT_RUNTIME (ZENOH_RUNTIME): a router and a client on
    loopback in one process still talk, with Zenoh's work on its application threads and one
    transmission thread; an invalid ZENOH_RUNTIME is a RuntimeError that names it, not a bare
    Rust panic."""
    import subprocess
    import sys

    from slcp.transport.zenoh_bus import LIGHT_CLIENT_RUNTIME

    def probe(runtime: str | None) -> subprocess.CompletedProcess:
        env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
        if runtime is not None:
            env["ZENOH_RUNTIME"] = runtime
        return subprocess.run([sys.executable, "-c", _RUNTIME_PROBE, str(free_port())], env=env,
                              capture_output=True, text=True, timeout=40)

    default, light = probe(None), probe(LIGHT_CLIENT_RUNTIME)
    assert default.returncode == 0 and light.returncode == 0, light.stderr[-2000:]
    d, li = json.loads(default.stdout), json.loads(light.stdout)
    assert d["got"] == li["got"] == "x"
    zenoh_threads = lambda names: [n for n in names if not n.startswith("python")]  # noqa: E731
    assert {n.split("-")[0] for n in zenoh_threads(d["threads"])} >= {"app", "acc", "net"}
    light_kinds = {n.split("-")[0] for n in zenoh_threads(li["threads"])}
    assert light_kinds == {"app", "tx"}  # transmission never waits behind a task of the one app worker
    assert len(zenoh_threads(li["threads"])) < len(zenoh_threads(d["threads"]))
    bad = probe("(bogus: 1)")
    assert bad.returncode != 0 and "RuntimeError: Zenoh could not start (is ZENOH_RUNTIME='(bogus: 1)'" in bad.stderr


_BURST_SUBSCRIBER = """
import asyncio, sys, time
from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

async def main():
    bus = ZenohBus(ZenohConfig(mode="client", connect=(sys.argv[1],)))
    sub = bus.subscribe("slcp/v1/test/burst", maxsize=10**6, wake=False)
    bus.declare_alive("slcp/v1/alive/test/burst")
    n, last, deadline = int(sys.argv[2]), -1, time.monotonic() + 40.0
    while len(sub) < n and time.monotonic() < deadline:
        await asyncio.sleep(1.0)
        if len(sub) == last and last > 0:
            break  # nothing more arrives
        last = len(sub)
    print(len(sub), flush=True)
    await bus.close()

asyncio.run(main())
"""


@pytest.mark.fleet
@pytest.mark.timeout(90)
def test_a_burst_through_the_router_to_a_client_loses_nothing() -> None:
    """20,000 messages of 2 kB published as fast as possible through a router to a client in
    another process all arrive (with Zenoh's default DROP congestion control about half were
    lost here): the transport never drops, only the emulated radio does."""
    import subprocess
    import sys

    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    n = 20_000

    async def main() -> int:
        ep = f"tcp/127.0.0.1:{free_port()}"
        router = ZenohBus(ZenohConfig(mode="router", listen=(ep,)))
        pub = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
        up = asyncio.Event()
        pub.watch_alive("slcp/v1/alive/test/**", lambda k, alive: alive and up.set())
        proc = subprocess.Popen([sys.executable, "-c", _BURST_SUBSCRIBER, ep, str(n)], stdout=subprocess.PIPE,
                                text=True)
        try:
            await asyncio.wait_for(up.wait(), 20.0)
            await asyncio.sleep(0.5)  # the subscription reaches the router with the token
            payload = bytes(range(256)) * 8
            for _ in range(n):
                await pub.publish("slcp/v1/test/burst", payload)
            out, _ = await asyncio.to_thread(proc.communicate, timeout=60)
            return int(out.strip())
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            await pub.close()
            await router.close()

    assert asyncio.run(main()) == n


def test_zenoh_peer_settings_and_a_bad_strategy() -> None:
    from slcp.transport.zenoh_bus import ZenohConfig

    got = json.loads(ZenohConfig().to_zenoh().get_json("scouting/gossip/autoconnect_strategy"))
    assert got == {"peer": {"to_router": "always", "to_peer": "greater-zid"}}
    with pytest.raises(ValueError, match="autoconnect_strategy"):
        ZenohConfig(autoconnect_strategy="sometimes").to_zenoh()


@pytest.mark.fleet
@pytest.mark.slow
@pytest.mark.timeout(120)
def test_zenoh_peers_recover_both_ways_after_a_freeze_about_a_lease_long(tmp_path) -> None:
    """Six peers behind a router on loopback (lease 2 s, as slcp's default); one is frozen
    (SIGSTOP) for 1.8 s, then 1.9 s, so the others may expire it before it can expire them. After
    each freeze every peer hears every peer again, both ways.

    This guards the recovery; it does not reproduce the split that Zenoh's default dialling can
    leave (eclipse-zenoh/zenoh#2806): in a separate script (six peers started at once, frozen
    3 s after the start for 1.6-2.5 s) that split happened in 4 of 15 runs with both peers of a
    pair dialling and in 0 of 14 with ``greater-zid``, but this test passed 3 times of 3 with
    ``SLCP_TEST_AUTOCONNECT=always`` (four freezes each)."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    from conftest import wait_for_port

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    helper = Path(__file__).with_name("_probe_peer.py")
    strategy = os.environ.get("SLCP_TEST_AUTOCONNECT", "greater-zid")
    names = ["A", "C", "D", "E", "F", "B"]  # B, started last, is frozen
    procs = [subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "router", "--listen", ep],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)]

    def heard(n: str, last: int = 2) -> list[set[str]]:
        p = tmp_path / f"{n}.jsonl"
        lines = p.read_text().splitlines()[-last:] if p.exists() else []
        return [set(json.loads(x)) for x in lines]

    def all_hear_all(timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if all(len(h) == 2 and all(s == set(names) for s in h) for h in map(heard, names)):
                return True
            time.sleep(0.25)
        return False

    try:
        wait_for_port(port)
        for n in names:
            procs.append(subprocess.Popen([sys.executable, str(helper), n, ep, "2000", strategy,
                                           str(tmp_path / f"{n}.jsonl")], start_new_session=True,
                                          stderr=subprocess.DEVNULL))
        assert all_hear_all(30.0), {n: heard(n) for n in names}
        frozen = procs[-1]
        for pause in (1.8, 1.9):
            os.kill(frozen.pid, signal.SIGSTOP)
            time.sleep(pause)
            assert "B" not in heard("A", 1)[0]  # the others noticed: B was silent
            os.kill(frozen.pid, signal.SIGCONT)
            assert all_hear_all(12.0), (pause, {n: heard(n, 1) for n in names})
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p.pid, signal.SIGCONT)
                p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def test_zenohs_own_warnings_reach_a_child_of_slcp_run_and_stay_quiet_elsewhere(tmp_path, monkeypatch) -> None:
    """The launcher's children log Zenoh's warnings (RUST_LOG=zenoh=warn unless set): a client
    whose router is not there says so in its log; a process without RUST_LOG shows only
    Zenoh's errors (the CLI's own one-line error stays the only message)."""
    import subprocess
    import sys

    from slcp.deploy.supervisor import _spawn

    probe = ("import asyncio, sys\n"
             "from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig\n"
             "async def main():\n"
             "    try:\n"
             "        ZenohBus(ZenohConfig(mode='client', connect=(sys.argv[1],)))\n"
             "    except ConnectionError:\n"
             "        print('refused')\n"
             "asyncio.run(main())\n")
    closed = f"tcp/127.0.0.1:{free_port()}"
    monkeypatch.delenv("RUST_LOG", raising=False)
    procs: dict = {}
    with open(tmp_path / "child.log", "w") as lf:
        _spawn(procs, "child", [sys.executable, "-c", probe, closed], lf).wait(timeout=30)
    child = (tmp_path / "child.log").read_text()
    assert "refused" in child and "WARN" in child and f"Unable to connect to {closed}" in child
    assert "\x1b[" not in child  # plain text in a log file
    quiet = subprocess.run([sys.executable, "-c", probe, closed], capture_output=True, text=True, timeout=30)
    assert quiet.stdout.strip() == "refused" and "WARN" not in quiet.stderr


def test_a_queue_is_bounded_in_bytes_and_refuses_oversized_payloads() -> None:
    """#39 finding 6: queues were bounded in messages only (100 payloads of 10 MB took a process
    to 668 MB). A payload over ``max_payload`` is counted and not queued; the queue drops its
    oldest items to stay within ``maxbytes``; the byte count follows every path out."""
    from slcp.transport.bus import Subscription

    async def main() -> None:
        sub = Subscription("k", 1000, asyncio.get_running_loop(), maxbytes=10_000, max_payload=4_000)
        sub.offer("k", b"x" * 4_001)
        assert sub.oversized == 1 and len(sub) == 0 and sub.queued_bytes == 0
        for k in range(10):
            sub.offer("k", bytes([k]) * 3_000)
        # 3 fit in 10,000 bytes: the 7 oldest were dropped, the newest 3 kept, in order
        assert sub.dropped == 7 and len(sub) == 3 and sub.queued_bytes == 9_000
        assert [p[0] for _, p in sub.drain()] == [7, 8, 9] and sub.queued_bytes == 0
        sub.offer("k", b"a" * 100)
        sub.offer("k", b"b" * 200)
        assert (await sub.get())[1] == b"a" * 100 and sub.queued_bytes == 200
        assert sub.received == 13
        with pytest.raises(ValueError):
            Subscription("k", 10, asyncio.get_running_loop(), maxbytes=100, max_payload=1000)

    asyncio.run(main())


def test_token_buckets_in_closed_form() -> None:
    from slcp.transport.rate_limit import TokenBuckets

    tb = TokenBuckets(rate=10.0, burst=5.0)
    assert sum(tb.take("a", 0.0) for _ in range(8)) == 5  # a full bucket: the burst, then nothing
    assert tb.take("b", 0.0)  # another key has its own
    assert not tb.take("a", 0.05) and tb.take("a", 0.1)  # 0.5 then 1 token back: one take
    assert sum(tb.take("a", 10.0) for _ in range(8)) == 5  # never more than the burst
    assert not tb.take("a", 9.0)  # a clock going back adds nothing
    with pytest.raises(ValueError):
        TokenBuckets(0.0, 1.0)


def test_arrays_of_any_number_type_and_numpy_scalars_travel_as_their_values() -> None:
    """A beacon built from integer arrays (a breakdown, constants, the covariance) and numpy
    scalars (time, sequence) decodes to the same values, as float64 and plain numbers."""
    b = Beacon("V1", np.int64(7), "SL-CP", np.float64(12.5), np.array([0.7, 2.0, 50.0]), np.zeros(3, int),
               np.eye(3, dtype=int) * 2, sources=((("V1",), np.eye(3, dtype=np.int32)), (("~common",), np.eye(3))),
               constants=(("V1~1.0", np.array([1, 0, 0])),))
    d = decode(encode(b))
    assert d.seq == 7 and d.t == 12.5 and type(d.t) is float and type(d.seq) is int
    np.testing.assert_array_equal(d.cov_pos, 2 * np.eye(3))
    np.testing.assert_array_equal(d.v_ned, np.zeros(3))
    assert [lab for lab, _ in d.sources] == [("V1",), ("~common",)]
    np.testing.assert_array_equal(d.sources[0][1], np.eye(3))
    np.testing.assert_array_equal(d.constants[0][1], [1.0, 0.0, 0.0])


@pytest.mark.fleet
@pytest.mark.timeout(60)
def test_a_session_closed_right_after_publishing_delivers_its_last_message() -> None:
    """Clients that publish a burst, then a last message, then close at once: every last message
    reaches a subscriber behind the router (closing the session without letting the queues
    drain lost 1 to 3 of the 16 here: a process's final diagnostics)."""
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    async def main() -> tuple[int, int]:
        ep = f"tcp/127.0.0.1:{free_port()}"
        router = ZenohBus(ZenohConfig(mode="router", listen=(ep,)))
        sub_bus = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
        sub = sub_bus.subscribe("slcp/v1/test/last", 1000)
        sent = 0
        try:
            for _ in range(2):
                pubs = [ZenohBus(ZenohConfig(mode="client", connect=(ep,))) for _ in range(8)]
                await asyncio.sleep(0.5)  # the subscriber's declaration reaches them

                async def burst_then_close(i: int, pub: ZenohBus) -> None:
                    for _ in range(50):
                        await pub.publish("slcp/v1/test/bulk", b"x" * 20_000)
                    await pub.publish("slcp/v1/test/last", str(i).encode())
                    await pub.close()

                await asyncio.gather(*(burst_then_close(i, p) for i, p in enumerate(pubs)))
                sent += len(pubs)
            await asyncio.sleep(0.5)
            return sent, len(sub.drain())
        finally:
            await sub_bus.close()
            await router.close()

    sent, got = asyncio.run(main())
    assert got == sent == 16


@pytest.mark.parametrize("where", ["in-memory", "peers", "router"])
def test_a_bus_learns_when_its_keys_have_subscribers(where) -> None:
    """``wait_subscribed`` says False while nobody subscribes to one of the keys, True once every
    key has a subscriber (by a wildcard too) and what is then published arrives: a log player
    waits on it, since Zenoh drops at the source what is published before (the first seconds of a
    drive played fast)."""
    from slcp.transport.zenoh_bus import ZenohBus, ZenohConfig

    async def main():
        closers = []
        if where == "in-memory":
            net = InMemoryNetwork()
            pub, sub_bus = net.bus(), net.bus()
        else:
            ep = f"tcp/127.0.0.1:{free_port()}"
            if where == "peers":
                pub = ZenohBus(ZenohConfig(listen=(ep,)))
                sub_bus = ZenohBus(ZenohConfig(connect=(ep,)))
            else:
                closers.append(ZenohBus(ZenohConfig(mode="router", listen=(ep,))))
                pub = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
                sub_bus = ZenohBus(ZenohConfig(mode="client", connect=(ep,)))
        closers += [pub, sub_bus]
        try:
            wanted = [keys.gnss("V3"), keys.imu("V3")]
            assert not await pub.wait_subscribed(wanted, 0.3)
            gnss = sub_bus.subscribe(keys.gnss("V3"))
            assert not await pub.wait_subscribed(wanted, 0.3)  # the IMU has nobody yet
            sub_bus.subscribe("slcp/v1/sensor/*/imu")
            assert await pub.wait_subscribed(wanted, 10.0)
            await pub.publish(keys.gnss("V3"), b"first")
            assert (await asyncio.wait_for(gnss.get(), 5.0))[1] == b"first"
        finally:
            for b in reversed(closers):
                await b.close()

    asyncio.run(main())
