"""The infrastructure router (``slcp router --fleet``) on loopback: mutual TLS with the fleet's
certificates and an ACL in which a vehicle publishes, subscribes and declares liveliness only under
its own keys; infrastructure (the emulator) may do everything under slcp/v1."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from slcp.transport import keys
from slcp.transport.security import create_fleet

from conftest import free_port, wait_for_port

pytestmark = pytest.mark.fleet


@pytest.fixture()
def router(tmp_path):
    fleet = tmp_path / "fleet"
    create_fleet(fleet, ["V1", "V2"])
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    p = subprocess.Popen([sys.executable, "-m", "slcp.deploy.cli", "router", "--fleet", str(fleet), "--listen", ep],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        wait_for_port(port)
        yield fleet, ep
    finally:
        os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


@pytest.mark.timeout(120)
def test_a_vehicle_can_only_speak_for_itself(router) -> None:
    from slcp.deploy.zenoh_security import client_config
    from slcp.transport.zenoh_bus import ZenohBus

    fleet, ep = router

    async def main():
        emu = ZenohBus(client_config(fleet, "emulator", (ep,)))
        v1 = ZenohBus(client_config(fleet, "V1", (ep,)))
        v2 = ZenohBus(client_config(fleet, "V2", (ep,)))
        try:
            tx = emu.subscribe(keys.ROOT + "/radio/tx/*")
            rx_v2 = v2.subscribe(keys.radio_rx("V2"))
            snoop = v1.subscribe(keys.radio_rx("V2"))  # V1 listening to what is delivered to V2
            seen: list[tuple[str, bool]] = []
            v2.watch_alive(keys.ROOT + "/alive/**", lambda k, up: seen.append((k, up)))
            v1.declare_alive(keys.alive("agent", "V1"))
            v1.declare_alive(keys.alive("agent", "V2"))  # impersonating V2's liveliness
            await asyncio.sleep(1.5)
            await v1.publish(keys.radio_tx("V1"), b"own")
            await v1.publish(keys.radio_tx("V2"), b"forged")
            await v1.publish(keys.gnss("V2"), b"forged sensor")
            await emu.publish(keys.radio_rx("V2"), b"delivered")
            await asyncio.sleep(1.5)
            return tx.drain(), rx_v2.drain(), snoop.drain(), seen
        finally:
            for b in (v1, v2, emu):
                await b.close()

    tx, rx_v2, snoop, seen = asyncio.run(main())
    assert tx == [(keys.radio_tx("V1"), b"own")]  # the forged beacon never reached the radio
    assert rx_v2 == [(keys.radio_rx("V2"), b"delivered")]
    assert snoop == []
    assert (keys.alive("agent", "V1"), True) in seen and not any(k.endswith("/V2") for k, _ in seen)


def test_the_router_configuration_is_printable_and_complete(router, tmp_path) -> None:
    fleet, ep = router
    out = subprocess.run([sys.executable, "-m", "slcp.deploy.cli", "router", "--fleet", str(fleet), "--listen", ep,
                          "--print-config"], capture_output=True, text=True, check=True).stdout
    cfg = json.loads(out)
    assert cfg["mode"] == "router" and cfg["listen"]["endpoints"] == [ep]
    tls = cfg["transport"]["link"]["tls"]
    assert tls["enable_mtls"] and Path(tls["root_ca_certificate"]).name == "ca.crt"
    acl = cfg["access_control"]
    assert acl["default_permission"] == "deny"
    assert {s["id"] for s in acl["subjects"]} == {"vehicle-V1", "vehicle-V2", "infrastructure"}
    bad = subprocess.run([sys.executable, "-m", "slcp.deploy.cli", "router", "--fleet", str(fleet), "--listen",
                          "tcp/127.0.0.1:7447", "--print-config"], capture_output=True, text=True)
    assert bad.returncode == 2 and "tls/<host>:<port>" in bad.stderr


@pytest.mark.timeout(120)
def test_a_sensor_driver_sees_its_agent_subscribe_through_the_secured_router(router) -> None:
    """`slcp sensors` plays a log once its vehicle's agent is up and subscribed to its topics
    (`wait_for_agent`: the agent's token, then Zenoh's matching status): both reach a vehicle's
    client through the ACL, so a secured fleet does not wait out the timeout."""
    from slcp.deploy.processes import wait_for_agent
    from slcp.deploy.zenoh_security import client_config
    from slcp.transport.zenoh_bus import ZenohBus

    fleet, ep = router

    async def main():
        sensors = ZenohBus(client_config(fleet, "V1", (ep,)))
        agent = ZenohBus(client_config(fleet, "V1", (ep,)))
        try:
            inputs = [keys.gnss("V1"), keys.imu("V1")]
            before = await wait_for_agent(sensors, "V1", inputs, 1.0)
            loop = asyncio.get_running_loop()
            agent.subscribe(keys.ROOT + "/sensor/V1/*")
            agent.declare_alive(keys.alive("agent", "V1"))
            t0 = loop.time()
            ok = await wait_for_agent(sensors, "V1", inputs, 20.0)
            return before, ok, loop.time() - t0
        finally:
            for b in (sensors, agent):
                await b.close()

    before, ok, took = asyncio.run(main())
    assert not before and ok and took < 10.0
