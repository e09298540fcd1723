"""Multi-host: the fleet across network namespaces created here. A hub namespace holds the
infrastructure (``slcp router`` with TLS + ACL, the emulator, the recorder) on a bridge; each
vehicle's agent runs in its own namespace, joined to the hub by a veth pair, and reaches the others
only through the router. Addresses are private to these namespaces (10.77.0.0/24); nothing touches
the host's own network. Skips with the reason where namespaces cannot be created."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from slcp.transport.security import create_fleet

from conftest import short_scenario

pytestmark = [pytest.mark.fleet, pytest.mark.slow]

HUB_IP = "10.77.0.1"


def _ip(*args: str, ns: str | None = None) -> None:
    cmd = ["ip", *(["-n", ns] if ns else []), *args]
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=10)


def _netns_unavailable() -> str | None:
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"slcp-probe-{uuid.uuid4().hex[:6]}"
    try:
        _ip("netns", "add", probe)
    except (OSError, subprocess.CalledProcessError) as exc:
        return f"cannot create a network namespace: {getattr(exc, 'stderr', '') or exc}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True, timeout=10)
    return None


class Namespaces:
    """A hub namespace with a bridge and one namespace per vehicle on a veth pair; removed on exit."""

    def __init__(self, vehicles: list[str]) -> None:
        tag = uuid.uuid4().hex[:6]
        self.hub = f"slcp-{tag}-hub"
        self.ns = {v: f"slcp-{tag}-{v.lower()}" for v in vehicles}
        self.ips = {v: f"10.77.0.{10 + i}" for i, v in enumerate(vehicles)}
        self.tag = tag

    def __enter__(self) -> Namespaces:
        try:
            _ip("netns", "add", self.hub)
            _ip("link", "set", "lo", "up", ns=self.hub)
            _ip("link", "add", "br0", "type", "bridge", ns=self.hub)
            _ip("addr", "add", f"{HUB_IP}/24", "dev", "br0", ns=self.hub)
            _ip("link", "set", "br0", "up", ns=self.hub)
            for i, (v, ns) in enumerate(self.ns.items()):
                _ip("netns", "add", ns)
                _ip("link", "set", "lo", "up", ns=ns)
                # create the pair inside the vehicle namespace, then move one end to the hub
                _ip("link", "add", "eth0", "type", "veth", "peer", "name", f"h{i}", ns=ns)
                _ip("link", "set", f"h{i}", "netns", self.hub, ns=ns)
                _ip("addr", "add", f"{self.ips[v]}/24", "dev", "eth0", ns=ns)
                _ip("link", "set", "eth0", "up", ns=ns)
                _ip("link", "set", f"h{i}", "master", "br0", ns=self.hub)
                _ip("link", "set", f"h{i}", "up", ns=self.hub)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        for ns in [*self.ns.values(), self.hub]:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


class Procs:
    """Processes started in namespaces, each in its own session; all stopped on exit."""

    def __init__(self) -> None:
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, ns: str, args: list[str], log: Path) -> subprocess.Popen:
        with open(log, "w") as fh:
            p = subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "slcp.deploy.cli", "-v", *args],
                                 stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[name] = p
        return p

    def stop(self, name: str, timeout: float = 15.0) -> int:
        p = self.procs[name]
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
            try:
                p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        return p.returncode

    def __enter__(self) -> Procs:
        return self

    def __exit__(self, *exc) -> None:
        for name in list(self.procs):
            self.stop(name, timeout=5.0)


def wait_listening(ns: str, port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        out = subprocess.run(["ip", "netns", "exec", ns, "ss", "-ltn"], capture_output=True, text=True).stdout
        if f"{HUB_IP}:{port}" in out:
            return
        time.sleep(0.1)
    raise TimeoutError(f"router not listening on {HUB_IP}:{port} in {ns}")


@pytest.mark.timeout(240)
def test_the_fleet_works_across_network_namespaces_through_the_router(tmp_path) -> None:
    reason = _netns_unavailable()
    if reason:
        pytest.skip(reason)
    vehicles = ["V0", "V1", "V2"]
    fleet = tmp_path / "fleet"
    create_fleet(fleet, vehicles, router_hosts=(HUB_IP,))
    port = 7447
    ep = f"tls/{HUB_IP}:{port}"
    rec = tmp_path / "messages.jsonl"
    scn = short_scenario(tmp_path, "paper-1", 25.0)  # V1 first at its stop line from about 18 s
    with Namespaces(vehicles) as net, Procs() as procs:
        procs.start("router", net.hub, ["router", "--fleet", str(fleet), "--listen", ep], tmp_path / "router.log")
        wait_listening(net.hub, port)
        procs.start("recorder", net.hub, ["record", "--fleet", str(fleet), "--connect", ep, "--out", str(rec)],
                    tmp_path / "recorder.log")
        for v in vehicles:
            cfg = tmp_path / f"agent-{v}.toml"
            cfg.write_text(f'[agent]\nvehicle = "{v}"\nscenario = "{scn}"\n\n[security]\ntrust_dir = "{fleet}"\n\n'
                           f'[zenoh]\nmode = "client"\nconnect = ["{ep}"]\ntls = true\n')
            procs.start(f"agent-{v}", net.ns[v], ["agent", "--config", str(cfg)], tmp_path / f"agent-{v}.log")
        emu = procs.start("emulator", net.hub, ["emulate", str(scn), "--fleet", str(fleet), "--connect", ep],
                          tmp_path / "emulator.log")
        try:
            assert emu.wait(timeout=180) == 0, (tmp_path / "emulator.log").read_text()[-2000:]
        finally:
            time.sleep(1.0)  # the last estimates in flight
            codes = {v: procs.stop(f"agent-{v}") for v in vehicles}
            procs.stop("recorder")
        assert codes == {v: 0 for v in vehicles}, {
            v: (tmp_path / f"agent-{v}.log").read_text()[-1500:] for v in vehicles
        }
    lines = [json.loads(x) for x in rec.read_text().splitlines()]
    est = [d for d in lines if d["type"] == "Estimate"]
    diag = {d["source"]: d for d in lines if d["type"] == "Diagnostics"}
    assert {(d["vehicle"], d["method"]) for d in est} == {
        (v, m) for v in vehicles for m in ("SP", "SL-SP", "CP", "SL-CP")
    }
    for v in vehicles:
        c = diag[v]["counters"]
        # beacons crossed namespaces through the router and the radio, ranges were fused with them,
        # and every beacon verified (signed with the vehicle's key); an agent that starts after its
        # neighbours drops their first beacons, before its own clock runs, without checking them
        assert c["beacons_rx"] > 100 and c["CP_ranges"] > 0, c
        assert not any(k.startswith("beacon_") and k != "beacon_before_clock" and n for k, n in c.items()), {
            k: n for k, n in c.items() if k.startswith("beacon_")
        }
    print(
        {v: {k: diag[v]["counters"][k] for k in ("beacons_rx", "CP_ranges", "SL-CP_ranges")} for v in vehicles},
        len(est),
    )
    assert any(d["first_stopped"] for d in est if d["vehicle"] == "V1" and d["method"] == "SL-SP")
    assert not any(d["first_stopped"] for d in est if d["vehicle"] == "V2")
    left = subprocess.run(["pgrep", "-f", str(tmp_path)], capture_output=True, text=True).stdout.strip()
    assert left == ""
